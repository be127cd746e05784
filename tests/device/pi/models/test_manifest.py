"""device/pi/models/manifest.py: the one module that names, reads and writes a model's
manifest; a manifest round-trips through the typed spec, and a bad one is one line
naming the file, the field and the value."""
from __future__ import annotations

import json
import re

import pytest

from device.pi.models.manifest import (FLOAT_MANIFEST, MANIFEST, read_spec, write_spec,
                                       write_variant_specs)
from device.pi.models.spec import ModelError, ModelSpec, profile_record
from tests import REPO_ROOT


def _spec(**kw) -> ModelSpec:
    base = dict(kind="pressure", task="pressure", model="ridge", classes=[], T=3,
                input_layout="vectors", n_inputs=4, profile=profile_record("roboskin"),
                output="variable", output_kind="value", onnx="model.onnx",
                sha256={"model.onnx": "0" * 64},
                params={"target_mean": 1.5, "input_clip": [[0, 0, 0, 0], [1, 1, 1, 1]]},
                measured={"int8": {"agreement": 1.0}, "cost_per_decision": {"files": {}}})
    base.update(kw)
    return ModelSpec(**base)


def test_a_manifest_round_trips_through_the_typed_spec(tmp_path):
    spec = _spec()
    path = write_spec(tmp_path, spec)
    assert path == tmp_path / MANIFEST
    back, where = read_spec(tmp_path)
    assert where == path and back.to_manifest() == spec.to_manifest()
    assert back.params.target_mean == 1.5 and back.params.input_clip[1] == [1, 1, 1, 1]
    assert back.measured.int8 == {"agreement": 1.0}
    # written once more from what was read: the same bytes
    before = path.read_bytes()
    write_spec(tmp_path, back)
    assert path.read_bytes() == before


@pytest.mark.parametrize("edit, field, value", [
    (lambda d: d["params"].update(colour="red"), "params.colour", "'red'"),      # unknown
    (lambda d: d["params"].pop("target_mean"), "params.target_mean", "nothing"),  # missing
    (lambda d: d["params"].update(target_mean="high"), "params.target_mean", "'high'"),
    (lambda d: d["params"].update(input_clip=[[0], [1]]), "params.input_clip", "[1, 1]"),
    (lambda d: d.update(T="3"), "T", "'3'"),                                      # mistyped
    (lambda d: d.update(cost_per_decision={}), "cost_per_decision", "{}"),        # unknown
    (lambda d: d["measured"].update(int8=0.99), "measured.int8", "0.99"),
])
def test_an_unknown_missing_or_mistyped_field_is_one_line_naming_file_field_and_value(
        tmp_path, edit, field, value):
    write_spec(tmp_path, _spec())
    doc = json.loads((tmp_path / MANIFEST).read_text())
    edit(doc)
    (tmp_path / MANIFEST).write_text(json.dumps(doc))
    with pytest.raises(ModelError) as err:
        read_spec(tmp_path)
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith(f"{tmp_path / MANIFEST}: {field} ")
    assert value in msg


def test_the_float_variant_gets_its_own_manifest_from_the_one_spec(tmp_path):
    files = {"model.onnx": {"variant": "float", "size_bytes": 10, "sha256": "1" * 64},
             "model.int8.onnx": {"variant": "int8", "size_bytes": 4, "sha256": "2" * 64}}
    spec = _spec(onnx="model.int8.onnx", variant="int8", size_bytes=4, files=files,
                 sha256={n: f["sha256"] for n, f in files.items()},
                 variants={"float": "model.onnx", "int8": "model.int8.onnx"})
    write_variant_specs(tmp_path, spec)
    fspec, where = read_spec(tmp_path / FLOAT_MANIFEST)
    assert where.name == FLOAT_MANIFEST
    assert (fspec.onnx, fspec.variant, fspec.size_bytes) == ("model.onnx", "float", 10)
    assert fspec.params == spec.params and fspec.measured == spec.measured
    spec.variant, spec.onnx = "float", "model.onnx"
    write_variant_specs(tmp_path, spec)
    assert not (tmp_path / FLOAT_MANIFEST).exists()        # a stale one is removed


def test_no_module_but_this_one_names_the_manifest_file():
    """The file name is a constant of device.pi.models.manifest; no other module of
    the packages writes it (nor edits a manifest's JSON by its name)."""
    name = re.compile(re.escape(MANIFEST))
    own = REPO_ROOT / "device" / "pi" / "models" / "manifest.py"
    named = sorted(str(p.relative_to(REPO_ROOT)) for pkg in ("device", "host")
                   for p in (REPO_ROOT / pkg).rglob("*.py")
                   if p != own and name.search(p.read_text()))
    assert named == []
    assert name.search(own.read_text())
