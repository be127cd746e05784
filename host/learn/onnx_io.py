"""Model artefacts on the host: build a model's spec and write ONNX files (the
manifest itself is written by :mod:`device.pi.models.manifest`), and run ONNX models
with ONNX Runtime.

A model folder holds ``model.onnx`` (float32) and, for a quantised model,
``model.int8.onnx`` beside it; :func:`fill_variants` records both in the spec, whose
manifest loads the default variant (the float one has a manifest of its own,
:func:`device.pi.models.manifest.write_variant_specs`).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from device.pi.models.artefact import FEATURE_SPEC_VERSION, ort_session, sha256_file
from device.pi.models.manifest import write_spec
from device.pi.models.params import family_of, field_names
from device.pi.models.spec import (MEASURED_KEYS, METRIC_KEYS, ModelSpec, SpecError,
                                   check_same_profiles, profile_record, profile_source)
from host.data.dataset import atomic_write

__all__ = ["FLOAT_NAME", "INT8_NAME", "json_default", "sklearn_to_onnx", "new_spec",
           "write_model", "fill_variants", "model_bytes", "session", "run_onnx",
           "is_classifier", "spec_profile", "profile_source", "models_profile"]

#: the fields of :class:`ModelSpec` a writer's ``keys`` may set
_SPEC_KEYS = ("task", "model", "classes", "T", "input_layout", "output", "output_kind",
              "uses_imu", "crop_size", "metrics", "config", "training", "files", "variants",
              "variant")

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


def spec_profile(profile) -> dict:
    """The spec's profile record of ``profile``: a built-in name or ``.toml`` path,
    a record already (``profile_record``), or None for the built-in roboskin."""
    if isinstance(profile, dict):
        rec = profile
    else:
        rec = profile_record(profile if profile is not None else "roboskin")
    return {k: rec[k] for k in ("name", "n_pins", "sha256", "toml")}


def models_profile(specs: dict, given=None) -> tuple[str, dict]:
    """(profile name or path, record) of the models ``specs`` ({manifest path: ModelSpec
    or profile record}): the one profile they carry. ``given`` (a profile the user
    named, or None) must be that profile: SpecError naming both files and hashes if
    not, as when two models carry different profiles."""
    recs = {w: (s.profile if isinstance(s, ModelSpec) else s) for w, s in specs.items()}
    rec = check_same_profiles(recs, profile_record(given) if given is not None else None)
    if rec is None:
        rec = profile_record("roboskin")
    return profile_source(rec), rec


def _plain(v):
    """``v`` as plain JSON types (numpy scalars and arrays, paths converted)."""
    return json.loads(json.dumps(v, default=json_default))


def training_record(training: dict) -> dict:
    """A run record for the spec's ``training``: the data summaries' ``window`` named
    ``T`` as everywhere in the spec."""
    out = dict(training)
    for k in ("data", "test_data"):
        if isinstance(out.get(k), dict) and "window" in out[k]:
            out[k] = {("T" if kk == "window" else kk): v for kk, v in out[k].items()}
    return out


def new_spec(n_features: int, keys: dict, onnx: str | None = None,
             sha256: str | None = None, size_bytes: int = 0,
             input_name: str = "x", input_dims: list | None = None) -> ModelSpec:
    """A :class:`ModelSpec` from a writer's ``keys``: ``kind``, ``T`` (required) and
    the spec's fields (task, model (default the kind), classes, metrics (missing ones
    of train/test/cv null), profile (a name, path or record; default roboskin),
    config, training, ...); the measured facts (``trained_on``, ``int8``,
    ``identity``, ``cost_per_decision``) go to ``measured``; the kind's parameters
    (:mod:`device.pi.models.params`) to ``params``; any other key is part of the
    run's record (``training``). The ONNX file ``onnx`` with its checksum, a float32
    input of ``n_features``; no ONNX file for a rule."""
    keys = _plain(dict(keys))
    kind = keys.pop("kind")
    metrics = keys.pop("metrics", None) or {}
    bad = sorted(set(metrics) - set(METRIC_KEYS))
    if bad:
        raise SpecError(f"metrics: keys {bad} are not among {list(METRIC_KEYS)}")
    if "T" not in keys:
        raise SpecError(f"T: a {kind} model's spec needs the frames it reads per window")
    kw = {k: keys.pop(k) for k in _SPEC_KEYS if k in keys}
    kw = {k: v for k, v in kw.items() if v is not None}     # None: the spec's default
    kw.setdefault("task", kind)
    kw.setdefault("model", kind)
    kw.setdefault("classes", [])
    kw.setdefault("input_layout", "vectors")
    profile = spec_profile(keys.pop("profile", None))
    measured = {k: keys.pop(k) for k in MEASURED_KEYS if k in keys and keys[k] is not None}
    names = set(field_names(family_of(kind, kw["model"])))
    params = {k: keys.pop(k) for k in list(keys) if k in names}
    training = dict(kw.pop("training", {}), **keys)        # the rest: the run's record
    return ModelSpec(kind=kind, n_inputs=int(n_features), profile=profile, input_name=input_name,
                     input_dims=list(input_dims) if input_dims else None,
                     metrics={k: metrics.get(k) for k in METRIC_KEYS}, params=params,
                     measured=measured, training=training_record(training),
                     onnx=onnx, sha256={onnx: sha256} if onnx and sha256 else {},
                     size_bytes=int(size_bytes), feature_spec=FEATURE_SPEC_VERSION, **kw)


def write_model(onnx_model, out_dir: Path | str, kind: str, n_features: int,
                extra: dict | None = None, onnx_name: str = FLOAT_NAME,
                input_name: str = "x", input_dims: list | None = None) -> Path:
    """Write ``onnx_model`` (an onnx.ModelProto) and its spec's manifest atomically,
    once; returns the folder."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    data = onnx_model.SerializeToString()
    atomic_write(out / onnx_name, lambda fh: fh.write(data))
    write_spec(out, new_spec(n_features, {"kind": kind, **(extra or {})}, onnx_name,
                             sha256_file(out / onnx_name), len(data), input_name, input_dims))
    return out


