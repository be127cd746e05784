"""device/pi/models/winfeat.py (the window features, numpy specification), its compiled
twin winfeat.c, and the models whose graphs read the features (features version 2).

Tolerances: the compiled features equal the numpy ones to the bit (float32 sums in the
same order, no fused multiply-add); numpy and the old ONNX feature nodes (whose
reductions sum in another order) agree within FEAT_RTOL/FEAT_ATOL; a cut graph's
probabilities are the old graph's within PROB_ATOL."""
from __future__ import annotations

import json
import os
import shutil
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from device.pi.models.artefact import ModelError
from device.pi.models.classifier import Classifier
from device.pi.models.window import RollingWindow, WindowTail
from device.pi.models.winfeat import (FEATURES_VERSION, FeatureError, FeatureSpec, WindowFeatures,
                                      feature_spec, window_stats)
from device.pi.vision import native
from tests import REPO_ROOT
from tests.realdata import real_data_dir

FEAT_RTOL = FEAT_ATOL = 1e-5
PROB_ATOL = 1e-5
MODELS = REPO_ROOT / "models"
CUT = ("surface", "slip", "texture")
#: the only operators a graph of features version 2 holds: the scaler (Sub, Mul,
#: Clip), the MLP (MatMul, Add, Sigmoid, Softmax), int8 (Quantize/Dequantize),
#: casts and the output's Identity and label (ArgMax, ArrayFeatureExtractor), a
#: binary classifier's [1 - p, p] (Sub, Concat of its one output), and the pressure
#: ridge's (Scaler, Reshape)
MODEL_OPS = {"Sub", "Mul", "Clip", "MatMul", "Add", "Sigmoid", "Softmax", "Relu", "Cast",
             "QuantizeLinear", "DequantizeLinear", "Identity", "ArgMax",
             "ArrayFeatureExtractor", "Concat", "Scaler", "Reshape"}


def _temporal(task: str) -> dict:
    return json.loads((MODELS / task / "manifest.json").read_text())["training"]["temporal"]


def _spec(p: dict) -> FeatureSpec:
    return FeatureSpec(p["T"], p["n_pins"], p["uses_imu"], p.get("pin_mask"), p.get("neighbours"))


def _old_feature_graph(p: dict, X: np.ndarray):
    """The ONNX feature nodes an fnn's graph held before the cut (the converter of
    host.learn.layers.TemporalFeatures), as a session."""
    from skl2onnx import convert_sklearn
    from skl2onnx.common.data_types import FloatTensorType

    from host.learn.layers import temporal_class
    from host.learn.onnx_io import session

    tf = temporal_class()(**p).fit(X)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = convert_sklearn(tf, initial_types=[("x", FloatTensorType([None, X.shape[1]]))],
                            target_opset=17)
    return session(m)


@pytest.fixture(scope="module")
def kernel():
    fn = native.winfeat_fn()
    if fn is None:
        pytest.skip(f"the compiled kernel is not loaded: {native.status()}")
    return fn


# -- numpy vs the compiled twin ----------------------------------------------------

_values = st.one_of(st.floats(-70, 70, width=32), st.sampled_from(
    [0.0, -0.0, np.nan, np.inf, -np.inf, 1e30, -1e30, 3e38, 2000.0, 1e-30]))


@st.composite
def _cases(draw):
    T = draw(st.integers(1, 5))
    M = draw(st.integers(1, 12))
    imu = draw(st.booleans())
    mask = draw(st.one_of(st.none(), st.lists(st.sampled_from([0, 1]), min_size=M, max_size=M)))
    nb = None
    if draw(st.booleans()):
        K = draw(st.integers(1, 4))
        nb = [draw(st.lists(st.integers(0, M - 1), min_size=K, max_size=K)) for _ in range(M)]
    try:
        spec = FeatureSpec(T, M, imu, mask, nb)
    except FeatureError:             # no pin with all its neighbours in use
        spec = FeatureSpec(T, M, imu, mask, None)
    kind = draw(st.sampled_from(["values", "constant", "zeros"]))
    if kind == "values":
        x = draw(st.lists(_values, min_size=spec.n_inputs, max_size=spec.n_inputs))
    else:
        x = [draw(_values) if kind == "constant" else 0.0] * spec.n_inputs
    return spec, np.array(x, np.float32)


