"""host/learn/onnx_io.py: the one manifest writer, the float/int8 variants of a model
folder, JSON of numpy values, and running ONNX on the host."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from device.pi.models.artefact import MANIFEST, sha256_file
from host.learn.onnx_io import (FLOAT_MANIFEST, FLOAT_NAME, INT8_NAME, json_default,
                                write_manifest, write_variants)


def test_json_default_writes_numpy_values_and_paths_and_refuses_the_rest():
    doc = {"a": np.float32(1.5), "b": np.arange(3), "c": np.int64(7), "p": Path("x/y")}
    assert json.loads(json.dumps(doc, default=json_default)) == {
        "a": 1.5, "b": [0, 1, 2], "c": 7, "p": "x/y"}
    with pytest.raises(TypeError, match="set"):
        json.dumps({"s": {1}}, default=json_default)


def test_write_variants_records_both_files_and_makes_int8_the_default(tmp_path):
    (tmp_path / FLOAT_NAME).write_bytes(b"float model")
    (tmp_path / INT8_NAME).write_bytes(b"int8")
    from host.learn.onnx_io import new_manifest
    write_manifest(tmp_path, new_manifest(4, {"kind": "surface", "n": np.int32(3)}, FLOAT_NAME,
                                          "0" * 64, 11))
    files = write_variants(tmp_path, int8=True, updates={"int8": {"agreement": 1.0}})
    doc = json.loads((tmp_path / MANIFEST).read_text())
    fdoc = json.loads((tmp_path / FLOAT_MANIFEST).read_text())
    assert doc["onnx"] == INT8_NAME and doc["variant"] == "int8" and doc["n"] == 3
    assert doc["size_bytes"] == 4 and doc["int8"] == {"agreement": 1.0}
    assert doc["variants"] == {"float": FLOAT_NAME, "int8": INT8_NAME}
    for name in (FLOAT_NAME, INT8_NAME):
        assert doc["sha256"][name] == sha256_file(tmp_path / name) == files[name]["sha256"]
    assert fdoc["onnx"] == FLOAT_NAME and fdoc["variant"] == "float"
    assert fdoc["size_bytes"] == len(b"float model") and fdoc["sha256"] == doc["sha256"]
    # float only: the float file is the default and the stale float manifest goes
    (tmp_path / INT8_NAME).unlink()
    write_variants(tmp_path, int8=False)
    doc = json.loads((tmp_path / MANIFEST).read_text())
    assert doc["onnx"] == FLOAT_NAME and doc["variant"] == "float"
    assert list(doc["sha256"]) == [FLOAT_NAME] and not (tmp_path / FLOAT_MANIFEST).exists()


def test_every_onnx_runtime_session_is_set_up_by_the_pis_code(monkeypatch):
    """host sessions (training, quantisation, the localiser's ONNX check) and the Pi's
    load_model share device.pi.models.artefact.ort_session."""
    from device.pi.models import artefact
    from host.learn import onnx_io
    from host.localiser import fit

    made = []
    monkeypatch.setattr(onnx_io, "ort_session",
                        lambda src, threads=1: made.append(threads) or artefact.ort_session(
                            src, threads))
    X = np.random.default_rng(0).normal(size=(20, 3))
    ridge = fit.fit_ridge(X, X @ np.ones((3, 2)), alpha=1.0)
    assert fit.onnx_vs_sklearn(fit.ridge_to_onnx(ridge, 3), ridge, X) < 1e-4
    opts = onnx_io.session(fit.ridge_to_onnx(ridge, 3), threads=2).get_session_options()
    assert made == [1, 2]
    assert (opts.intra_op_num_threads, opts.inter_op_num_threads, opts.log_severity_level) == (
        2, 1, 3)


def test_new_manifest_is_what_the_pi_reads_for_onnx_and_for_rule_models(tmp_path):
    from device.pi.models.artefact import read_manifest
    from host.learn.onnx_io import new_manifest

    onnx = new_manifest(12, {"kind": "surface", "T": 3}, FLOAT_NAME, "ab" * 32, 99)
    rule = new_manifest(12, {"model": "rule", "kind": "surface"})
    assert onnx["sha256"] == {FLOAT_NAME: "ab" * 32} and onnx["size_bytes"] == 99
    assert rule["onnx"] is None and rule["sha256"] == {} and rule["input"]["shape"] == [None, 12]
    for name, doc in (("o", onnx), ("r", rule)):
        read, _ = read_manifest(write_manifest(tmp_path / name, doc))
        assert read == doc


def test_a_free_form_manifest_is_refused_by_the_writer_naming_the_field(tmp_path):
    """The writer checks every manifest against the model spec: a dict without the
    spec's fields, an old key variant, or a metrics key other than train/test/cv."""
    from device.pi.models.spec import SpecError
    from host.learn.onnx_io import new_manifest, new_spec

    with pytest.raises(SpecError, match=r"manifest\.json: manifest version None"):
        write_manifest(tmp_path, {"kind": "surface", "onnx": FLOAT_NAME})
    doc = new_manifest(4, {"kind": "surface", "T": 3}, FLOAT_NAME, "0" * 64, 11)
    with pytest.raises(SpecError, match=r"manifest\.json: window: an old key.*'T'"):
        write_manifest(tmp_path, dict(doc, window=3))
    with pytest.raises(SpecError, match=r"metrics: keys \['heldout'\] are not among"):
        new_spec(4, {"kind": "surface", "metrics": {"train": {}, "heldout": {}}}, FLOAT_NAME)
    assert not (tmp_path / MANIFEST).exists()
    spec = new_spec(4, {"kind": "surface", "metrics": {"test": {"accuracy": 0.5}}}, FLOAT_NAME)
    assert spec.metrics == {"train": None, "test": {"accuracy": 0.5}, "cv": None}
    assert spec.profile["name"] == "roboskin" and spec.profile["n_pins"] == 133
