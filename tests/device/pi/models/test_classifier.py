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
from device.pi.models.classifier import Classifier, clean_probabilities

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

