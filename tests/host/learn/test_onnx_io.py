"""host/learn/onnx_io.py: the spec a writer builds (its typed params and measured
facts), the float/int8 variants of a model folder, JSON of numpy values, and running
ONNX on the host."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from device.pi.models.artefact import sha256_file
from device.pi.models.manifest import (FLOAT_MANIFEST, MANIFEST, read_spec, write_spec,
                                       write_variant_specs)
from host.learn.onnx_io import FLOAT_NAME, INT8_NAME, fill_variants, json_default, new_spec


def test_json_default_writes_numpy_values_and_paths_and_refuses_the_rest():
    doc = {"a": np.float32(1.5), "b": np.arange(3), "c": np.int64(7), "p": Path("x/y")}
    assert json.loads(json.dumps(doc, default=json_default)) == {
        "a": 1.5, "b": [0, 1, 2], "c": 7, "p": "x/y"}
    with pytest.raises(TypeError, match="set"):
        json.dumps({"s": {1}}, default=json_default)


def test_fill_variants_records_both_files_and_makes_int8_the_default(tmp_path):
    (tmp_path / FLOAT_NAME).write_bytes(b"float model")
    (tmp_path / INT8_NAME).write_bytes(b"int8")
    spec = new_spec(4, {"kind": "surface", "T": 2, "classes": ["a", "b"], "n": np.int32(3),
                        "int8": {"agreement": 1.0}}, FLOAT_NAME, "0" * 64, 11)
    files = fill_variants(tmp_path, spec, int8=True)
    write_variant_specs(tmp_path, spec)
    doc = json.loads((tmp_path / MANIFEST).read_text())
    fdoc = json.loads((tmp_path / FLOAT_MANIFEST).read_text())
    assert doc["onnx"] == INT8_NAME and doc["variant"] == "int8" and doc["training"]["n"] == 3
    assert doc["size_bytes"] == 4 and doc["measured"]["int8"] == {"agreement": 1.0}
    assert doc["variants"] == {"float": FLOAT_NAME, "int8": INT8_NAME}
    for name in (FLOAT_NAME, INT8_NAME):
        assert doc["sha256"][name] == sha256_file(tmp_path / name) == files[name]["sha256"]
    assert fdoc["onnx"] == FLOAT_NAME and fdoc["variant"] == "float"
    assert fdoc["size_bytes"] == len(b"float model") and fdoc["sha256"] == doc["sha256"]
    # float only: the float file is the default and the stale float manifest goes
    (tmp_path / INT8_NAME).unlink()
    spec, _ = read_spec(tmp_path)
    fill_variants(tmp_path, spec, int8=False)
    write_variant_specs(tmp_path, spec)
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


def test_new_spec_is_what_the_pi_reads_for_onnx_and_for_rule_models(tmp_path):
    onnx = new_spec(12, {"kind": "surface", "T": 3, "classes": ["hard", "soft"]}, FLOAT_NAME,
                    "ab" * 32, 99)
    rule = new_spec(12, {"model": "rule", "kind": "surface", "T": 2, "classes": ["hard", "soft"],
                         "n_pins": 3, "rule": {"a": 1}, "rule_sha256": "x"})
    assert onnx.sha256 == {FLOAT_NAME: "ab" * 32} and onnx.size_bytes == 99
    assert rule.onnx is None and rule.sha256 == {} and rule.n_inputs == 12
    assert rule.params.rule == {"a": 1}             # a rule's typed parameters
    for name, spec in (("o", onnx), ("r", rule)):
        read, _ = read_spec(write_spec(tmp_path / name, spec))
        assert read.to_manifest() == spec.to_manifest()


def test_a_writer_routes_measured_facts_params_and_the_rest(tmp_path):
    """A writer's keys: the measured facts to ``measured``, the family's parameters to
    ``params``, anything else to the run record; an old metrics key is refused."""
    from device.pi.models.spec import SpecError

    spec = new_spec(4, {"kind": "pressure", "T": 1, "target_mean": 2.0,
                        "cost_per_decision": {"files": {}}, "identity": {"warning": None},
                        "trained_on": {"data": "real", "recordings": []}, "alpha": 3.0},
                    FLOAT_NAME, "0" * 64)
    assert spec.params.target_mean == 2.0 and spec.training["alpha"] == 3.0
    assert spec.measured.cost_per_decision == {"files": {}}
    assert spec.measured.identity == {"warning": None}
    assert spec.measured.trained_on["data"] == "real"
    assert "cost_per_decision" not in spec.params.to_doc()
    with pytest.raises(SpecError, match=r"metrics: keys \['heldout'\] are not among"):
        new_spec(4, {"kind": "surface", "T": 1, "metrics": {"train": {}, "heldout": {}}},
                 FLOAT_NAME)
    with pytest.raises(SpecError, match=r"params\.target_mean is required for a regressor"):
        new_spec(4, {"kind": "pressure", "T": 1}, FLOAT_NAME)
    spec = new_spec(4, {"kind": "surface", "T": 1, "classes": ["a", "b"],
                        "metrics": {"test": {"accuracy": 0.5}}}, FLOAT_NAME)
    assert spec.metrics == {"train": None, "test": {"accuracy": 0.5}, "cv": None}
    assert spec.profile["name"] == "roboskin" and spec.profile["n_pins"] == 133
