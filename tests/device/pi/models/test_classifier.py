"""The Pi's classifier (device/pi/models/classifier.py): probabilities cleaned, finite
for any window, and artefacts refused when corrupt, truncated or edited, naming the
file."""
from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from device.pi.models.artefact import FEATURE_SPEC_VERSION, ModelError
from device.pi.models.classifier import INPUT_CLIP, Classifier, clean_probabilities
from device.pi.models.window import ENCODED_BOUND, RollingWindow

finite_or_not = st.floats(allow_nan=True, allow_infinity=True, width=64)


@pytest.fixture(scope="module")
def small_classifier(small_model):
    return Classifier.load(small_model[1])


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


@given(arrays(np.float64, st.integers(2, 6), elements=finite_or_not))
@settings(max_examples=100, deadline=None)
def test_probabilities_are_cleaned(p):
    q, fault = clean_probabilities(p)
    assert np.isfinite(q).all() and q.sum() == pytest.approx(1.0) and (q >= 0).all()
    if fault:
        assert np.allclose(q, 1.0 / len(p))


@given(arrays(np.float32, st.integers(1, 400), elements=st.floats(width=32, allow_nan=True,
                                                                   allow_infinity=True)))
@settings(max_examples=60, deadline=None)
def test_the_classifier_is_finite_for_any_window(small_classifier, values):
    clf = small_classifier
    x = np.resize(values, clf.n_features)
    k, p = clf.predict(x)
    assert np.isfinite(p).all() and p.sum() == pytest.approx(1.0) and 0 <= k < clf.n_classes
    assert not clf.fault



@given(arrays(np.float32, 2, elements=st.floats(width=32, allow_nan=True, allow_infinity=True)))
@settings(max_examples=200, deadline=None)
def test_model_output_gives_the_cleaned_probabilities_to_the_bit(small_classifier, out):
    """Usual outputs (in 0..1, not all 0) and odd ones alike come out as
    clean_probabilities makes them; the fault flag is set for a non-finite output or
    one with nothing left after clipping."""
    clf = small_classifier
    assert clf.n_classes == 2
    p = clf.probabilities_from_output(out)
    want, _ = clean_probabilities(out)
    assert np.array_equal(p, want)
    broken = not np.isfinite(out).all() or not np.nan_to_num(out).clip(0, 1).sum() > 0
    assert clf.fault == broken


@given(st.lists(arrays(np.float64, 2, elements=finite_or_not), min_size=1, max_size=6))
@settings(max_examples=60, deadline=None)
def test_a_window_reaches_the_model_as_predict_would_clean_it(small_classifier, small_model,
                                                                values):
    """predict_window hands the window's encoding to the model as it is: for any pushed
    values that is what predict's cleaning would give."""
    clf = small_classifier
    ws = small_model[2]
    w = RollingWindow(clf.T, ws.n_pins)
    with np.errstate(over="ignore", invalid="ignore"):       # float32 casts of huge values
        for i in range(clf.T):
            v = np.resize(values[i % len(values)] * (i + 1), (ws.n_pins, 2))
            w.push(vectors=v, imu=np.resize(values[-1], 6) * 1e5)
    x = w.encode(clf.input_layout, with_imu=clf.uses_imu)
    assert np.isfinite(x).all() and np.abs(x).max() <= ENCODED_BOUND <= INPUT_CLIP
    k, p = clf.predict_window(w)
    k2, p2 = clf.predict(x)
    assert k == k2 and np.array_equal(p, p2)


def test_each_prediction_reads_its_own_input(small_model):
    """The session reads the classifier's input buffer at every run (bound once, on
    the first): predictions in a row match ONNX Runtime's plain run on each input."""
    clf = Classifier.load(small_model[1])
    sess = clf.model.session
    out_name = sess.get_outputs()[-1].name
    rng = np.random.default_rng(1)
    seen = set()
    for _ in range(6):
        x = rng.normal(0.0, 3.0, (1,) + clf.input_shape).astype(np.float32)
        k, p = clf.predict(x)
        want = clf.probabilities_from_output(sess.run([out_name], {clf.model.input_name: x})[0])
        assert np.array_equal(p, want) and k == int(np.argmax(want))
        seen.add(tuple(np.round(p, 6)))
    assert len(seen) > 1                      # the inputs did give different outputs


def _three_output_model(folder, classes, symbolic: bool = False, n_out: int = 3,
                        op: str = "Softmax"):
    """A model folder: a 4-input softmax over 3 (``n_out``) outputs, with a manifest
    naming ``classes`` (``symbolic``: the graph does not declare its output size)."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    from device.pi.models.artefact import sha256_file
    w = numpy_helper.from_array(np.arange(4 * n_out, dtype=np.float32).reshape(4, n_out) / 10,
                                "w")
    out_dims = [None, "C"] if symbolic else [None, n_out]
    graph = helper.make_graph(
        [helper.make_node("MatMul", ["x", "w"], ["z"]),
         helper.make_node(op, ["z"], ["probabilities"], **({"axis": 1} if op == "Softmax"
                                                            else {}))], "g",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [None, 4])],
        [helper.make_tensor_value_info("probabilities", TensorProto.FLOAT, out_dims)], [w])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    folder.mkdir()
    onnx.save(model, folder / "model.onnx")
    from device.pi.models.spec import ModelSpec, profile_record
    spec = ModelSpec(kind="texture", task="texture", model="fnn", classes=classes, T=1,
                     input_layout="vectors", n_inputs=4, profile=profile_record("roboskin"),
                     onnx="model.onnx", feature_spec=FEATURE_SPEC_VERSION,
                     sha256={"model.onnx": sha256_file(folder / "model.onnx")})
    (folder / "manifest.json").write_text(json.dumps(spec.to_manifest()))
    return folder


@pytest.mark.parametrize("symbolic", [False, True])
def test_a_manifest_whose_classes_do_not_match_the_model_output_is_refused_at_load(
        tmp_path, symbolic):
    """Two classes for a 3-output model used to load and then fault every frame."""
    good = _three_output_model(tmp_path / "good", ["a", "b", "c"], symbolic)
    clf = Classifier.load(good)
    k, p = clf.predict(np.ones(4))
    assert p.shape == (3,) and not clf.fault
    for classes in (["smooth", "lego"], ["a", "b", "c", "d"]):
        d = _three_output_model(tmp_path / f"m{len(classes)}{symbolic}", classes, symbolic)
        with pytest.raises(ModelError, match=rf"m{len(classes)}\w*/manifest\.json: 'classes' "
                                             rf"lists {len(classes)} names .* outputs 3 values"):
            Classifier.load(d)


def test_a_manifest_naming_a_class_twice_is_refused_at_load(tmp_path):
    d = _three_output_model(tmp_path / "m", ["smooth", "lego", "glass"])
    doc = json.loads((d / "manifest.json").read_text())
    doc["classes"] = ["smooth", "lego", "smooth"]
    (d / "manifest.json").write_text(json.dumps(doc))
    with pytest.raises(ModelError, match=r"m/manifest\.json: classes names \['smooth'\] more "
                                         r"than once"):
        Classifier.load(d)


def test_a_two_class_model_with_one_sigmoid_output_still_loads(tmp_path):
    """The one-output case (2 classes, the positive class's probability) stays allowed."""
    clf = Classifier.load(_three_output_model(tmp_path / "m", ["no-slip", "slip"], n_out=1,
                                              op="Sigmoid"))
    assert clf.n_classes == 2
    assert clf.predict(np.zeros(4))[1].tolist() == [0.5, 0.5]
