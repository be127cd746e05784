"""Automatic labels of real clips (host/localiser/labels.py): the layout fit, the
per-frame label check, tracking through a clip, and the rejected frames of the
shared trained model (see conftest.py)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from device.pi.vision.extract import ROBOSKIN_PARAMS
from device.pi.vision.neighbours import layout_neighbours
from device.sim import Simulator, load_profile, parse_scene
from host.localiser.labels import (
    LabelChecks,
    check_labels,
    fit_layout,
    label_clip,
    read_clip,
)
from host.localiser.sim import random_scene_doc
from tests.realdata import real_data_dir

# --------------------------------------------------------------------------
# Labels of real frames
# --------------------------------------------------------------------------


@pytest.mark.real
def test_corrupted_real_frames_rejected_and_listed(trained):
    if not trained["real"]:
        real_data_dir("roboskin/north.avi", "roboskin/east.avi")
    res = trained["res"]
    clip, half, rot = (trained["corrupt"][k] for k in ("clip", "half", "rot"))
    rejected = res["training"]["rejected"]
    mine = {r["frame"]: r["reason"] for r in rejected if r["clip"] == clip}
    assert half in mine and "too few pins matched" in mine[half]
    assert rot in mine
    # the frames around them are fine (the check is per frame, tracking recovers)
    for t in (half - 1, half + 2, rot - 1, rot + 2):
        assert t not in mine, (t, mine.get(t))
    lab = res["training"]["real_labelled"][clip]
    assert lab["rejected"] == len(mine) and lab["accepted"] == 60 - len(mine)
    # and the manifest lists the same
    m = json.loads((trained["dir"] / "manifest.json").read_text())
    listed = {(r["clip"], r["frame"]) for r in m["training"]["rejected"]}
    assert (clip, half) in listed and (clip, rot) in listed


def _sim_labels():
    sim = Simulator(parse_scene(random_scene_doc(np.random.default_rng(5))), seed=5)
    i = int(np.flatnonzero(sim.truth["contact"])[len(np.flatnonzero(sim.truth["contact"])) // 2])
    rest = sim.rest_pins_px.astype(np.float64)
    return sim.truth["pins_px"][i].astype(np.float64), rest


def test_check_labels_rejects_shuffled_and_missing():
    lab, rest = _sim_labels()
    nbr, _ = layout_neighbours(rest, 6)
    pitch = 11.7
    n = len(lab)
    ok = np.ones(n, bool)
    idx = np.arange(n)
    assert check_labels(lab, ok, idx, rest, nbr, pitch) is None
    rng = np.random.default_rng(0)
    # shuffled identities: 20 pins swap labels
    sel = rng.choice(n, 20, replace=False)
    bad = lab.copy()
    bad[sel] = lab[rng.permutation(sel)]
    reason = check_labels(bad, ok, idx, rest, nbr, pitch)
    assert reason is not None and "inconsistent" in reason
    # missing pins: 40 % unmatched
    m = ok.copy()
    m[rng.choice(n, int(0.4 * n), replace=False)] = False
    reason = check_labels(lab, m, idx, rest, nbr, pitch)
    assert reason is not None and "too few pins matched" in reason
    # one detection assigned to two pins
    d = idx.copy()
    d[3] = d[4]
    assert "duplicate" in check_labels(lab, ok, d, rest, nbr, pitch)
    # two labels on one spot
    c = lab.copy()
    c[10] = c[11]
    assert check_labels(c, ok, idx, rest, nbr, pitch) is not None


def test_fit_layout_recovers_a_similarity_transform():
    rest = load_profile("roboskin").pins_px.astype(np.float64)
    a = math.radians(2.0)
    R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    centre = rest.mean(0)
    moved = (1.03 * (R @ (rest - centre).T)).T + centre + (1.5, -2.0)
    det = moved[::-1].copy()                   # detections in another order
    fit = fit_layout(rest, det, gate_px=4.0)
    assert abs(fit["scale"] - 1.03) < 1e-6
    assert abs(fit["rotation_deg"] - 2.0) < 1e-6
    assert fit["residual_px"] < 1e-6
    np.testing.assert_allclose(fit["pins_px"], moved, atol=1e-6)
    np.testing.assert_array_equal(det[fit["idx"]], moved)


def test_label_clip_follows_simulated_pins():
    """A simulated drag labelled like a real clip: labels near the true pins."""
    sim = Simulator(parse_scene(random_scene_doc(np.random.default_rng(21))), seed=21)
    frames = [sim.render(i) for i in range(0, sim.n_frames, 2)]
    prof = load_profile("roboskin")
    lab = label_clip(frames, prof.pins_px, ROBOSKIN_PARAMS, clip="sim",
                     layout_dome=(*prof.dome_centre_px, prof.dome_radius_px))
    T, N = len(frames), prof.n_pins
    assert lab["labels_px"].shape == (T, N, 2) and lab["matched"].shape == (T, N)
    assert np.isfinite(lab["labels_px"]).all() and len(lab["binaries"]) == T
    assert lab["ok"].mean() >= 0.8, lab["rejected"][:5]
    assert len(lab["rejected"]) == int((~lab["ok"]).sum())
    truth = sim.truth["pins_px"][::2].astype(np.float64)
    ok = lab["ok"]
    err = np.hypot(*(lab["labels_px"][ok] - truth[ok]).transpose(2, 0, 1))
    m = lab["matched"][ok]
    assert np.median(err[m]) < 1.0


def test_label_clip_without_a_dome_rejects_every_frame():
    frames = [np.zeros((120, 160), np.uint8)] * 3
    lab = label_clip(frames, load_profile("roboskin").pins_px, ROBOSKIN_PARAMS, clip="dark")
    assert not lab["ok"].any() and lab["dome"] is None
    assert [r["frame"] for r in lab["rejected"]] == [0, 1, 2]
    assert all(r["reason"] == "no dome found in the clip" and r["clip"] == "dark"
               for r in lab["rejected"])


def test_label_clip_and_read_clip_name_bad_inputs(tmp_path):
    with pytest.raises(ValueError, match="clip='empty'"):
        label_clip([], load_profile("roboskin").pins_px, ROBOSKIN_PARAMS, clip="empty")
    missing = tmp_path / "none.avi"
    with pytest.raises(ValueError, match="none.avi"):
        read_clip(missing)


def test_label_checks_defaults_are_what_check_labels_uses():
    lab = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0]])
    nbr, _ = layout_neighbours(lab, 3)
    ok = np.ones(4, bool)
    strict = LabelChecks(min_matched_frac=1.0)
    ok[0] = False
    assert check_labels(lab, ok, np.arange(4), lab, nbr, 10.0) is None
    assert "too few pins matched" in check_labels(lab, ok, np.arange(4), lab, nbr, 10.0, strict)
