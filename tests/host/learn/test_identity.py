"""host/learn/identity.py: the recording-identity check flags recordings a probe can
tell apart (on the model's inputs or on the session statistics), does not flag
recordings drawn from one distribution, and says why when it has no verdict."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from host.learn.identity import (N_BLOCKS, WARNING, identity_check, verdict_lines,
                                 warning_line)
from tests.realdata import real_data_dir
from tests.windows import synthetic


def _one_class_two_recordings(offset: float, seed: int = 0, per_group: int = 120):
    """120 windows each of two recordings of class 'a' (and of one of 'b'); the
    second recording's displacements shifted by ``offset`` px."""
    ws = synthetic(n_groups=3, per_group=per_group, classes=("a", "a", "b"), imu=False,
                   seed=seed)
    ws.recordings = np.array(["r0", "r1", "r2"], object)[ws.groups]
    ws.vectors[ws.groups == 1] += np.float32(offset)
    return ws


def test_two_recordings_that_differ_by_an_offset_are_flagged():
    res = identity_check(_one_class_two_recordings(1.0), "surface", "fnn")
    a = res["classes"]["a"]
    assert a["mode"] == "recordings" and a["recordings"] == ["r0", "r1"]
    assert a["balanced_accuracy_ci95"][0] > 0.5 + res["margin"] and a["flagged"]
    assert a["n_windows"] == 240                       # every window of each recording
    assert res["flagged"] and res["verdict"] == "flagged"
    assert res["warning"].startswith(WARNING)
    assert warning_line(res).startswith("recording-identity check: " + WARNING)
    assert res["classes"]["b"]["verdict"] == "no verdict"


def test_recordings_drawn_from_one_distribution_are_not_flagged():
    flagged = 0
    for seed in range(3):
        res = identity_check(_one_class_two_recordings(0.0, seed), "surface", "fnn", seed=seed)
        a = res["classes"]["a"]
        lo, hi = a["balanced_accuracy_ci95"]
        assert lo <= a["balanced_accuracy"] <= hi
        flagged += res["flagged"]
        assert (res["warning"] is None) == (not res["flagged"])
        assert warning_line(res) is None or res["flagged"]
    assert flagged == 0


def test_recordings_that_differ_only_in_their_session_statistics_are_flagged():
    """Same pin displacements; the second recording is darker (brightness and contrast
    per frame) and its frames come twice as far apart."""
    ws = _one_class_two_recordings(0.0)
    rng = np.random.default_rng(1)
    N, T = len(ws), ws.window
    ws.session = np.stack([rng.normal(120, 2, (N, T)), rng.normal(40, 1, (N, T)),
                           np.full((N, T), 1 / 120)], axis=-1).astype(np.float32)
    dark = ws.groups == 1
    ws.session[dark] *= np.float32([0.8, 0.8, 2.0])
    res = identity_check(ws, "surface", "fnn")
    assert res["classes"]["a"]["flagged"] and res["flagged"]
    ws.session[dark] /= np.float32([0.8, 0.8, 2.0])
    assert not identity_check(ws, "surface", "fnn")["flagged"]


def test_one_recording_per_class_is_no_verdict_and_says_what_would_settle_it():
    """The docs' flow: one recording a class. No pair of recordings of one class, so
    no verdict, in words; the session statistics are compared across the classes."""
    ws = synthetic(n_groups=2, per_group=120, classes=("a", "b"), imu=False)
    ws.recordings = np.array(["ra", "rb"], object)[ws.groups]
    N, T = len(ws), ws.window
    ws.session = np.ones((N, T, 3), np.float32)
    ws.session[ws.groups == 1, :, 0] = 2.0            # the b recording is brighter
    ws.session += np.random.default_rng(0).normal(0, 0.01, ws.session.shape).astype(np.float32)
    res = identity_check(ws, "texture", "fnn")
    assert res["verdict"] == "no verdict" and not res["flagged"] and res["warning"] is None
    for c in ("a", "b"):
        e = res["classes"][c]
        assert e["mode"] == "one recording" and e["verdict"] == "no verdict"
        assert f"record a second session of {c} to check" in e["settle"]
    across = res["across_classes"]
    assert across["told_apart"] and "second session" in across["note"]
    lines = verdict_lines(res)
    assert any(line.startswith("a (one recording): no verdict") for line in lines)
    assert any(line.startswith("across classes, session statistics alone") for line in lines)


