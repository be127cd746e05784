"""host/learn/train.py, host/learn/evaluate.py, device/pi/models/classifier.py, device/pi/models/rules.py:
training, ONNX export, int8 quantisation and its check, manifests, refusal of bad
artefacts, hard cases, and the numerics the Pi relies on."""
from __future__ import annotations
from tests import REPO_ROOT
from tests.windows import synthetic

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from device.pi.models.artefact import FEATURE_SPEC_VERSION, ModelError, sha256_file
from device.pi.models.classifier import Classifier, clean_probabilities
from device.pi.numerics import sigmoid, softmax
from device.pi.models.regressor import Regressor
from device.pi.models.rules import RuleClassifier
from device.pi.models.window import RollingWindow, encode_vectors
from host.data.windows import WindowSet
from host.learn.evaluate import evaluate_model
from host.learn.train import (QuantisationError, TrainError, bench_scene, compare_int8,
                        model_inputs, quantise_model, scene_toml, slip_latency, train_model)

T = 3
SURFACE_KINDS = ("hard", "soft", "wet", "no-touch")


# -- data ----------------------------------------------------------------------

def _simulate(out: Path, n_per_kind: int, seed: int, beyond: bool) -> Path:
    """Small randomised step scenes: bench_scene without camera effects (for speed)
    and with the stance direction near 90 degrees (12 trials cannot teach that the
    direction does not matter)."""
    from host.data.simulate import simulate_to_dataset

    scenes = out.parent / f"{out.name}-scenes"
    scenes.mkdir(parents=True)
    for k in range(n_per_kind):
        for i, kind in enumerate(SURFACE_KINDS):
            doc = bench_scene(kind, np.random.default_rng([seed, i, k]), beyond=beyond)
            doc["effects"] = ["imu_noise"]
            for a in doc["timeline"]:
                if a["action"] == "drag":
                    a["direction_deg"] = 90.0 + 10.0 * (k - 1)
            path = scenes / f"{kind}_{k}.toml"
            path.write_text(scene_toml(doc))
            simulate_to_dataset(str(path), out, seed=seed * 1000 + k, progress=False)
    return out


@pytest.fixture(scope="module")
def surface_sets(tmp_path_factory):
    """Train: 3 step trials per class; test: 1 per class, unseen seeds, surface
    parameters drawn beyond the training range."""
    from host.data.load import load_spec

    base = tmp_path_factory.mktemp("surface")
    tr = _simulate(base / "train", 3, seed=1, beyond=False)
    te = _simulate(base / "test", 1, seed=2, beyond=True)
    cache = {}
    return (load_spec(str(tr), "surface", T, progress=False, cache=cache),
            load_spec(str(te), "surface", T, progress=False, cache=cache))


@pytest.fixture(scope="module")
def surface_model(surface_sets, tmp_path_factory):
    ws_tr, ws_te = surface_sets
    out = tmp_path_factory.mktemp("models") / "surface"
    res = train_model("surface", "fnn", ws_tr, ws_te, quantise=True, seed=0, out_dir=out,
                      progress=False, alpha=0.1, epochs=200)
    return res, out


@pytest.fixture(scope="module")
def small_model(tmp_path_factory):
    """A quick FNN on synthetic windows (for numerics and refusal tests)."""
    ws = synthetic()
    out = tmp_path_factory.mktemp("small") / "m"
    res = train_model("surface", "fnn", ws, quantise=True, out_dir=out, progress=False,
                      hidden=(8, 4), epochs=60, min_agreement=0.9)
    return res, out, ws


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
    assert 0.0 <= sat["held_out"]["share_outside"] < 0.01
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
    assert doc["int8"]["agreement"] >= 0.99
    assert doc["metrics"]["test"]["accuracy"] == res["metrics"]["test"]["accuracy"]
    assert doc["training"]["data"] == ws_tr.summary()
    assert doc["training"]["test_data"] == ws_te.summary()
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


