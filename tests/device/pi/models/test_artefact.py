"""device/pi/models/artefact.py: ONNX + manifest artefacts: round trip, and refusal of
bad files by name."""
from __future__ import annotations

import json

import numpy as np
import pytest
from sklearn.linear_model import Ridge
from sklearn.pipeline import make_pipeline
from sklearn.preprocessing import StandardScaler

from device.pi.models.artefact import BoundRun, ModelError, load_model
from host.learn.onnx_io import sklearn_to_onnx, write_model


@pytest.fixture()
def ridge_dir(tmp_path):
    rng = np.random.default_rng(0)
    X = rng.normal(size=(200, 12)).astype(np.float32)
    y = X @ rng.normal(size=(12, 3)) + 0.1
    est = make_pipeline(StandardScaler(), Ridge(alpha=1.0)).fit(X, y)
    out = write_model(sklearn_to_onnx(est, 12), tmp_path / "m", kind="pressure", n_features=12,
                      extra={"T": 1, "target_mean": 0.1, "targets": ["a", "b", "c"]})
    return out, est, X


def test_round_trip_matches_sklearn(ridge_dir):
    out, est, X = ridge_dir
    m = load_model(out, expect_kind="pressure")
    y = m.run(X)[0]
    assert np.allclose(y, est.predict(X), atol=1e-4)
    assert m.spec.params.target_mean == 0.1             # a regressor's typed parameter
    assert m.spec.training["targets"] == ["a", "b", "c"]  # any other key: the run record
    with pytest.raises(ModelError, match=r"manifest\.json: kind is 'pressure', expected 'surface'"):
        load_model(out, expect_kind="surface")


def test_truncated_model_is_refused_by_name(ridge_dir):
    out, _, _ = ridge_dir
    p = out / "model.onnx"
    p.write_bytes(p.read_bytes()[:100])
    with pytest.raises(ModelError, match=r"model\.onnx: checksum"):
        load_model(out)


def test_corrupt_model_with_matching_checksum_is_refused(ridge_dir):
    out, _, _ = ridge_dir
    from device.pi.models.artefact import sha256_file
    p = out / "model.onnx"
    p.write_bytes(b"\x00garbage" * 10)
    doc = json.loads((out / "manifest.json").read_text())
    doc["sha256"]["model.onnx"] = sha256_file(p)
    (out / "manifest.json").write_text(json.dumps(doc))
    with pytest.raises(ModelError, match=r"model\.onnx: ONNX Runtime cannot load"):
        load_model(out)


@pytest.mark.parametrize("edit,match", [
    (lambda d: d.update(feature_spec=99), "feature-spec version 99"),
    (lambda d: d.update(format="other"), "not a tacfoot model"),
    (lambda d: d.pop("sha256"), "lacks 'sha256'"),
    # every field the loaders read has its type and a sane range
    (lambda d: d.update(onnx=5), r"onnx must be the model file's name \(null only for a rule "
                                 r"model\), got 5"),
    (lambda d: d.update(onnx=None), r"onnx must be the model file's name"),
    (lambda d: d.update(version="abc"), r"manifest version must be a whole number >= 0, "
                                        r"got 'abc'"),
    (lambda d: d.update(T=1e9), r"T must be a whole number of frames in \[1, 1000\], "
                                r"got 1000000000\.0"),
    (lambda d: d.update(T=10**9), r"T must be a whole number of frames in \[1, 1000\]"),
    (lambda d: d.update(T=0), r"T must be a whole number of frames"),
    (lambda d: d.update(feature_spec="1"), r"feature_spec must be a whole number >= 0, got '1'"),
    (lambda d: d.update(sha256=["x"]), r"sha256 must map file names to SHA-256 hex digests"),
    (lambda d: d.update(input={"shape": "x"}), r"input\.shape must be \[batch, size, \.\.\.\] "
                                               r"with whole-number sizes, got 'x'"),
    (lambda d: d.update(input={"shape": [None, -4]}), r"input\.shape must be"),
    (lambda d: d.update(input=7), r"input\.shape must be .*got 7"),
    (lambda d: d.update(kind=3), r"kind must be a non-empty name, got 3"),
    (lambda d: d["params"].update(target_mean="x"), r"params\.target_mean must be a finite "
                                                   r"number, got 'x'"),
    (lambda d: d["params"].pop("target_mean"), r"params\.target_mean is required"),
    (lambda d: d["params"].update(cost_per_decision={}), r"params\.cost_per_decision is not a "
                                                        r"parameter of a regressor model"),
    (lambda d: d.update(input_clip=[[0], [1]]), r"input_clip is not a field of the model spec"),
])
def test_bad_manifest_is_refused(ridge_dir, edit, match):
    out, _, _ = ridge_dir
    doc = json.loads((out / "manifest.json").read_text())
    edit(doc)
    (out / "manifest.json").write_text(json.dumps(doc))
    with pytest.raises(ModelError, match=match):
        load_model(out, expect_kind="pressure")


