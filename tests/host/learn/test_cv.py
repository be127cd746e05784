"""Grouped cross-validation inside host train, and the default pressure model (gbt)
trained, cross-validated and run by the Pi's Regressor on synthetic presses."""
from __future__ import annotations

import json

import numpy as np
import pytest

from device.pi.models.regressor import Regressor
from device.pi.models.window import RollingWindow
from host.data.spec_npz import load_npz
from host.learn.config import TrainConfig
from host.learn.cv import CI_OVER_TRIALS, cross_validate_model
from host.learn.estimators import hyperparameters
from host.learn.tasks import DEFAULT_MODEL, LAYOUT, TASK_MODELS, TrainError
from host.learn.train import train_model


def press_npz(path, n_trials=20, T=3, M=10, lost_share=0.15, seed=0):
    """Synthetic presses as an .npz data spec: each pin moves gain[m] * depth along
    its own direction in every one of the window's T frames; the load is
    1000 * depth; ``lost_share`` of the pins are untracked, (0, 0)."""
    rng = np.random.default_rng(seed)
    ang = rng.uniform(0, 2 * np.pi, M)
    gain = rng.uniform(0.5, 2.0, M)
    depth = np.tile(np.linspace(0.5, 4.0, 5), n_trials) + rng.normal(0, 0.05, 5 * n_trials)
    v = ((gain * depth[:, None])[..., None] * np.stack([np.cos(ang), np.sin(ang)], -1))
    v = np.repeat(v[:, None], T, axis=1) + rng.normal(0, 0.05, (len(depth), T, M, 2))
    v[rng.random(v.shape[:3]) < lost_share] = 0.0
    np.savez(path, vectors=v.astype(np.float32), targets=1000.0 * depth,
             groups=np.repeat(np.arange(n_trials), 5))
    return path


def test_gbt_is_the_pressure_default_and_reads_vectors():
    assert DEFAULT_MODEL["pressure"] == "gbt" and "gbt" in TASK_MODELS["pressure"]
    assert LAYOUT["gbt"] == "vectors"
    with pytest.raises(TrainError, match="takes no"):
        hyperparameters("gbt", alpha=1.0, window=1, n_pins=4)
    with pytest.raises(TrainError, match="n_pins"):
        hyperparameters("gbt", window=1, n_pins=0)


def test_gbt_cv_interval_over_trials_and_the_runtime_runs_the_model(tmp_path):
    """T = 3 windows (the shipped pressure model's T): grouped CV reports the MAE
    with its 95 % interval over trials; the written model, loaded by the Pi's
    Regressor, gives sklearn's numbers on RollingWindow encodings, lost pins
    included."""
    T, M = 3, 10
    ws = load_npz(press_npz(tmp_path / "p.npz", T=T, M=M), "pressure", T, False, "roboskin")
    out = tmp_path / "model"
    res = train_model("pressure", DEFAULT_MODEL["pressure"], ws, cv=4, quantise=True,
                      seed=0, out_dir=out, progress=False)
    cv = res["metrics"]["cv"]
    assert res["model"] == "gbt" and cv["folds"] == 4 and cv["grouped"]
    lo, hi = cv["mae_ci95"]
    assert lo <= cv["mae"] <= hi and hi - lo > 0, cv
    assert cv["ci_method"] == CI_OVER_TRIALS and cv["trials"] == 15    # 25 % held out
    assert cv["mae"] < 0.2 * cv["mae_predict_mean"], cv
    assert res["metrics"]["test"]["mae"] < 0.2 * res["metrics"]["test"]["mae_predict_mean"]
    assert res["int8"]["skipped"] and res["default"] == "model.onnx"
    assert res["fit"]["onnx_parity"]["of_range"] < 1e-4
    man = json.loads((out / "manifest.json").read_text())
    assert man["model"] == "gbt" and man["T"] == T and man["input_layout"] == "vectors"

    reg = Regressor.load(out)
    assert reg.T == T and reg.n_features == T * M * 2
    z = np.load(tmp_path / "p.npz")
    for i in (0, 7, 33, 61):
        w = RollingWindow(T, M)
        for t in range(T):
            w.push(vectors=z["vectors"][i, t])
        got = reg.predict_window(w)
        assert not reg.fault
        assert got == pytest.approx(z["targets"][i], abs=0.25 * 1000), (i, got)


def test_cv_of_a_regressor_refuses_too_few_trials(tmp_path):
    ws = load_npz(press_npz(tmp_path / "p.npz", n_trials=3, T=1), "pressure", 1, False,
                  "roboskin")
    with pytest.raises(TrainError, match="cv=5"):
        cross_validate_model(TrainConfig("pressure", "gbt", cv=5), ws,
                             hyperparameters("gbt", window=1, n_pins=ws.n_pins), progress=False)