def test_evaluate_reports_metrics_latency_size_and_kept_fraction(surface_model, surface_sets):
    res, out = surface_model
    _, ws_te = surface_sets
    ev = evaluate_model(out, ws_te)
    assert ev["variant"] == "int8" and ev["n_windows"] == len(ws_te)
    assert ev["metrics"]["accuracy"] == pytest.approx(res["int8"]["metrics"]["accuracy"])
    conf = np.array(ev["metrics"]["confusion"]["matrix"])
    assert conf.sum() == len(ws_te) and np.trace(conf) == round(ev["metrics"]["accuracy"]
                                                                * len(ws_te))
    assert set(ev["metrics"]["per_class"]) == set(res["classes"])
    lat = ev["latency_ms"]
    assert 0 < lat["p50"] <= lat["p99"] and lat["n"] == len(ws_te)
    assert ev["model_bytes"] == (out / "model.int8.onnx").stat().st_size
    assert ev["kept_fraction"] == ws_te.kept_fraction and ev["threads"] == 1
    evf = evaluate_model(out, ws_te, variant="float")
    assert evf["model_bytes"] == (out / "model.onnx").stat().st_size
    assert evf["metrics"]["accuracy"] == pytest.approx(res["metrics"]["test"]["accuracy"])
    from dataclasses import replace

    with pytest.raises(ValueError, match="the windows have T=5 frames, the model sees T=3"):
        evaluate_model(out, replace(ws_te.subset(np.arange(4)), window=5))


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


# -- int8 checks ---------------------------------------------------------------

def test_int8_check_fails_loudly_and_keeps_nothing(small_model, tmp_path, monkeypatch):
    res, out, ws = small_model
    X = model_inputs(ws, "vectors", True)
    y = np.array([sorted(set(ws.labels)).index(x) for x in ws.labels])
    fbytes = (out / "model.onnx").read_bytes()
    rep = quantise_model(fbytes, X, tmp_path / "q.onnx", check_inputs=X, check_targets=y)
    assert rep["passed"] and rep["agreement"] >= 0.99 and (tmp_path / "q.onnx").exists()
    # corrupt the int8 weights: the comparison catches it
    import onnx
    from onnx import numpy_helper

    q = onnx.load(str(tmp_path / "q.onnx"))
    last = [n for n in q.graph.node if n.op_type == "MatMul"][-1]       # the output layer
    dq = next(n for n in q.graph.node if last.input[1] in n.output)
    init = next(i for i in q.graph.initializer if i.name == dq.input[0])
    a = numpy_helper.to_array(init)
    assert a.dtype == np.int8                                        # its int8 weights
    init.CopyFrom(numpy_helper.from_array((-a.astype(np.int16)).clip(-127, 127)
                                          .astype(np.int8), init.name))
    bad = compare_int8(fbytes, q.SerializeToString(), X, y)
    assert not bad["passed"] and bad["agreement"] < 0.99 and bad["accuracy_int8"] < 0.9
    # force the disagreement inside quantise_model: it raises and keeps no file
    import host.learn.train as ht

    real = ht.compare_int8

    def disagree(*a, **kw):
        r = real(*a, **kw)
        return dict(r, agreement=0.9, passed=False)

    monkeypatch.setattr(ht, "compare_int8", disagree)
    with pytest.raises(QuantisationError, match=r"q2\.onnx agrees with the float model on "
                                                r"90\.00% of \d+ held-out windows .*below the "
                                                r"required 99\.00%"):
        quantise_model(fbytes, X, tmp_path / "q2.onnx", check_inputs=X)
    assert not (tmp_path / "q2.onnx").exists()
    # and train --quantise fails as a whole, writing nothing
    with pytest.raises(QuantisationError, match="int8 check failed"):
        train_model("surface", "fnn", ws, quantise=True, out_dir=tmp_path / "m",
                    progress=False, hidden=(8, 4), epochs=20)
    assert not (tmp_path / "m").exists()


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


