"""host/learn/cnn.py: the paper's CNN over T stacked binary frames (PyTorch, optional).

Trained once per module on simulated 4-class surface scenes (hard / soft / wet drags
plus the no-touch frames around them) and tested on scenes it never saw: other drag
directions, another depth and another speed.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip(
    "torch", reason="the CNN needs PyTorch, the optional 'cnn' extra: pip install .[cnn]")

from device.pi.models.artefact import load_model  # noqa: E402
from device.pi.models.manifest import MANIFEST  # noqa: E402
from device.pi.models.window import encode_frames  # noqa: E402
from host.data.simulate import simulate_to_dataset  # noqa: E402
from host.learn.cnn import (ONNX_ATOL, OUTPUT_NAME, FrameCNN, frames_input,  # noqa: E402
                      require_torch, train_cnn)
from host.data.load import load_spec  # noqa: E402

T = 3
SCENE = """\
[sensor]
profile = "roboskin"
fps = 120
[surface]
preset = "{preset}"
[[timeline]]
action = "lower"
depth_mm = {depth}
duration_s = 0.1
[[timeline]]
action = "drag"
direction_deg = {direction}
speed_mm_s = {speed}
duration_s = 0.3
[[timeline]]
action = "lift"
duration_s = 0.1
"""
PRESETS = ("hard", "soft", "wet")


def make_dataset(root: Path, name: str, directions, depth_mm: float, speed_mm_s: float,
                 seed: int) -> Path:
    out = root / name
    for preset in PRESETS:
        for d in directions:
            scene = root / f"{name}-{preset}-{d}.toml"
            scene.write_text(SCENE.format(preset=preset, depth=depth_mm, direction=d,
                                          speed=speed_mm_s))
            simulate_to_dataset(str(scene), out, seed=seed, trials=1, progress=False)
    return out


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("cnn")
    train = make_dataset(root, "train", (0, 90, 180, 270), 2.5, 20.0, seed=0)
    test = make_dataset(root, "test", (45, 225), 2.2, 25.0, seed=100)
    cache: dict = {}
    ws_train = load_spec(str(train), "surface", T, progress=False, cache=cache)
    ws_test = load_spec(str(test), "surface", T, progress=False, cache=cache)
    return ws_train, ws_test


@pytest.fixture(scope="module")
def trained(data, tmp_path_factory):
    ws_train, ws_test = data
    out = tmp_path_factory.mktemp("cnn-model") / "surface-cnn"
    res = train_cnn(ws_train, ws_test, epochs=15, seed=0, out_dir=out, progress=False)
    return res, out


def test_cnn_learns_surfaces_it_never_saw(data, trained):
    ws_train, ws_test = data
    res, _ = trained
    assert res["classes"] == ["hard", "no-touch", "slippery", "soft"]
    held = res["metrics"]["test"]
    chance = max(np.unique(ws_test.labels, return_counts=True)[1]) / len(ws_test)
    assert held["n"] == len(ws_test)
    assert held["accuracy"] >= 0.8 > chance + 0.4, held
    assert set(held["per_class"]) == set(res["classes"])
    assert all(0.0 <= m["f1"] <= 1.0 for m in held["per_class"].values())
    cm = np.array(held["confusion"]["matrix"])
    assert cm.sum() == len(ws_test) and np.trace(cm) / cm.sum() == pytest.approx(
        held["accuracy"])
    assert res["loss"][-1] < res["loss"][0]
    assert res["T"] == T and res["frame_size"] == ws_train.frames.shape[-1]


def test_onnx_runtime_equals_torch_and_the_pi_loads_it(data, trained):
    ws_train, ws_test = data
    res, out = trained
    model = load_model(out, expect_kind="surface")
    X = encode_frames(ws_test.frames[::5])
    np.testing.assert_array_equal(X, frames_input(ws_test.frames[::5]))
    p_onnx = model.run(X)[0]
    p_torch = res["estimator"].predict_proba(X)
    assert p_onnx.shape == (len(X), 4) and p_onnx.dtype == np.float32
    np.testing.assert_allclose(p_onnx, p_torch, atol=ONNX_ATOL, rtol=0)
    np.testing.assert_allclose(p_onnx.sum(axis=1), 1.0, atol=1e-5)
    assert res["onnx_vs_torch_max_abs"] <= ONNX_ATOL
    # dynamic batch: one window at a time, as on the Pi, gives the same numbers
    one = model.run(encode_frames(ws_test.frames[0]))[0]
    np.testing.assert_allclose(one[0], p_onnx[0], atol=ONNX_ATOL, rtol=0)
    # a constant window (blank crops, saturated crops) still gives finite probabilities
    for v in (0, 255):
        p = model.run(encode_frames(np.full((2, T, 32, 32), v, np.uint8)))[0]
        assert np.isfinite(p).all() and np.allclose(p.sum(axis=1), 1.0, atol=1e-5)


def test_manifest_fields(data, trained):
    ws_train, _ = data
    res, out = trained
    doc = json.loads((out / MANIFEST).read_text())
    S = ws_train.frames.shape[-1]
    assert doc["kind"] == doc["task"] == "surface"
    assert doc["model"] == "cnn"
    assert doc["classes"] == res["classes"]
    assert doc["T"] == T and doc["training"]["frame_size"] == doc["crop_size"] == S
    assert "window" not in doc and set(doc["metrics"]) == {"train", "test", "cv"}
    assert doc["input_layout"] == "frames"
    assert doc["input"] == {"name": "x", "shape": [None, T, S, S], "dtype": "float32"}
    assert doc["output"] == OUTPUT_NAME
    assert doc["metrics"]["test"]["accuracy"] == res["metrics"]["test"]["accuracy"]
    cnn = doc["training"]["cnn_params"]           # the run's record, not a loader parameter
    assert cnn["hidden"] == 1000 and cnn["kernel"] == 8 and cnn["dropout"] == 0.2
    assert doc["params"]["output_doc"].startswith(OUTPUT_NAME)
    assert doc["training"]["data"]["windows"] == len(ws_train)
    assert doc["profile"]["name"] == "roboskin" and doc["profile"]["n_pins"] == 133
    size = (out / doc["onnx"]).stat().st_size
    assert doc["size_bytes"] == size == res["size_bytes"]
    assert size < 1_000_000            # the full 1000-unit layer fits in 1 MB


def test_training_is_deterministic_and_restores_torch_state(data):
    ws_train, _ = data
    X = frames_input(ws_train.frames[::4])
    y = ws_train.labels[::4]
    threads = torch.get_num_threads()
    det = torch.are_deterministic_algorithms_enabled()
    rng_state = torch.random.get_rng_state()
    kw = dict(hidden=64, epochs=2)
    a = FrameCNN(seed=3, **kw).fit(X, y).predict_proba(X)
    b = FrameCNN(seed=3, **kw).fit(X, y).predict_proba(X)
    c = FrameCNN(seed=4, **kw).fit(X, y).predict_proba(X)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    assert torch.get_num_threads() == threads
    assert torch.are_deterministic_algorithms_enabled() == det
    assert torch.equal(torch.random.get_rng_state(), rng_state)


def test_smaller_hidden_layer_gives_a_smaller_model(data):
    ws_train, _ = data
    X = frames_input(ws_train.frames[::4])
    est = FrameCNN(hidden=256, epochs=1).fit(X, ws_train.labels[::4])
    assert len(est.to_onnx().SerializeToString()) < 200_000


def test_bad_inputs_give_clear_errors(data):
    ws_train, _ = data
    X = frames_input(ws_train.frames[:8])
    with pytest.raises(ValueError, match="at least 2 classes"):
        FrameCNN(epochs=1).fit(X, np.array(["hard"] * 8))
    with pytest.raises(ValueError, match="hidden"):
        FrameCNN(hidden=0).fit(X, ws_train.labels[:8])
    with pytest.raises(ValueError, match="dropout"):
        FrameCNN(dropout=1.0).fit(X, ws_train.labels[:8])
    with pytest.raises(ValueError, match=r"\(N, T, S, S\)"):
        FrameCNN().fit(X[:, 0], ws_train.labels[:8])
    with pytest.raises(ValueError, match="too small"):
        FrameCNN(epochs=1).fit(np.zeros((4, T, 4, 4), np.float32), ["a", "b", "a", "b"])
    with pytest.raises(RuntimeError, match="not fitted"):
        FrameCNN().predict(X)
    with pytest.raises(ValueError, match="frame_size"):
        frames_input(None)
    no_frames = ws_train.subset(np.arange(8))
    no_frames.frames = None
    with pytest.raises(ValueError, match="frame_size"):
        train_cnn(no_frames, epochs=1, progress=False)
    pressure = ws_train.subset(np.arange(8))
    pressure.task = "pressure"
    with pytest.raises(ValueError, match="classifier"):
        train_cnn(pressure, epochs=1, progress=False)


def test_missing_torch_names_the_cnn_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "torch", None)     # "import torch" now fails
    with pytest.raises(ImportError, match=r"pip install \.\[cnn\]"):
        require_torch()
    with pytest.raises(ImportError, match="cnn"):
        FrameCNN().fit(np.zeros((4, T, 32, 32), np.float32), ["a", "b", "a", "b"])


def test_int8_cnn_quantises_its_convs_and_agrees_with_float(data, trained, tmp_path):
    """Static QDQ int8 of the CNN (Conv and Gemm/MatMul), calibrated on training
    windows, agrees with the float model on held-out windows (>= 99 % argmax) and
    is smaller; the calibration windows are 4-D frame stacks."""
    import onnx

    from host.learn.cnn import quantise_cnn

    ws_train, ws_test = data
    res, out = trained
    q = tmp_path / "model.int8.onnx"
    rep = quantise_cnn(res["onnx_path"], ws_train, q, max_windows=256, seed=0)
    assert q.is_file() and rep["passed"] and rep["kind"] == "classifier"
    assert rep["agreement"] >= 0.99
    ops = [n.op_type for n in onnx.load(str(q)).graph.node]
    assert "QuantizeLinear" in ops and "DequantizeLinear" in ops
    assert rep["int8_bytes"] < rep["float_bytes"]
    # the int8 model runs on 4-D windows one at a time, as on the Pi
    from host.learn.onnx_io import session
    s = session(q.read_bytes())
    p = s.run(None, {s.get_inputs()[0].name: frames_input(ws_test.frames[:1])})[0]
    assert p.shape == (1, 4) and np.isfinite(p).all()


def test_int8_in_the_model_folder_becomes_the_default_the_pi_loads(data, trained, tmp_path):
    """quantise_cnn into the model folder: manifest.json then names the int8 file and
    the Pi's Classifier loads it; manifest.float.json keeps the float one."""
    import shutil

    from device.pi.models.classifier import Classifier
    from host.learn.cnn import quantise_cnn
    from host.learn.evaluate import evaluate_model

    ws_train, ws_test = data
    res, out = trained
    folder = tmp_path / "cnn"
    shutil.copytree(out, folder)
    quantise_cnn(folder / "model.onnx", ws_train, folder / "model.int8.onnx", max_windows=128)
    doc = json.loads((folder / MANIFEST).read_text())
    assert doc["onnx"] == "model.int8.onnx" and doc["variant"] == "int8" and doc["T"] == T
    assert json.loads((folder / "manifest.float.json").read_text())["onnx"] == "model.onnx"
    clf = Classifier.load(folder)
    k, p = clf.predict(frames_input(ws_test.frames[:1]))
    assert 0 <= k < 4 and np.isfinite(p).all()
    for variant in ("float", "int8"):
        ev = evaluate_model(folder, ws_test, variant=variant)
        assert ev["metrics"]["accuracy"] > 0.5, (variant, ev["metrics"]["accuracy"])