def _compiled(fn, spec: FeatureSpec, x: np.ndarray) -> np.ndarray:
    """The features of one encoded window ``x`` from the compiled kernel (a window
    whose quantised rows are ``x``'s, as RollingWindow keeps them)."""
    w = RollingWindow(spec.T, spec.M)
    w._qvectors[:] = x[:spec.T * spec.M * 2].reshape(spec.T, -1)
    if spec.uses_imu:
        w._qimu[:] = x[spec.T * spec.M * 2:].reshape(spec.T, 6)
    out = np.full((1, spec.n_features), np.nan, np.float32)
    wf = WindowFeatures([spec], [out])
    ctx = wf._context([0], [(w._qvectors, w._qimu)])
    assert fn(ctx.ctypes.data) == 0
    return out[0]


@settings(max_examples=int(os.environ.get("TACFOOT_FUZZ_EXAMPLES", "150")), deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(case=_cases())
def test_the_compiled_features_are_numpys_to_the_bit_and_finite(kernel, case):
    spec, x = case
    want = window_stats(spec, x)[0]
    got = _compiled(kernel, spec, x)
    assert np.isfinite(want).all()
    np.testing.assert_array_equal(got, want)


def test_a_zero_variance_window_gives_zero_changes_and_its_own_means():
    spec = _spec(_temporal("texture"))
    x = np.full(spec.n_inputs, 1.5, np.float32)
    f = window_stats(spec, x)[0]
    assert np.isfinite(f).all()
    used = spec.mask.sum() / spec.M
    T, M = spec.T, spec.M
    dv = f[spec.n_inputs:spec.n_inputs + (T - 1) * M * 2]
    assert not dv.any()
    avg = f[spec.n_inputs + (T - 1) * M * 2:][:2 * T]
    np.testing.assert_allclose(avg, 1.5 * used, rtol=1e-6)


def test_the_kernel_refuses_a_bad_context_and_writes_nothing(kernel):
    spec = FeatureSpec(3, 4, False)
    out = np.zeros((1, spec.n_features), np.float32)
    wf = WindowFeatures([spec], [out])
    w = RollingWindow(3, 4)
    ctx = wf._context([0], [(w._qvectors, w._qimu)])
    for slot, bad in ((1, 0), (2, 5), (9, 0), (1, 1 << 40)):
        c = ctx.copy()
        c[1 + slot] = bad
        assert kernel(c.ctypes.data) == -1
    assert not out.any()


# -- numpy vs the old ONNX feature nodes ---------------------------------------------

@pytest.mark.parametrize("task", ["surface", "texture"])
def test_numpy_gives_the_old_graph_features_on_random_windows(task):
    p = _temporal(task)
    spec = _spec(p)
    rng = np.random.default_rng(3)
    X = np.round(rng.normal(0, 4, (64, spec.n_inputs)) * 4).astype(np.float32) / 4
    X[:8] = rng.normal(0, 30, (8, spec.n_inputs))          # off the 0.25 px grid, large
    got = _old_feature_graph(p, X).run(None, {"x": X})[0]
    np.testing.assert_allclose(window_stats(spec, X), got, rtol=FEAT_RTOL, atol=FEAT_ATOL)


def _real_windows(n_frames: int = 160):
    """(encoded vectors windows of T=15 with the IMU, contact flags) of concrete.avi's
    first frames, as the leg's window holds them."""
    import cv2

    from device.pi.vision.encoder import FrameEncoder
    d = real_data_dir("roboskin/concrete.avi", "roboskin/concrete_gyro.npy") / "roboskin"
    imu = np.load(d / "concrete_gyro.npy")
    cap = cv2.VideoCapture(str(d / "concrete.avi"))
    enc = FrameEncoder("roboskin")
    w = RollingWindow(15, 133)
    out = []
    try:
        for i in range(n_frames):
            ok, frame = cap.read()
            if not ok:
                break
            ef = enc.encode(frame, i / 120.0)
            w.push(vectors=ef.vectors, imu=imu[i % len(imu)])
            if w.full:
                out.append((w.encode("vectors", with_imu=True).copy(),
                            bool(ef.features.contact)))
    finally:
        cap.release()
    return out


@pytest.fixture(scope="module")
def real_windows():
    return _real_windows()


@pytest.mark.parametrize("task", ["surface", "texture"])
def test_numpy_gives_the_old_graph_features_on_real_windows(task, real_windows):
    p = _temporal(task)
    spec = _spec(p)
    T, M = spec.T, spec.M
    X = []
    for x, _ in real_windows:
        v = x[0, :15 * M * 2].reshape(15, -1)[-T:].reshape(-1)
        m = x[0, 15 * M * 2:].reshape(15, 6)[-T:].reshape(-1)
        X.append(np.concatenate([v, m]) if spec.uses_imu else v)
    X = np.array(X, np.float32)
    got = _old_feature_graph(p, X).run(None, {"x": X})[0]
    np.testing.assert_allclose(window_stats(spec, X), got, rtol=FEAT_RTOL, atol=FEAT_ATOL)


# -- the cut graphs --------------------------------------------------------------------

def test_the_shipped_graphs_hold_the_models_alone():
    import onnx

    files = [MODELS / t / n for t in CUT for n in ("model.onnx", "model.int8.onnx")]
    files += sorted((MODELS / "fused").glob("*.onnx"))
    for f in files:
        ops = {n.op_type for n in onnx.load(str(f)).graph.node}
        assert ops <= MODEL_OPS, (f.name, sorted(ops - MODEL_OPS))
    for t in CUT:
        doc = json.loads((MODELS / t / "manifest.json").read_text())
        spec = feature_spec(doc["features"], t)
        assert doc["features"]["version"] == FEATURES_VERSION
        assert doc["input"]["shape"] == [None, spec.n_features]
    fused = json.loads((MODELS / "fused" / "manifest.json").read_text())
    assert len(onnx.load(str(MODELS / "fused" / fused["onnx"])).graph.node) < 100


@pytest.fixture()
def cut_dir(model_dir, tmp_path):
    """The tiny surface fnn (features in its graph) and a cut copy of it."""
    from host.learn.cut import cut_folder

    old, new = tmp_path / "old" / "surface", tmp_path / "new" / "surface"
    shutil.copytree(model_dir / "surface", old)
    shutil.copytree(model_dir / "surface", new)
    sizes = cut_folder(new)
    assert set(sizes) == {"model.onnx", "model.int8.onnx"}
    assert cut_folder(new) == {}                     # cut already: left as it is
    return old, new


def test_a_cut_model_decides_as_its_old_graph_and_an_old_model_still_loads(cut_dir):
    old_dir, new_dir = cut_dir
    for mf in ("manifest.json", "manifest.float.json"):
        old, new = Classifier.load(old_dir / mf), Classifier.load(new_dir / mf)
        assert old.features is None and new.features is not None
        assert old.n_features == new.n_features == 3 * 133 * 2 + 18
        w = RollingWindow(3, 133)
        rng = np.random.default_rng(2)
        for i in range(10):
            w.push(vectors=rng.normal(0, 1 + i, (133, 2)), imu=rng.normal(0, 2, 6))
            if not w.full:
                continue
            (a, pa), (b, pb) = old.predict_window(w), new.predict_window(w)
            assert a == b
            np.testing.assert_allclose(pa, pb, rtol=0, atol=PROB_ATOL)
            c, pc = new.predict(w.encode("vectors", with_imu=True))
            assert c == b
            np.testing.assert_array_equal(pc, pb)


def test_a_features_version_the_runtime_does_not_know_is_refused_in_one_line(cut_dir):
    _, new_dir = cut_dir
    mf = new_dir / "manifest.json"
    doc = json.loads(mf.read_text())
    doc["features"]["version"] = 3
    mf.write_text(json.dumps(doc))
    with pytest.raises(ModelError, match="features version 3") as e:
        Classifier.load(mf)
    assert "\n" not in str(e.value)
    doc["features"]["version"] = FEATURES_VERSION
    doc["features"]["n_features"] += 1
    mf.write_text(json.dumps(doc))
    with pytest.raises(ModelError, match="features.n_features"):
        Classifier.load(mf)


def test_the_fused_graph_of_cut_models_runs_each_models_features_once(cut_dir, tmp_path):
    from device.pi.models.fused import load_fused
    from host.learn.fuse import fuse_models

    _, new_dir = cut_dir
    d = tmp_path / "fused-models"
    for t in ("surface", "slip"):
        shutil.copytree(new_dir, d / t)
    for mf in (d / "slip").glob("manifest*.json"):
        doc = json.loads(mf.read_text())
        doc["kind"] = doc["task"] = "slip"
        doc["classes"] = ["a", "slip", "b", "c"]
        mf.write_text(json.dumps(doc))
    fuse_models(d)
    for variant, mf in (("int8", "manifest.json"), ("float", "manifest.float.json")):
        loaded = {t: Classifier.load(d / t / mf) for t in ("surface", "slip")}
        ones = {t: Classifier.load(d / t / mf) for t in ("surface", "slip")}
        fused, why = load_fused(d, variant, loaded)
        assert fused is not None, why
        assert fused.shared_inputs == {"slip": "surface"}
        assert len(fused._features.specs) == 1           # one feature vector for both
        big = RollingWindow(5, 133)
        w = WindowTail(big, 3)
        rng = np.random.default_rng(4)
        for i in range(8):
            big.push(vectors=rng.normal(0, 3, (133, 2)), imu=rng.normal(0, 1, 6))
            if not w.full:
                continue
            got = fused.run({"surface": w, "slip": w})
            for t in ("surface", "slip"):
                want = ones[t].predict_window(w)
                assert got[t][0] == want[0]
                np.testing.assert_array_equal(got[t][1], want[1])


# -- the real clip -----------------------------------------------------------------------

@pytest.mark.parametrize("variant", ["int8", "float"])
def test_real_clip_decisions_are_the_old_graphs(variant, real_windows):
    """concrete.avi with its IMU: the shipped models of features version 2, run as the
    leg runs them (the fused graph, the features from the compiled kernel when it is
    built), give each model's class of the old graph (the feature nodes the graph held,
    then the same model nodes), probabilities within PROB_ATOL."""
    from device.pi.runtime.config import LegConfig
    from device.pi.runtime.load import load_models

    m = load_models(MODELS, variant, None, LegConfig())
    assert m.fused is not None
    mods = {t: getattr(m, t) for t in CUT}
    olds = {t: _old_feature_graph(_temporal(t), np.zeros((1, mods[t].n_features), np.float32))
            for t in CUT}
    big = RollingWindow(15, 133)
    wins = {15: big, 3: WindowTail(big, 3)}
    n_contact = 0
    for x, contact in real_windows:
        big._qvectors[:] = x[0, :15 * 266].reshape(15, 266)
        big._qimu[:] = x[0, 15 * 266:].reshape(15, 6)
        big.count, big._encoded = 15, {}
        due = {t: wins[mods[t].T] for t in CUT if t != "texture" or contact}
        n_contact += contact
        got = m.fused.run(due)
        for t, w in due.items():
            enc = w.encode("vectors", with_imu=mods[t].uses_imu)
            feats = olds[t].run(None, {"x": np.ascontiguousarray(enc)})[0]
            sess = mods[t].model.session
            out = sess.run([mods[t]._out_name], {sess.get_inputs()[0].name: feats})[0]
            p = mods[t].probabilities_from_output(out)
            assert got[t][0] == int(p.argmax()), (t, variant)
            np.testing.assert_allclose(got[t][1], p, rtol=0, atol=PROB_ATOL)
    assert n_contact > 50


def test_the_context_slots_are_the_libraries():
    from device.pi.models import winfeat
    assert winfeat.CTX_SLOTS == native.WINFEAT_SLOTS