# -- refusing bad artefacts --------------------------------------------------------

def test_corrupt_or_truncated_model_files_are_refused_naming_the_file(small_model, tmp_path):
    import shutil

    _, out, _ = small_model
    d = tmp_path / "m"
    shutil.copytree(out, d)
    Classifier.load(d)                                    # fine as written
    q = d / "model.int8.onnx"
    data = q.read_bytes()
    q.write_bytes(data[: len(data) // 2])                 # truncated
    with pytest.raises(ModelError, match=r"model\.int8\.onnx.*checksum"):
        Classifier.load(d)
    q.write_bytes(data[:100] + bytes([data[100] ^ 0xFF]) + data[101:])   # one byte flipped
    with pytest.raises(ModelError, match=r"model\.int8\.onnx"):
        Classifier.load(d)
    q.write_bytes(data)
    Classifier.load(d / "manifest.float.json")
    (d / "model.onnx").unlink()
    with pytest.raises(ModelError, match=r"model\.onnx: model file missing"):
        Classifier.load(d / "manifest.float.json")
    doc = json.loads((d / "manifest.json").read_text())
    (d / "manifest.json").write_text(json.dumps(dict(doc, feature_spec=FEATURE_SPEC_VERSION + 1)))
    with pytest.raises(ModelError, match=r"manifest\.json: feature-spec version"):
        Classifier.load(d)
    (d / "manifest.json").write_text(json.dumps(doc)[:-40])
    with pytest.raises(ModelError, match=r"manifest\.json: corrupt manifest"):
        Classifier.load(d)
    (d / "manifest.json").write_text(json.dumps(dict(doc, classes=["only"])))
    with pytest.raises(ModelError, match=r"manifest\.json.*classes"):
        Classifier.load(d)
    (d / "manifest.json").write_text(json.dumps(doc))
    clf = Classifier.load(d)
    with pytest.raises(ModelError, match=r"model\.int8\.onnx: expects an input of"):
        clf.predict(np.zeros(3))


def test_an_edited_rule_is_refused(tmp_path):
    ws = synthetic(classes=("hard", "soft"), imu=False)
    train_model("surface", "rule", ws, out_dir=tmp_path / "r", progress=False)
    RuleClassifier.load(tmp_path / "r")
    doc = json.loads((tmp_path / "r" / "manifest.json").read_text())
    doc["rule"]["contact_px"] += 1.0
    (tmp_path / "r" / "manifest.json").write_text(json.dumps(doc))
    with pytest.raises(ModelError, match=r"r/manifest\.json: the rule table does not match"):
        Classifier.load(tmp_path / "r")


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


def test_grouped_cv_reports_each_fold(tmp_path):
    ws = synthetic(n_groups=8)
    res = train_model("surface", "fnn", ws, out_dir=tmp_path / "m", cv=3, progress=False,
                      hidden=(8, 4), epochs=100)
    cv = res["metrics"]["cv"]
    assert cv["folds"] == 3 and cv["grouped"] and len(cv["fold_accuracy"]) == 3
    assert cv["n"] == len(ws) - res["metrics"]["test"]["n"]     # on the training part
    assert cv["accuracy"] > 0.9


# -- slip latency ------------------------------------------------------------------

def test_slip_latency_counts_frames_from_each_true_onset():
    lab = np.array(["no-slip"] * 3 + ["slip"] * 4 + ["no-slip"] * 2 + ["slip"] * 3
                   + ["no-slip"] * 2 + ["slip"] * 2, object)
    n = len(lab)
    ws = synthetic(n_groups=1, per_group=n)
    ws.labels = lab
    pred = np.zeros(n, bool)
    pred[[4, 5]] = True          # onset at 3, detected at 4: 1 frame
    pred[[9]] = True             # onset at 9, detected at once: 0 frames
    # the third onset (14) is never detected: missed
    res = slip_latency(ws, pred)
    assert res["onsets"] == 3 and res["detected"] == 2 and res["missed"] == 1
    assert res["latencies_frames"] == [1, 0] and res["median_frames"] == 0.5


# -- numerics on the Pi ---------------------------------------------------------------

finite_or_not = st.floats(allow_nan=True, allow_infinity=True, width=64)


@given(arrays(np.float64, st.integers(1, 12), elements=finite_or_not))
@settings(max_examples=200, deadline=None)
def test_softmax_is_finite_normalised_and_shift_invariant(z):
    p = softmax(z)
    assert np.isfinite(p).all() and (p >= 0).all() and (p <= 1).all()
    assert p.sum() == pytest.approx(1.0)
    zf = np.nan_to_num(z, nan=0.0, posinf=1e4, neginf=-1e4).clip(-1e4, 1e4)
    if np.isfinite(z).all() and np.abs(z).max() < 1e3:
        assert np.allclose(softmax(z + 123.0), p)
        assert zf[np.argmax(p)] >= zf.max() - 1e-9     # the top class has the top logit
        i, j = np.argmax(zf), np.argmin(zf)
        assert p[i] >= p[j]


@given(arrays(np.float64, st.integers(1, 12), elements=finite_or_not))
@settings(max_examples=200, deadline=None)
def test_sigmoid_is_finite_bounded_symmetric_and_monotone(z):
    s = sigmoid(z)
    assert np.isfinite(s).all() and (s >= 0).all() and (s <= 1).all()
    ok = ~np.isnan(z)
    assert np.allclose(sigmoid(-z[ok]), 1.0 - s[ok], atol=1e-12)
    order = np.argsort(np.nan_to_num(z[ok], posinf=1e308, neginf=-1e308), kind="stable")
    assert (np.diff(s[ok][order]) >= 0).all()


@given(arrays(np.float64, st.integers(2, 6), elements=finite_or_not))
@settings(max_examples=100, deadline=None)
def test_probabilities_are_cleaned(p):
    q, fault = clean_probabilities(p)
    assert np.isfinite(q).all() and q.sum() == pytest.approx(1.0) and (q >= 0).all()
    if fault:
        assert np.allclose(q, 1.0 / len(p))


@st.composite
def training_matrix(draw):
    n = draw(st.integers(3, 12))
    d = draw(st.integers(1, 5))
    scale = draw(st.sampled_from([1e-3, 1.0, 1e3, 1e6]))
    X = draw(arrays(np.float32, (n, d), elements=st.floats(-1, 1, width=32))) * np.float32(scale)
    const = draw(st.lists(st.integers(0, d - 1), max_size=d))
    X[:, const] = np.float32(draw(st.floats(-100, 100, width=32)))   # zero-variance columns
    return X


@given(training_matrix(), arrays(np.float32, 5, elements=st.floats(width=32, allow_nan=False)))
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
def test_the_folded_scaler_matches_sklearn_and_stays_finite(X, probe):
    """The MLPs' scaler in the graph (Sub, Mul, Clip) equals sklearn's StandardScaler
    clipped to +-8 standard deviations, zero-variance columns included, and its
    output is finite and bounded for any input without NaN (inf included)."""
    from sklearn.preprocessing import StandardScaler
    from skl2onnx import convert_sklearn
    from skl2onnx.common.data_types import FloatTensorType

    from host.learn.train import SCALED_CLIP, _scaler_class, _session

    sc = _scaler_class()().fit(X)
    m = convert_sklearn(sc, initial_types=[("x", FloatTensorType([None, X.shape[1]]))],
                        target_opset=17)
    sess = _session(m)
    got = sess.run(None, {"x": X})[0]
    want = np.clip(StandardScaler().fit(X).transform(X.astype(np.float64)), -8.0, 8.0)
    assert SCALED_CLIP == 8.0
    assert np.allclose(got, sc.transform(X), rtol=1e-5, atol=1e-5)
    assert np.allclose(got, want, rtol=1e-3, atol=1e-3)
    const = np.ptp(X, axis=0) == 0          # every value identical
    assert np.allclose(got[:, const], 0.0, atol=1e-3)
    x = np.resize(probe, X.shape[1])[None].astype(np.float32)
    out = sess.run(None, {"x": x})[0]
    assert np.isfinite(out).all() and (np.abs(out) <= SCALED_CLIP).all()


@given(arrays(np.float32, st.integers(1, 400), elements=st.floats(width=32, allow_nan=True,
                                                                   allow_infinity=True)))
@settings(max_examples=60, deadline=None)
def test_the_classifier_is_finite_for_any_window(small_model_module, values):
    clf = small_model_module
    x = np.resize(values, clf.n_features)
    k, p = clf.predict(x)
    assert np.isfinite(p).all() and p.sum() == pytest.approx(1.0) and 0 <= k < clf.n_classes
    assert not clf.fault


@pytest.fixture(scope="module")
def small_model_module(small_model):
    return Classifier.load(small_model[1])


# -- scenes ------------------------------------------------------------------------

def test_bench_scenes_parse_and_test_ranges_reach_beyond_training():
    from device.sim.scene import parse_scene

    try:
        import tomllib
    except ModuleNotFoundError:   # Python 3.10
        import tomli as tomllib
    from host.learn.train import BENCH_KINDS, SURFACE_RANGES

    for kind in BENCH_KINDS:
        for beyond in (False, True):
            doc = bench_scene(kind, np.random.default_rng(0), beyond)
            sc = parse_scene(tomllib.loads(scene_toml(doc)), source=kind)
            assert sc.duration_s > 0.3
    mus = [bench_scene("wet", np.random.default_rng(k), True)["surface"]["mu"] for k in range(60)]
    lo, hi = SURFACE_RANGES["wet"]["mu"][0]
    assert min(mus) < lo and max(mus) > hi


def test_rotated_windows_match_a_drag_in_the_rotated_direction(tmp_path):
    """Rotation augmentation: the 0-degree drag rotated by 30 degrees matches the
    30-degree drag (pins moved by the layout's symmetry, vectors and IMU turned)."""
    from host.data.simulate import simulate_to_dataset
    from host.data.extract import layout_for_profile
    from host.data.load import load_spec
    from host.learn.train import augment_rotations, layout_rotations, rotate_windows

    rots = dict(layout_rotations(layout_for_profile("roboskin")))
    assert sorted(rots) == list(range(30, 360, 30))
    base = (REPO_ROOT / "device/sim/scenes/drag-0.toml").read_text()
    ws = {}
    for deg in (0, 30):
        scene = tmp_path / f"d{deg}.toml"
        scene.write_text(base.replace("direction_deg = 0", f"direction_deg = {deg}"))
        simulate_to_dataset(str(scene), tmp_path / f"ds{deg}", seed=0, progress=False)
        ws[deg] = load_spec(str(tmp_path / f"ds{deg}"), "slip", T, progress=False,
                            min_classes=1)
    n = min(len(ws[0]), len(ws[30]))
    want = ws[30].vectors[:n, -1]
    got = rotate_windows(ws[0], 30, rots[30]).vectors[:n, -1]
    wrong = rotate_windows(ws[0], 330, rots[330]).vectors[:n, -1]
    scale = np.abs(want).mean()
    assert np.abs(got - want).mean() < 0.08 * scale < np.abs(wrong - want).mean()
    assert np.allclose(rotate_windows(ws[0], 30, rots[30]).imu[:n], ws[30].imu[:n], atol=1e-3)
    aug = augment_rotations(ws[0], 3)
    assert len(aug) == 4 * len(ws[0]) and aug.source["augmented_deg"] == [0, 90, 180, 270]
    assert np.array_equal(aug.labels[:len(ws[0])], ws[0].labels) and aug.grids is None


def test_the_fnn_first_layer_in_onnx_equals_its_numpy_transform():
    from skl2onnx import convert_sklearn
    from skl2onnx.common.data_types import FloatTensorType

    from host.learn.train import _session, _temporal_class

    rng = np.random.default_rng(0)
    for Tn, imu in ((2, False), (3, True), (5, True)):
        M = 7
        X = (rng.normal(0, 3, (50, Tn * M * 2 + (6 * Tn if imu else 0)))).astype(np.float32)
        tf = _temporal_class()(T=Tn, n_pins=M, uses_imu=imu).fit(X)
        m = convert_sklearn(tf, initial_types=[("x", FloatTensorType([None, X.shape[1]]))],
                            target_opset=17)
        got = _session(m).run(None, {"x": X})[0]
        want = tf.transform(X)
        assert got.shape == want.shape == (50, tf.n_features_out_)
        assert np.allclose(got, want, atol=1e-5)
        # the appended columns hold what they say: e.g. the last frame's mean |v|
        v = X[:, :Tn * M * 2].reshape(50, Tn, M, 2)
        assert np.allclose(want[:, -1], np.hypot(v[:, -1, :, 0], v[:, -1, :, 1]).mean(1),
                           atol=1e-5)


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
    assert m["slip_f1"] == m["per_class"]["slip"]["f1"] and m["latency"]["onsets"] >= 0
    ev = evaluate_model(tmp_path / "f", slip)
    assert "latency" in ev["metrics"] and ev["metrics"]["slip_f1"] >= 0.0


def res_n_inputs(model_dir) -> int:
    return json.loads((Path(model_dir) / "manifest.json").read_text())["input"]["shape"][1]


def test_rolling_window_encodes_once_per_push_and_never_serves_a_stale_input():
    """Models sharing a window read one encoding per frame; a push or clear drops it,
    and the shared array is read-only so no model can alter another's input."""
    from device.pi.models.window import RollingWindow, encode_vectors
    w = RollingWindow(2, 3)
    rng = np.random.default_rng(0)
    for _ in range(2):
        w.push(vectors=rng.normal(size=(3, 2)), imu=rng.normal(size=6))
    a = w.encode("vectors", with_imu=True)
    assert w.encode("vectors", with_imu=True) is a
    assert not a.flags.writeable
    with pytest.raises(ValueError):
        a[0, 0] = 1.0
    assert w.encode("vectors") is not a and w.encode("vectors").shape[1] == a.shape[1] - 12
    v_new = rng.normal(size=(3, 2))
    w.push(vectors=v_new, imu=np.zeros(6))
    b = w.encode("vectors", with_imu=True)
    assert b is not a
    np.testing.assert_array_equal(b, encode_vectors(w.vectors, w.imu))
    w.clear()
    assert w.encode("vectors", with_imu=True) is not b


def test_quantise_if_passes_keeps_float_and_strict_mode_still_fails(monkeypatch, tmp_path):
    import host.learn.train

    def failing_quantise(*a, **k):
        raise QuantisationError("int8 check failed: agrees with the float model on 90.00%")

    monkeypatch.setattr(host.learn.train, "quantise_model", failing_quantise)
    ws = synthetic()
    kw = dict(out_dir=None, progress=False, hidden=(8, 4), epochs=20)
    with pytest.raises(QuantisationError, match="90.00%"):
        train_model("surface", "fnn", ws, quantise=True, **dict(kw, out_dir=tmp_path / "a"))
    assert not (tmp_path / "a").exists()
    res = train_model("surface", "fnn", ws, quantise="if-passes", **dict(kw, out_dir=tmp_path / "b"))
    assert "90.00%" in res["int8"]["failed"] and res["default"] == "model.onnx"
    with pytest.raises(TrainError, match="quantise must be"):
        train_model("surface", "fnn", ws, quantise="yes", **dict(kw, out_dir=tmp_path / "c"))