def fill_variants(folder: Path | str, spec: ModelSpec, int8: bool) -> dict:
    """Record every model file of ``folder`` in ``spec`` (sha256 and size of
    ``model.onnx`` and, with ``int8``, ``model.int8.onnx``; ``files``, ``variants``),
    the int8 file the default with ``int8``, else the float one. Nothing is written
    (:func:`device.pi.models.manifest.write_variant_specs` writes the manifests).
    Returns the files' records."""
    folder = Path(folder)
    names = {FLOAT_NAME: "float"}
    if int8:
        names[INT8_NAME] = "int8"
    files = {n: {"variant": v, "size_bytes": (folder / n).stat().st_size,
                 "sha256": sha256_file(folder / n)} for n, v in names.items()}
    default = INT8_NAME if int8 else FLOAT_NAME
    spec.sha256 = {n: f["sha256"] for n, f in files.items()}
    spec.files = files
    spec.variants = {f["variant"]: n for n, f in files.items()}
    spec.onnx = default
    spec.variant = names[default]
    spec.size_bytes = files[default]["size_bytes"]
    spec.check("ModelSpec")
    return files


def replace_graphs(folder: Path | str, spec: ModelSpec, new_bytes: dict) -> dict:
    """Write the rewritten graphs ``new_bytes`` (file name -> bytes) of a model
    folder atomically, then record them in ``spec`` (the int8 verdict's byte counts,
    :func:`fill_variants`) and write its manifests. Returns, per file, its
    (old size, new size) in bytes."""
    from device.pi.models.manifest import write_variant_specs
    folder = Path(folder)
    out = {n: ((folder / n).stat().st_size, len(b)) for n, b in new_bytes.items()}
    for name, data in new_bytes.items():
        atomic_write(folder / name, lambda fh, data=data: fh.write(data))
    q = spec.measured.int8
    if INT8_NAME in out and isinstance(q, dict):
        spec.measured.int8 = dict(q, float_bytes=out[FLOAT_NAME][1], int8_bytes=out[INT8_NAME][1])
    fill_variants(folder, spec, INT8_NAME in out and spec.variant == "int8")
    write_variant_specs(folder, spec)
    return out


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
