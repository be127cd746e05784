"""A model folder's manifest files: the one module that names, reads and writes them.

:data:`MANIFEST` loads a model folder's default variant and :data:`FLOAT_MANIFEST`
the float file beside an int8 default. Each is a :class:`~device.pi.models.spec.ModelSpec`
document: :func:`read_spec` gives the spec (one-line errors naming the file, the
field and the value), :func:`write_spec` writes one atomically after checking that
it reads back, and :func:`write_variant_specs` writes both variants of a folder
from one spec. No other module names the files or edits their JSON.
"""
from __future__ import annotations

import json
from pathlib import Path

from device.jsondoc import read_json_doc
from device.pi.models.spec import SPEC_VERSION, FORMAT, ModelError, ModelSpec, SpecError

__all__ = ["MANIFEST", "FLOAT_MANIFEST", "VARIANTS", "read_spec", "write_spec",
           "write_variant_specs", "manifest_for", "manifest_path", "has_manifest"]

#: the manifest of a model folder: the one place its name is written
MANIFEST = "manifest.json"
#: the float model's manifest beside an int8 one (quantised models only)
FLOAT_MANIFEST = "manifest.float.json"
#: which ONNX file of a model folder to load
VARIANTS = ("int8", "float")


def manifest_for(folder: Path | str, variant: str) -> Path:
    """The manifest to load from a model folder: :data:`MANIFEST` (int8 when the
    model was quantised) or, for the ``float`` variant, :data:`FLOAT_MANIFEST` when
    there is one. A folder with no manifest is returned as it is (the reader then
    names the missing file)."""
    if variant not in VARIANTS:
        raise ValueError(f"variant must be one of {list(VARIANTS)}, got variant={variant!r}")
    folder = Path(folder)
    if variant == "float" and (folder / FLOAT_MANIFEST).is_file():
        return folder / FLOAT_MANIFEST
    return folder / MANIFEST if (folder / MANIFEST).is_file() else folder


def has_manifest(folder: Path | str) -> bool:
    """Whether ``folder`` holds a model's :data:`MANIFEST`."""
    return (Path(folder) / MANIFEST).is_file()


def manifest_path(path: Path | str) -> Path:
    """The manifest file of a model folder or of a manifest path."""
    path = Path(path)
    return path / MANIFEST if path.is_dir() else path


def read_spec(path: Path | str) -> tuple[ModelSpec, Path]:
    """(spec, manifest file) of a model folder (its :data:`MANIFEST`) or a manifest
    path; ModelError naming the file, the field and the value when it is missing,
    not JSON or off the model spec."""
    doc, mpath = read_json_doc(path, MANIFEST, FORMAT, SPEC_VERSION, "model", "manifest",
                               ModelError)
    try:
        return ModelSpec.from_manifest(doc, mpath), mpath
    except SpecError as exc:
        raise ModelError(str(exc)) from None


def _json_value(o):
    """``json.dumps(default=...)`` for numpy scalars and arrays and paths."""
    if hasattr(o, "tolist"):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")


def write_spec(folder: Path | str, spec: ModelSpec, name: str = MANIFEST) -> Path:
    """Write ``spec`` as the manifest ``folder/name`` (default :data:`MANIFEST`),
    atomically (a reader sees the old file or the new one), after checking that it
    reads back as the same spec; returns the path."""
    import os

    path = Path(folder) / name
    text = json.dumps(spec.to_manifest(), indent=1, default=_json_value)
    ModelSpec.from_manifest(json.loads(text), path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "w") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def write_variant_specs(folder: Path | str, spec: ModelSpec) -> list[Path]:
    """Write a model folder's manifests from one spec: :data:`MANIFEST` loads the
    spec's default ``variant``; with an int8 default, :data:`FLOAT_MANIFEST` loads
    the float file (``variants["float"]``), else a stale one is removed."""
    import dataclasses

    folder = Path(folder)
    out = [write_spec(folder, spec)]
    if spec.variant == "int8" and spec.variants and "float" in spec.variants:
        fname = spec.variants["float"]
        size = ((spec.files or {}).get(fname) or {}).get("size_bytes", spec.size_bytes)
        out.append(write_spec(folder, dataclasses.replace(spec, onnx=fname, variant="float",
                                                          size_bytes=int(size)),
                              FLOAT_MANIFEST))
    else:
        (folder / FLOAT_MANIFEST).unlink(missing_ok=True)
    return out