def test_too_few_windows_are_inconclusive_and_say_how_many_are_needed():
    """Recordings that differ, but too short to cut into blocks: inconclusive, with
    the number of windows a recording needs, and not flagged."""
    ws = _one_class_two_recordings(1.0, per_group=12)
    res = identity_check(ws, "surface", "fnn")
    a = res["classes"]["a"]
    assert a["verdict"] == "inconclusive" and not a["flagged"] and not res["flagged"]
    assert "record longer" in a["settle"] and str(N_BLOCKS) in a["settle"]
    assert res["verdict"] == "inconclusive"


def test_a_rule_and_a_regressor_are_not_checked():
    ws = _one_class_two_recordings(1.0)
    assert "skipped" in identity_check(ws, "surface", "rule")
    assert verdict_lines(identity_check(ws, "surface", "rule"))[0].startswith("skipped")


# -- on a real clip: its halves as two recordings, one altered as a second session --

@pytest.fixture(scope="module")
def concrete():
    data = real_data_dir("roboskin/concrete.avi")
    from host.data.video import video_frames
    return video_frames(data / "roboskin" / "concrete.avi", gray=True)


def _halves(images, alter=None, split=0.5, T=15):
    """concrete.avi's windows, those before the split frame recording 'A' and those
    whose frames all follow it 'B'; ``alter(image, t_s, i) -> (image, t_s)`` changes
    the frames from the split on, before the pipeline sees them."""
    from host.data.extract import extract_features
    from host.data.windows import TrialPart, WindowSet, stack_parts, window_ends, window_labels
    h = int(len(images) * split)
    frames = []
    for i, im in enumerate(images):
        t = i / 120
        if alter is not None and i >= h:
            im, t = alter(im, t, i - h, h)
        frames.append(SimpleNamespace(image=im, t_s=t))
    clip = extract_features(frames, "roboskin", None, progress=False, fps=120.0)
    ends, _ = window_ends(clip.ready, 0, clip.n_frames, T, 1)
    contact = clip.contact[ends]
    labels = window_labels("texture", np.full(len(ends), "concrete", object), contact)
    part = TrialPart(clip, ends, labels, None, contact, None, 0, 0, clip.n_frames, "R")
    ws = WindowSet(task="texture", window=T, classes=[], source={},
                   **stack_parts([part], "texture", T, {0: {}}))
    ws.recordings = np.where(ws.frame_index < h, "A", "B").astype(object)
    return ws.subset((ws.frame_index < h) | (ws.frame_index - T + 1 >= h))


def test_a_clips_halves_with_nothing_altered_are_not_flagged(concrete):
    for split in (0.4, 0.6):
        res = identity_check(_halves(concrete, split=split), "texture", "fnn")
        assert res["classes"]["concrete"]["mode"] == "recordings"
        assert not res["flagged"], verdict_lines(res)


@pytest.mark.parametrize("alter", [
    lambda im, t, i, h: (np.clip(im * np.float32(0.8), 0, 255).astype(np.uint8), t),
    lambda im, t, i, h: (im, (h + 2 * i) / 120),
], ids=["exposure 0.8", "frame interval doubled"])
def test_a_clips_second_half_altered_as_a_second_session_is_flagged(concrete, alter):
    res = identity_check(_halves(concrete, alter), "texture", "fnn")
    e = res["classes"]["concrete"]
    assert e["flagged"] and e["balanced_accuracy_ci95"][0] > 0.7, verdict_lines(res)
    assert warning_line(res)
