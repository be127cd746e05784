"""Model artefacts on the host: write ONNX + manifest.json (the one manifest writer,
read back by ``device.pi.models.artefact``) and run ONNX models with ONNX Runtime.

A model folder holds ``model.onnx`` (float32) and, for a quantised model,
``model.int8.onnx`` beside it; ``manifest.json`` loads the default variant and
``manifest.float.json`` the float one (:func:`write_variants`).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from device.pi.models.artefact import (FEATURE_SPEC_VERSION, FLOAT_MANIFEST, FORMAT, MANIFEST,
                                      VERSION, ort_session, sha256_file)
from host.data.dataset import atomic_write, atomic_write_text

__all__ = ["FLOAT_NAME", "INT8_NAME", "FLOAT_MANIFEST", "json_default", "sklearn_to_onnx",
           "new_manifest", "write_manifest", "write_model", "write_variants", "model_bytes",
           "session", "run_onnx", "is_classifier"]

FLOAT_NAME = "model.onnx"
INT8_NAME = "model.int8.onnx"


def json_default(o):
    """``json.dumps(default=...)`` for numpy scalars and arrays and paths."""
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")


def sklearn_to_onnx(estimator, n_features: int, input_name: str = "x"):
    """Convert a fitted scikit-learn estimator or pipeline (scaler folded in)."""
    from skl2onnx import convert_sklearn
    from skl2onnx.common.data_types import FloatTensorType

    return convert_sklearn(estimator, initial_types=[(input_name, FloatTensorType(
        [None, n_features]))], target_opset=17)


def new_manifest(n_features: int, keys: dict, onnx: str | None = None,
                 sha256: str | None = None, size_bytes: int = 0, input_name: str = "x") -> dict:
    """A manifest: the keys :func:`device.pi.models.artefact.read_manifest` needs (format,
    version, feature spec, the ONNX file and its checksum, a float32 input of
    ``n_features``; no ONNX file for a rule), updated with ``keys``."""
    return {"format": FORMAT, "version": VERSION, "feature_spec": FEATURE_SPEC_VERSION,
            "onnx": onnx, "sha256": {onnx: sha256} if onnx else {}, "size_bytes": size_bytes,
            "input": {"name": input_name, "shape": [None, int(n_features)], "dtype": "float32"},
            **keys}


def write_manifest(folder: Path | str, doc: dict, name: str = MANIFEST) -> Path:
    """Write ``doc`` as ``folder/name`` atomically; returns the path."""
    path = Path(folder) / name
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps(doc, indent=1, default=json_default))
    return path


def write_model(onnx_model, out_dir: Path | str, kind: str, n_features: int,
                extra: dict | None = None, onnx_name: str = FLOAT_NAME,
                input_name: str = "x") -> Path:
    """Write ``onnx_model`` (an onnx.ModelProto) and its manifest atomically."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    data = onnx_model.SerializeToString()
    atomic_write(out / onnx_name, lambda fh: fh.write(data))
    write_manifest(out, new_manifest(n_features, {"kind": kind, **(extra or {})}, onnx_name,
                                     sha256_file(out / onnx_name), len(data), input_name))
    return out


def write_variants(folder: Path | str, int8: bool, updates: dict | None = None) -> dict:
    """Record every model file of ``folder`` in its manifest.json (sha256 and size
    of ``model.onnx`` and, with ``int8``, ``model.int8.onnx``; ``variants``), with
    ``updates`` merged in. With ``int8`` the manifest loads the int8 file and
    ``manifest.float.json`` the float one; without, the float file is the default
    and a stale ``manifest.float.json`` is removed. Returns the files' records."""
    folder = Path(folder)
    names = {FLOAT_NAME: "float"}
    if int8:
        names[INT8_NAME] = "int8"
    files = {n: {"variant": v, "size_bytes": (folder / n).stat().st_size,
                 "sha256": sha256_file(folder / n)} for n, v in names.items()}
    default = INT8_NAME if int8 else FLOAT_NAME
    doc = json.loads((folder / MANIFEST).read_text())
    doc.update(updates or {})
    doc.update({"sha256": {n: f["sha256"] for n, f in files.items()}, "files": files,
                "variants": {f["variant"]: n for n, f in files.items()},
                "onnx": default, "variant": names[default],
                "size_bytes": files[default]["size_bytes"]})
    write_manifest(folder, doc)
    if int8:
        write_manifest(folder, dict(doc, onnx=FLOAT_NAME, variant="float",
                                    size_bytes=files[FLOAT_NAME]["size_bytes"]), FLOAT_MANIFEST)
    else:
        (folder / FLOAT_MANIFEST).unlink(missing_ok=True)
    return files


def model_bytes(m) -> bytes:
    """The serialised model of a ModelProto, bytes or a path."""
    if hasattr(m, "SerializeToString"):
        return m.SerializeToString()
    if isinstance(m, bytes):
        return m
    return Path(m).read_bytes()


def session(model, threads: int = 1):
    """:func:`device.pi.models.artefact.ort_session` (the Pi's set-up) for a
    ModelProto, bytes or a path."""
    src = model_bytes(model) if not isinstance(model, (str, Path)) else str(model)
    return ort_session(src, threads)


def is_classifier(sess) -> bool:
    """Whether the session's model has a ``probabilities`` output."""
    return "probabilities" in [o.name for o in sess.get_outputs()]


def run_onnx(sess, X: np.ndarray, batch: int = 1024) -> np.ndarray:
    """float64 probabilities (N, C) of a classifier or values (N,) of a regressor."""
    names = [o.name for o in sess.get_outputs()]
    out = "probabilities" if "probabilities" in names else names[0]
    inp = sess.get_inputs()[0].name
    parts = [sess.run([out], {inp: np.ascontiguousarray(X[i:i + batch], np.float32)})[0]
             for i in range(0, len(X), batch)]
    res = np.concatenate(parts) if parts else np.zeros((0,), np.float32)
    return res.astype(np.float64) if out == "probabilities" else res.reshape(-1).astype(
        np.float64)
