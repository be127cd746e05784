"""host/learn/sessions.py: training windows as another recording session gives them
(exposure at the frame level through the Pi's pipeline, a moved pin layout, lost
pins)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from host.data.load import load_spec
from host.data.windows import WindowSet
from host.learn.config import TrainConfig
from host.learn.sessions import (DEFAULT_SESSIONS, SessionDraw, augment_sessions, exposure,
                                 lose_pins, perturbed_layout, session_settings)
from host.learn.tasks import TrainError

#: no change at all: a copy must give back the recording's own windows
SAME = dict(DEFAULT_SESSIONS, copies=1, gain=[1, 1], gamma=[1, 1], offset=[0, 0],
            shift_px=0, scale=0, rotate_deg=0, lost=[0, 0])


@pytest.fixture(scope="module")
def sim_windows(tmp_path_factory):
    """Texture windows (T = 3) of two short simulated recordings, read through the
    Pi's pipeline from a manifest."""
    d = tmp_path_factory.mktemp("sessions")
    (d / "m.csv").write_text("path,label,start_frame,end_frame\n"
                             "sim://press-hard?seed=1,smooth,0,40\n"
                             "sim://press-soft?seed=2,rough,0,40\n")
    return load_spec(str(d / "m.csv"), "texture", 3, progress=False)


def test_settings_default_off_and_bad_values_are_one_line_naming_the_field():
    assert session_settings(None) is None
    assert session_settings(False) is False and session_settings("none") is False
    assert session_settings(True) == DEFAULT_SESSIONS
    assert session_settings({"copies": 0}) is False
    assert session_settings({"gain": (0.9, 1.1)})["gain"] == [0.9, 1.1]
    for bad, field in (({"gain": [1.2, 0.9]}, "sessions.gain"), ({"gamma": [0, 1]},
                       "sessions.gamma"), ({"lost": [0, 1.5]}, "sessions.lost"),
                       ({"copies": -1}, "sessions.copies"), ({"shift_px": "3"},
                       "sessions.shift_px"), ({"blur": 1}, "unknown"), ("yes", "sessions=")):
        with pytest.raises(TrainError, match=field) as e:
            session_settings(bad)
        assert "\n" not in str(e.value)
    with pytest.raises(TrainError, match="sessions.offset"):
        TrainConfig(task="texture", sessions={"offset": [20, -20]})
    cfg = TrainConfig(task="slip", sessions={"copies": 1})
    assert cfg.sessions["copies"] == 1 and cfg.replay()["sessions"]["copies"] == 1
    assert TrainConfig(task="texture").replay()["sessions"] is None
    back = TrainConfig.from_replay(dict(cfg.replay(), data=["x.csv"]), "train.toml")
    assert back.sessions == cfg.sessions
    with pytest.raises(TrainError, match="train.toml: sessions.gain"):
        TrainConfig.from_replay({"task": "texture", "data": ["x.csv"],
                                 "sessions": {"gain": [3, 2]}}, "train.toml")


def test_exposure_layout_and_lost_pins_do_what_they_say():
    img = np.array([[0, 100, 200, 255]], np.uint8)
    assert exposure(img) is img
    want = np.round(255 * np.clip((img * 0.8 + 10) / 255, 0, 1) ** 1.25).astype(np.uint8)
    assert np.array_equal(exposure(img, 0.8, 1.25, 10), want)
    lay = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0]])
    moved = perturbed_layout(lay, SessionDraw(dx=2.0, dy=-1.0, scale=1.1, rot_deg=90.0))
    assert np.allclose(moved.mean(axis=0), lay.mean(axis=0) + [2.0, -1.0])
    d = lambda p: np.hypot(*(p[1] - p[0]))  # noqa: E731
    assert math.isclose(d(moved), 11.0)                           # scaled
    assert np.allclose(moved[1] - moved[0], [0.0, 11.0])          # rotated 90 degrees
    rng = np.random.default_rng(0)
    v = np.ones((50, 4, 20, 2), np.float32)
    lost = np.zeros((50, 4, 20), bool)
    lose_pins(v, lost, (0.2, 0.3), rng)
    share = lost[:, 0].mean(axis=1)
    assert (lost == lost[:, :1]).all()                            # the whole window
    assert share.min() >= 0.15 and share.max() <= 0.35
    assert not v[lost].any() and v[~lost].all()


