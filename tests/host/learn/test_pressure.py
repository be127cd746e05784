"""Pressure from all vectors with untracked pins read as missing: the hard-plate
grouped CV figure on real data, the fill layer's behaviour on synthetic presses, and
ONNX parity through the Pi's Regressor."""
from __future__ import annotations

import numpy as np
import pytest

from device.pi.models.regressor import Regressor
from device.pi.models.window import RollingWindow
from host.learn.pressure import (bootstrap_mae, cross_validate_pressure, export_pressure,
                                 hard_plate, pressure_pipeline, tracked_class)
from host.learn.tasks import TrainError


def presses(n_trials=40, M=24, lost_share=0.1, seed=0):
    """Synthetic presses: each pin moves gain[m] * depth (px) along its own direction;
    the load is 1000 * depth; ``lost_share`` of the pins are untracked (0, 0)."""
    rng = np.random.default_rng(seed)
    ang = rng.uniform(0, 2 * np.pi, M)
    gain = rng.uniform(0.5, 2.0, M)
    depth = np.tile(np.linspace(0.5, 4.0, 5), n_trials) + rng.normal(0, 0.05, 5 * n_trials)
    v = (gain * depth[:, None])[..., None] * np.stack([np.cos(ang), np.sin(ang)], -1)
    v = v + rng.normal(0, 0.05, v.shape)
    v[rng.random(v.shape[:2]) < lost_share] = 0.0
    return (v.reshape(len(v), -1).astype(np.float32), 1000.0 * depth,
            np.repeat(np.arange(n_trials), 5), M)


def drop(X, M, share, seed=1):
    """X with a further ``share`` of the pins untracked."""
    v = X.reshape(len(X), M, 2).copy()
    v[np.random.default_rng(seed).random(v.shape[:2]) < share] = 0.0
    return v.reshape(len(X), -1)


def test_untracked_pins_are_filled_not_read_as_zero():
    X, y, g, M = presses()
    Xd = drop(X, M, 0.4)                 # a new recording that loses 40 % more pins
    ours = pressure_pipeline("ridge", 1, M, alpha=1.0).fit(X, y)
    raw = pressure_pipeline("ridge150-raw", 1, M).fit(X, y)
    err_ours = np.abs(ours.predict(Xd) - y).mean()
    err_raw = np.abs(raw.predict(Xd) - y).mean()
    # zeros read as "did not move" pull the raw model's load down by hundreds
    assert err_raw > 300, err_raw
    assert err_ours < 0.25 * err_raw, (err_ours, err_raw)


def test_fill_layer_keeps_tracked_pins_and_appends_share_and_mean():
    X, y, g, M = presses()
    tp = tracked_class()(1, M).fit(X)
    x = X[:3].copy()
    x[0, :4] = 0.0                        # pins 0 and 1 untracked
    out = tp.transform(x)
    assert out.shape == (3, 2 * M + 2)
    tracked = (np.hypot(x[0, 0::2], x[0, 1::2]) > 0)
    keep = np.repeat(tracked, 2)
    np.testing.assert_array_equal(out[0, :2 * M][keep], x[0][keep])   # tracked pins kept
    assert np.all(np.hypot(out[0, 0:2 * M:2], out[0, 1:2 * M:2])[~tracked] > 0.1)  # filled
    assert out[0, 2 * M] == pytest.approx(tracked.mean())
    assert out[0, 2 * M + 1] == pytest.approx(np.hypot(x[0, 0::2], x[0, 1::2])[tracked].mean(),
                                              rel=1e-5)


@pytest.mark.parametrize("kind", ["gbt", "ridge"])
def test_onnx_through_the_regressor_matches_sklearn(tmp_path, kind):
    X, y, g, M = presses(n_trials=16, M=12)
    out, pipe, parity = export_pressure(X, y, g, tmp_path / kind, kind=kind)
    reg = Regressor.load(out)
    assert reg.n_features == 2 * M and reg.input_layout == "vectors" and reg.T == 1
    Xd = drop(X[:20], M, 0.5)
    for x in np.concatenate([X[:20], Xd]):
        assert reg.predict_one(x) == pytest.approx(float(pipe.predict(x[None])[0]), abs=0.1)
    # the runtime's path: a RollingWindow of the frame's (M, 2) vectors, lost pins 0
    w = RollingWindow(1, M)
    w.push(vectors=Xd[0].reshape(M, 2))
    assert reg.predict_window(w) == pytest.approx(float(pipe.predict(w.encode("vectors"))[0]),
                                                  abs=0.1)
    assert parity["of_range"] < 1e-4
    # the folder says what it is: a model card written from its spec
    card = (out / "README.md").read_text()
    assert "contact pressure" in card and "profile `roboskin`" in card


def test_bootstrap_interval_brackets_the_mae_and_cv_errors_are_clear():
    err = np.abs(np.random.default_rng(0).normal(0, 10, 100))
    groups = np.repeat(np.arange(20), 5)
    lo, hi = bootstrap_mae(err, groups)
    assert lo < err.mean() < hi
    with pytest.raises(TrainError, match="at least 5 groups"):
        cross_validate_pressure(np.zeros((8, 4)), np.arange(8.0), np.repeat(np.arange(4), 2),
                                kind="ridge", k=5)
    with pytest.raises(TrainError, match="kind must be one of"):
        pressure_pipeline("forest", 1, 2)


def test_hard_plate_grouped_cv_mae_at_most_180_and_beats_the_raw_ridge():
    from tests.realdata import real_data_dir
    root = real_data_dir("roboskin/vectors2.npy", "roboskin/pressures2.npy") / "roboskin"
    X, y, g, M = hard_plate(root / "vectors2.npy", root / "pressures2.npy")
    assert M == 146 and X.shape == (500, 292)
    res = cross_validate_pressure(X, y, g, kind="gbt", k=5)
    base = cross_validate_pressure(X, y, g, kind="ridge150-raw", k=5)
    assert res["mae"] <= 180 and res["mae_ci95"][1] <= 180, res
    assert res["mae"] < base["mae"], (res, base)
    assert res["mae"] <= 0.1 * res["mae_predict_mean"]


def test_data_whose_marker_count_is_not_the_profiles_pin_count_is_refused_in_one_line():
    """133-marker windows with a 130-pin profile: one line naming both counts (the
    leg would refuse the model); the profile's own count passes."""
    from host.learn.pressure import check_pin_count
    from tests.windows import synthetic
    ws = synthetic(n_groups=2, per_group=4, n_pins=133, targets=True)
    check_pin_count(ws, "roboskin")
    with pytest.raises(TrainError) as exc:
        check_pin_count(ws, {"name": "mine", "n_pins": 130}, "plate.npz")
    msg = str(exc.value)
    assert "\n" not in msg and "plate.npz has 133 markers" in msg and "n_pins=130" in msg