def test_missing_and_garbled_manifest(tmp_path):
    with pytest.raises(ModelError, match="manifest not found"):
        load_model(tmp_path)
    (tmp_path / "manifest.json").write_text("{nope")
    with pytest.raises(ModelError, match="corrupt manifest"):
        load_model(tmp_path)


def test_manifest_for_picks_int8_by_default_and_float_when_there_is_one(tmp_path):
    from device.pi.models.manifest import FLOAT_MANIFEST, MANIFEST, manifest_for
    (tmp_path / MANIFEST).write_text("{}")
    assert manifest_for(tmp_path, "int8") == tmp_path / MANIFEST
    assert manifest_for(tmp_path, "float") == tmp_path / MANIFEST       # not quantised
    (tmp_path / FLOAT_MANIFEST).write_text("{}")
    assert manifest_for(tmp_path, "float") == tmp_path / FLOAT_MANIFEST
    assert manifest_for(tmp_path, "int8") == tmp_path / MANIFEST
    empty = tmp_path / "empty"
    empty.mkdir()
    assert manifest_for(empty, "int8") == empty                         # the loader names it
    with pytest.raises(ValueError, match="variant"):
        manifest_for(tmp_path, "int4")


def _point_manifest_at(out, name, target):
    from device.pi.models.artefact import sha256_file
    doc = json.loads((out / "manifest.json").read_text())
    doc["onnx"] = name
    doc["sha256"] = {name: sha256_file(target)}
    (out / "manifest.json").write_text(json.dumps(doc))


def test_a_manifest_naming_a_file_outside_its_folder_is_refused(ridge_dir, tmp_path):
    out, _, _ = ridge_dir
    outside = tmp_path / "elsewhere.onnx"
    outside.write_bytes((out / "model.onnx").read_bytes())
    for name in (str(outside), "../elsewhere.onnx"):
        _point_manifest_at(out, name, outside)
        with pytest.raises(ModelError, match="outside the model folder"):
            load_model(out)
    # a link inside the folder that resolves outside it
    (out / "link.onnx").symlink_to(outside)
    _point_manifest_at(out, "link.onnx", outside)
    with pytest.raises(ModelError, match="outside the model folder"):
        load_model(out)


def test_model_file_keeps_names_inside_the_folder(tmp_path):
    from device.pi.models.artefact import model_file
    (tmp_path / "sub").mkdir()
    assert model_file(tmp_path, "sub/model.onnx") == tmp_path / "sub" / "model.onnx"
    for bad in ("/etc/hostname", "../x.onnx", "sub/../../x.onnx", "", 5):
        with pytest.raises(ModelError):
            model_file(tmp_path, bad)


def test_a_bound_run_reads_its_buffer_at_every_call(ridge_dir):
    """BoundRun runs the model on the current contents of its input buffer, call after
    call (bound to the buffer after the first), as a plain run would; a session with
    no I/O binding is run the plain way."""
    out, est, X = ridge_dir
    m = load_model(out, expect_kind="pressure")
    name = m.session.get_outputs()[0].name
    x = np.zeros((1, 12), np.float32)
    bound = BoundRun(m.session, m.input_name, x, name)
    for row in X[:5]:
        x[0] = row
        assert np.allclose(bound(), est.predict(row[None]), atol=1e-4)
        assert np.array_equal(bound(), m.run(x)[0])

    class PlainSession:                   # only run(), as a minimal stand-in has
        def run(self, names, feed):
            return m.session.run(names, feed)

    plain = BoundRun(PlainSession(), m.input_name, x, name)
    for row in X[5:8]:
        x[0] = row
        assert np.array_equal(plain(), m.run(x)[0])
