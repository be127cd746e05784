"""host/learn/train.py (``host train``): training, ONNX export, int8 default,
manifests, the Pi's loaders reading what it writes, and hard cases."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import host.learn.trainers
from device.pi.models.artefact import FEATURE_SPEC_VERSION, sha256_file
from device.pi.models.classifier import Classifier
from device.pi.models.regressor import Regressor
from device.pi.models.rules import RuleClassifier
from device.pi.models.window import RollingWindow, encode_vectors
from host.learn.evaluate import evaluate_model
from host.learn.inputs import model_inputs
from host.learn.tasks import QuantisationError, TrainError
from host.learn.train import train_model
from tests.windows import synthetic

T = 3


# -- training on simulated steps -------------------------------------------------

def test_fnn_surface_held_out_on_unseen_seeds_and_int8_agrees(surface_model, surface_sets):
    res, out = surface_model
    ws_tr, ws_te = surface_sets
    assert res["classes"] == ["hard", "no-touch", "slippery", "soft"]
    assert res["uses_imu"] and res["input_layout"] == "vectors"
    test = res["metrics"]["test"]
    assert test["n"] == len(ws_te)
    # 12 training trials, 4 test trials with surfaces beyond the training range
    assert test["accuracy"] >= 0.9, test["confusion"]
    assert all(test["per_class"][c]["f1"] >= 0.75 for c in res["classes"]), test["per_class"]
    q = res["int8"]
    assert q["checked_on"] == "held-out windows" and q["n"] == len(ws_te)
    assert q["agreement"] >= 0.99 and q["passed"]
    assert 0.0 <= q["max_prob_diff"] < 1.0
    sat = q["saturation"]
    assert sat["calibration"]["tensors"] >= 3 and sat["calibration"]["share_outside"] == 0.0
    assert 0.0 <= sat["test"]["share_outside"] < 0.01
    assert q["int8_bytes"] < q["float_bytes"]


def test_manifest_lists_everything_and_the_pi_loads_both_variants(surface_model, surface_sets):
    res, out = surface_model
    ws_tr, ws_te = surface_sets
    doc = json.loads((out / "manifest.json").read_text())
    assert doc["kind"] == doc["task"] == "surface" and doc["model"] == "fnn"
    assert doc["classes"] == res["classes"] and doc["T"] == T
    assert doc["feature_spec"] == FEATURE_SPEC_VERSION
    assert doc["input_layout"] == "vectors" and doc["uses_imu"] is True
    assert doc["input"]["shape"] == [None, T * ws_tr.n_pins * 2 + T * 6]
    assert doc["onnx"] == "model.int8.onnx" and doc["variant"] == "int8"
    for name in ("model.onnx", "model.int8.onnx"):
        assert doc["sha256"][name] == sha256_file(out / name)
        assert doc["files"][name]["size_bytes"] == (out / name).stat().st_size
    assert doc["size_bytes"] == (out / "model.int8.onnx").stat().st_size
    assert doc["measured"]["int8"]["agreement"] >= 0.99
    assert doc["metrics"]["test"]["accuracy"] == res["metrics"]["test"]["accuracy"]
    from host.learn.onnx_io import training_record
    assert doc["training"]["data"] == training_record({"data": ws_tr.summary()})["data"]
    assert doc["training"]["test_data"]["T"] == ws_te.summary()["window"]
    assert set(doc["metrics"]) == {"train", "test", "cv"} and "window" not in doc
    assert doc["profile"]["name"] == "roboskin" and doc["measured"]["trained_on"]["split"] == res["holdout"]
    assert doc["training"]["seed"] == 0 and doc["training"]["hidden"] == [64, 32]
    fdoc = json.loads((out / "manifest.float.json").read_text())
    assert fdoc["onnx"] == "model.onnx" and fdoc["sha256"] == doc["sha256"]
    # the Pi's wrapper, both variants: same decisions as the training report
    X = model_inputs(ws_te, "vectors", True)
    for mpath, key in ((out, None), (out / "manifest.float.json", "float")):
        clf = Classifier.load(mpath)
        assert clf.classes == doc["classes"] and clf.uses_imu and clf.T == T
        ids = np.array([clf.predict(x)[0] for x in X])
        acc = float((np.array(clf.classes)[ids] == ws_te.labels.astype(str)).mean())
        want = (res["int8"]["metrics"]["accuracy"] if key is None
                else res["metrics"]["test"]["accuracy"])
        assert acc == pytest.approx(want, abs=2.0 / len(X))
    # and from a rolling window, as the runtime feeds it
    w = RollingWindow(T, ws_te.n_pins)
    for t in range(T):
        w.push(vectors=ws_te.vectors[5, t], imu=ws_te.imu[5, t])
    assert clf.predict_window(w)[0] == clf.predict(X[5])[0]


def test_rule_and_grid_fnn_train_export_and_load(surface_sets, tmp_path):
    ws_tr, ws_te = surface_sets
    res = train_model("surface", "rule", ws_tr, ws_te, quantise=True, out_dir=tmp_path / "rule",
                      progress=False)
    assert res["int8"] == {"skipped": "a rule has no weights to quantise"}
    rule = res["rule"]
    assert rule["contact_px"] > 0 and 0 < rule["soft_ratio"] < 1 and rule["wet_ratio"] > 0
    clf = Classifier.load(tmp_path / "rule")
    assert isinstance(clf, RuleClassifier)
    ev = evaluate_model(tmp_path / "rule", ws_te)
    assert ev["metrics"]["accuracy"] == pytest.approx(res["metrics"]["test"]["accuracy"])
    assert ev["metrics"]["accuracy"] > 0.5            # chance is ~0.3
    # the paper's first rule: the average vector gives the shear direction
    from device.pi.vision.features import average_vector, direction_deg

    i = int(np.argmax(np.abs(ws_te.vectors[:, -1]).sum(axis=(1, 2))))
    clf.predict(encode_vectors(ws_te.vectors[i]))
    q = np.round(ws_te.vectors[i, -1] / 0.25) * 0.25
    assert clf.last["direction_deg"] == pytest.approx(direction_deg(*average_vector(q)), abs=1e-6)
    assert clf.last["magnitude_px"] > rule["contact_px"]
    g = train_model("surface", "grid-fnn", ws_tr, ws_te, out_dir=tmp_path / "grid",
                    progress=False, hidden=(16, 8), epochs=80)
    doc = json.loads((tmp_path / "grid" / "manifest.json").read_text())
    assert doc["input_layout"] == "grids" and doc["uses_imu"] is False
    assert doc["input"]["shape"][1] == 2 * T * ws_tr.grids.shape[2] ** 2
    assert not (tmp_path / "grid" / "model.int8.onnx").exists()
    assert g["metrics"]["test"]["accuracy"] > 0.5


def test_ridge_pressure_int8_and_the_pi_regressor(tmp_path):
    ws = synthetic(targets=True, imu=False, n_groups=8)
    res = train_model("pressure", "ridge", ws, quantise=True, out_dir=tmp_path / "p",
                      progress=False, cv=4, alpha=1.0)
    test = res["metrics"]["test"]
    assert test["mae_of_range"] < 0.05
    assert res["metrics"]["cv"]["folds"] == 4 and len(res["metrics"]["cv"]["fold_mae"]) == 4
    q = res["int8"]
    assert q["kind"] == "regressor" and q["passed"] and "mae_change" in q
    reg = Regressor.load(tmp_path / "p", kind="pressure")
    X = model_inputs(ws, "vectors", False)
    y = np.array([reg.predict_one(x) for x in X[:20]])
    assert np.abs(y - ws.targets[:20]).mean() < 0.2 * (ws.targets.max() - ws.targets.min())
    bad = X[0].copy()
    bad[:3] = [np.nan, np.inf, -1e30]
    assert np.isfinite(reg.predict_one(bad))


# -- hard cases ----------------------------------------------------------------------

def test_zero_variance_features_and_extreme_inputs_stay_finite(tmp_path):
    ws = synthetic(seed=1)
    ws.vectors[:, :, 0, :] = 0.0                         # a pin that never moves
    ws.imu[:] = 0.0                                      # an IMU that reads nothing
    res = train_model("surface", "fnn", ws, out_dir=tmp_path / "m", progress=False,
                      hidden=(8, 4), epochs=40)
    assert res["metrics"]["test"]["accuracy"] > 0.9
    clf = Classifier.load(tmp_path / "m")
    D = clf.n_features
    for x in (np.full(D, np.nan), np.full(D, np.inf), np.full(D, -np.inf), np.full(D, 1e38),
              np.where(np.arange(D) % 2, 1e30, -1e30), np.zeros(D)):
        k, p = clf.predict(x)
        assert np.isfinite(p).all() and p.sum() == pytest.approx(1.0) and 0 <= k < 2
    # the encoders clip extreme windows before they reach the model at all
    v = np.full((1, T, ws.n_pins, 2), 1e30, np.float32)
    assert np.isfinite(encode_vectors(v, np.full((1, T, 6), np.inf))).all()


def test_constant_windows_single_class_and_too_few_folds_are_clear_errors(tmp_path):
    ws = synthetic()
    const = synthetic()
    const.vectors[:] = 1.0
    const.imu[:] = 0.0
    with pytest.raises(TrainError, match="zero variance"):
        train_model("surface", "fnn", const, out_dir=tmp_path / "c", progress=False)
    one = ws.subset(np.flatnonzero(ws.labels == "a"))
    with pytest.raises(TrainError, match=r"labels: task surface needs training windows of at "
                                         r"least 2 classes, the data hold 1: \['a'\]"):
        train_model("surface", "fnn", one, one, out_dir=tmp_path / "o", progress=False)
    with pytest.raises(TrainError, match=r"cv=10: too few groups for 10 folds: the data have "
                                         r"\d trials"):
        train_model("surface", "fnn", ws, out_dir=tmp_path / "k", cv=10, progress=False)
    tiny = ws.subset([0, 1, 20])                         # two classes, three windows
    with pytest.raises(TrainError, match="cv=5 folds need at least 5 windows, the data have 3"):
        train_model("surface", "fnn", tiny, tiny, out_dir=tmp_path / "t", cv=5, progress=False)
    with pytest.raises(TrainError, match=r"model='ridge' does not serve task='surface'"):
        train_model("surface", "ridge", ws, out_dir=tmp_path / "r", progress=False)
    with pytest.raises(TrainError, match=r"task must be one of .* got task='walk'"):
        train_model("walk", "fnn", ws, out_dir=tmp_path / "w", progress=False)
    with pytest.raises(TrainError, match="grid-fnn|grids"):
        nogrid = synthetic()
        nogrid.grids = None
        train_model("surface", "grid-fnn", nogrid, out_dir=tmp_path / "g", progress=False)
    for p in ("c", "o", "k", "t", "r", "w", "g"):
        assert not (tmp_path / p).exists()


def test_fnn_regressor_and_slip_rule_and_fnn_on_synthetic_windows(tmp_path):
    ws = synthetic(targets=True, imu=False, n_groups=8)
    res = train_model("pressure", "fnn", ws, quantise=True, out_dir=tmp_path / "p",
                      progress=False, hidden=(16, 8), epochs=150)
    assert res["temporal_features"] and res["int8"]["kind"] == "regressor"
    assert res["metrics"]["test"]["mae"] < res["metrics"]["test"]["mae_predict_mean"]
    assert np.isfinite(Regressor.load(tmp_path / "p").predict_one(
        np.full(res_n_inputs(tmp_path / "p"), np.nan)))
    slip = synthetic(classes=("no-slip", "slip"), n_groups=6)
    slip.task = "slip"
    slip.contact[:] = True
    r = train_model("slip", "rule", slip, out_dir=tmp_path / "r", progress=False)
    assert r["classes"] == ["no-slip", "slip"] and "latency" in r["metrics"]["test"]
    f = train_model("slip", "fnn", slip, out_dir=tmp_path / "f", progress=False,
                    hidden=(8, 4), epochs=60)
    m = f["metrics"]["test"]
    assert m["slip_f1"] == m["per_class"]["slip"]["f1"]
    # the synthetic classes are far apart (mean displacement 0 against 2 px): learnable
    assert m["slip_f1"] > 0.9
    # every synthetic trial holds one class, so no window starts a slip within a trial
    assert m["latency"]["onsets"] == 0 and m["latency"]["detected"] == 0
    ev = evaluate_model(tmp_path / "f", slip)
    assert ev["metrics"]["latency"]["onsets"] == 0 and ev["metrics"]["slip_f1"] > 0.9


def res_n_inputs(model_dir) -> int:
    return json.loads((Path(model_dir) / "manifest.json").read_text())["input"]["shape"][1]


def test_quantise_if_passes_keeps_float_and_strict_mode_still_fails(monkeypatch, tmp_path):
    def failing_quantise(*a, **k):
        raise QuantisationError("int8 check failed: agrees with the float model on 90.00%",
                                kind="classifier", agreement=0.9, required=0.99)

    monkeypatch.setattr(host.learn.trainers, "quantise_model", failing_quantise)
    ws = synthetic()
    kw = dict(out_dir=None, progress=False, hidden=(8, 4), epochs=20)
    with pytest.raises(QuantisationError, match="90.00%"):
        train_model("surface", "fnn", ws, quantise=True, **dict(kw, out_dir=tmp_path / "a"))
    assert not (tmp_path / "a").exists()
    res = train_model("surface", "fnn", ws, quantise="if-passes", **dict(kw, out_dir=tmp_path / "b"))
    assert "90.00%" in res["int8"]["failed"] and res["default"] == "model.onnx"
    assert res["int8"]["agreement"] == 0.9 and res["int8"]["required"] == 0.99
    doc = json.loads((tmp_path / "b" / "manifest.json").read_text())
    assert doc["variant"] == "float" and doc["measured"]["int8"]["agreement"] == 0.9
    assert not (tmp_path / "b" / "manifest.float.json").exists()
    with pytest.raises(TrainError, match="quantise must be"):
        train_model("surface", "fnn", ws, quantise="yes", **dict(kw, out_dir=tmp_path / "c"))


def _same_surface_two_recordings(seed: int, n_groups: int = 8):
    """Windows of one surface from two recordings, "a" and "b", whose only
    difference is that "b" always loses pins 0-4 (glare on that recording)."""
    ws = synthetic(n_groups=n_groups, per_group=40, n_pins=20, classes=("a", "b"), imu=False,
                   seed=seed)
    rng = np.random.default_rng(seed)
    ws.vectors[:] = rng.normal(1.0, 0.3, ws.vectors.shape).astype(np.float32)
    b = ws.labels == "b"
    ws.vectors[b, :, :5] = 0.0
    ws.lost[b, :, :5] = True
    ws.task = "texture"
    return ws


def test_a_model_cannot_tell_two_recordings_of_one_surface_apart(tmp_path):
    """Pins that a training recording keeps losing are ignored (in the ONNX graph too),
    so a lost-pin pattern is no cue: two recordings of the same surface stay at chance,
    while the same pins, seen, would separate them perfectly."""
    from host.learn.train import recording_lost_pins
    ws, wt = _same_surface_two_recordings(0), _same_surface_two_recordings(1)
    assert recording_lost_pins(ws) == [0, 1, 2, 3, 4]
    res = train_model("texture", "fnn", ws, wt, out_dir=tmp_path / "m", progress=False,
                      hidden=(16, 8), epochs=60)
    assert res["ignored_pins"] == [0, 1, 2, 3, 4]
    assert res["metrics"]["test"]["accuracy"] < 0.7
    man = json.loads((tmp_path / "m" / "manifest.json").read_text())
    assert man["params"]["ignored_pins"] == [0, 1, 2, 3, 4]


def test_texture_on_a_non_133_pin_profile_gets_every_feature_and_carries_its_profile(tmp_path):
    """Trained with tactip331 (331 pins), the texture fnn's roughness neighbours come
    from that layout (none would come from the 133-pin default), the input size is
    the runtime's window over 331 pins, and the manifest carries the profile."""
    from device.pi.models.spec import profile_record
    ws = synthetic(n_groups=4, per_group=10, n_pins=331, Tn=2, classes=("lego", "smooth"),
                   imu=False)
    ws.task = "texture"
    res = train_model("texture", "fnn", ws, out_dir=tmp_path / "m", progress=False,
                      hidden=(8, 4), epochs=20, profile="tactip331")
    assert res["roughness"] is True
    man = json.loads((tmp_path / "m" / "manifest.json").read_text())
    assert man["params"]["roughness"] is True and man["training"]["temporal"]["neighbours"]
    assert man["profile"]["sha256"] == profile_record("tactip331")["sha256"]
    assert man["profile"]["n_pins"] == 331
    assert man["input"]["shape"][1] == RollingWindow(2, 331).encode("vectors").size
    assert Classifier.load(tmp_path / "m").n_features == man["input"]["shape"][1]


