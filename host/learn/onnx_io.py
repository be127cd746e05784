"""Write model artefacts (ONNX + manifest.json) that ``device.pi.models.artefact`` loads."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from device.pi.models.artefact import FEATURE_SPEC_VERSION, FORMAT, MANIFEST, VERSION, sha256_file
from host.data.dataset import atomic_write, atomic_write_text


def sklearn_to_onnx(estimator, n_features: int, input_name: str = "x"):
    """Convert a fitted scikit-learn estimator or pipeline (scaler folded in)."""
    from skl2onnx import convert_sklearn
    from skl2onnx.common.data_types import FloatTensorType

    return convert_sklearn(estimator, initial_types=[(input_name, FloatTensorType(
        [None, n_features]))], target_opset=17)


def write_model(onnx_model, out_dir: Path | str, kind: str, n_features: int,
                extra: dict | None = None, onnx_name: str = "model.onnx",
                input_name: str = "x") -> Path:
    """Write ``onnx_model`` (an onnx.ModelProto) and its manifest atomically."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    data = onnx_model.SerializeToString()
    atomic_write(out / onnx_name, lambda fh: fh.write(data))
    manifest = {"format": FORMAT, "version": VERSION, "kind": kind,
                "feature_spec": FEATURE_SPEC_VERSION, "onnx": onnx_name,
                "sha256": {onnx_name: sha256_file(out / onnx_name)},
                "size_bytes": len(data),
                "input": {"name": input_name, "shape": [None, int(n_features)],
                          "dtype": "float32"}}
    manifest.update(extra or {})
    atomic_write_text(out / MANIFEST, json.dumps(manifest, indent=1, default=_plain))
    return out


def _plain(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o).__name__)