def test_a_copy_without_change_is_the_recording_again_and_exposure_acts_on_frames(
        sim_windows):
    """Re-extracting a recording through the pipeline with no change gives its windows
    back exactly (same trial, last frame, label); with the gain lowered the whole
    recording, rest frame too, is darker and the vectors change."""
    ws = sim_windows
    n = len(ws)
    out = augment_sessions(ws, SAME)
    rec = out.source["augmented_sessions"]
    assert rec["frame_level_trials"] == 2 and rec["lost_pins_only_trials"] == 0
    assert len(out) == 2 * n and rec["windows"] == n
    assert np.array_equal(out.vectors[n:], ws.vectors)
    assert np.array_equal(out.lost[n:], ws.lost)
    for k in ("t_index", "groups", "labels", "contact"):
        assert np.array_equal(getattr(out, k)[n:], getattr(ws, k))
    dark = augment_sessions(ws, dict(SAME, gain=[0.6, 0.6]))
    assert dark.session[n:, :, 0].mean() < 0.7 * ws.session[:, :, 0].mean()  # brightness
    assert not np.array_equal(dark.vectors[n:], ws.vectors)
    assert np.isfinite(dark.vectors).all()


def test_default_copies_vary_per_copy_and_lose_pins(sim_windows):
    ws = sim_windows
    n = len(ws)
    out = augment_sessions(ws, dict(DEFAULT_SESSIONS, lost=[0.2, 0.2]), seed=3)
    assert n < len(out) <= 3 * n
    new = out.subset(np.arange(n, len(out)))
    gone = new.lost.all(axis=1).mean(axis=1)                      # lost the whole window
    assert gone.min() >= 0.2 - 1.0 / ws.n_pins
    b = new.session[:, :, 0].mean(axis=1)
    assert len(np.unique(np.round(b, 3))) > 2                    # exposures differ
    again = augment_sessions(ws, dict(DEFAULT_SESSIONS, lost=[0.2, 0.2]), seed=3)
    assert np.array_equal(again.vectors, out.vectors)            # seeded


def test_windows_without_frames_get_lost_pin_copies_only():
    T, M, N = 3, 6, 10
    ws = WindowSet(task="texture", window=T, vectors=np.ones((N, T, M, 2), np.float32),
                   lost=np.zeros((N, T, M), bool), imu=None, grids=None, frames=None,
                   contact=np.ones(N, bool), labels=np.array(["a", "b"] * 5, object),
                   targets=None, groups=np.zeros(N, np.int64), t_index=np.arange(N) + T,
                   trial_len=np.full(N, N + T, np.int64))
    out = augment_sessions(ws, dict(DEFAULT_SESSIONS, lost=[0.5, 0.5]))
    assert out.source["augmented_sessions"]["lost_pins_only_trials"] == 2
    assert len(out) == 3 * N and out.lost[N:].all(axis=1).sum(axis=1).min() >= 2


def test_texture_training_fits_session_copies_by_default_and_records_them(sim_windows,
                                                                          tmp_path):
    from host.learn.train import train_model
    from device.pi.models.manifest import read_spec
    ws = sim_windows
    res = train_model("texture", "fnn", ws, ws, out_dir=tmp_path / "m", progress=False,
                      epochs=5, rates=(), identity=False)
    spec, _ = read_spec(tmp_path / "m")
    got = spec.training["sessions"]
    assert got["copies"] == DEFAULT_SESSIONS["copies"] and got["frame_level_trials"] == 4
    assert res["fit"] is not None and spec.training["fit_windows"] == len(ws) + got["windows"]
    from host.learn.card import card_text
    assert "2 session copies" in card_text(spec)
    from host.learn.train import split_run
    from host.learn.trainers import plan
    assert plan(split_run(TrainConfig(task="texture", sessions=False), ws, ws)).sessions is False
    assert plan(split_run(TrainConfig(task="texture", model="fnn"), ws, ws)).sessions
    with pytest.raises(TrainError, match="sessions"):
        plan(split_run(TrainConfig(task="texture", model="grid-fnn", sessions=True), ws, ws))