def test_texture_trains_on_copies_re_cut_at_other_frame_rates_when_asked(tmp_path):
    """With rates, the texture fnn also fits windows re-cut with 3 of 5 frames kept
    (and some dropped), so it sees several frame intervals; the manifest records the
    rules. Without rates=, it takes the task's default (TASK_RATES: on for texture);
    rates=() trains on the windows as given."""
    from host.learn.tasks import TASK_RATES

    ws = synthetic(n_groups=4, per_group=30, n_pins=20, classes=("lego", "smooth"), imu=False)
    ws.task = "texture"
    assert (ws.t_index >= 0).all()
    train_model("texture", "fnn", ws, out_dir=tmp_path / "m", progress=False,
                hidden=(8, 4), epochs=5)
    man = json.loads((tmp_path / "m" / "manifest.json").read_text())
    assert man["training"]["rates"] == list(TASK_RATES["texture"]) == ["3of5", "3of5+drop10"]
    train_model("texture", "fnn", ws, out_dir=tmp_path / "p", progress=False,
                hidden=(8, 4), epochs=5, rates=())
    plain = json.loads((tmp_path / "p" / "manifest.json").read_text())
    assert plain["training"]["rates"] == []
    assert man["training"]["fit_windows"] > plain["training"]["fit_windows"]


def test_a_given_test_set_from_the_training_recordings_is_marked_optimistic(tmp_path):
    """A --test set cut from the recordings trained on (later frames of the same
    clips, as the shipped texture model's) is not 'given' but optimistic; one from
    other recordings stays 'given'."""
    ws = synthetic(targets=True, imu=False, n_groups=6)
    ws.recordings = np.array([f"clip{g % 3}.avi sha256:0" for g in ws.groups], object)
    tr, te = ws.subset(ws.groups < 4), ws.subset(ws.groups >= 4)
    same = train_model("pressure", "ridge", tr, te, out_dir=tmp_path / "same",
                       progress=False)["metrics"]["test"]
    assert same["same_recordings"] is True and "optimistic" in same["protocol"]
    te.recordings = np.array([f"other{g}.avi sha256:1" for g in te.groups], object)
    other = train_model("pressure", "ridge", tr, te, out_dir=tmp_path / "other",
                        progress=False)["metrics"]["test"]
    assert other["same_recordings"] is False and other["protocol"] == "given"
