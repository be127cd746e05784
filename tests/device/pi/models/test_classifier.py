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
