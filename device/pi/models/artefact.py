"""Deployable model artefacts: one ONNX file plus a JSON manifest.

A pickle is never loaded on the Pi. The manifest names the ONNX file, its SHA-256,
the feature-spec version the model was trained against, and the input layout.
:func:`load_model` refuses a model whose checksum or feature-spec version does not
match, whose files are missing, truncated or corrupt, or whose manifest names a file
that resolves outside the model folder (an absolute path, ``..``, or a link leading
out), with a message that names the file.

manifest.json follows the model spec (:mod:`device.pi.models.spec`, version 2):
:func:`read_manifest` parses it with :meth:`ModelSpec.from_manifest` and refuses an
older manifest or a field out of the schema, naming the file and the field::

    {"format": "tacfoot-model", "version": 2, "kind": "texture", "task": "texture",
     "feature_spec": 1, "onnx": "model.onnx", "sha256": {"model.onnx": "..."},
     "input": {"name": "x", "shape": [null, 3990], "dtype": "float32"}, "T": 15,
     "metrics": {"train": {...}, "test": {...}, "cv": null},
     "profile": {"name": "roboskin", "n_pins": 133, "sha256": "...", "toml": "..."},
     "trained_on": {...}, "config": {...}, ...}
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from device.jsondoc import read_json_doc
from device.pi.models.spec import SPEC_VERSION, ModelSpec, SpecError

FORMAT = "tacfoot-model"
VERSION = SPEC_VERSION
#: bump when the feature code changes what a model sees
FEATURE_SPEC_VERSION = 1
MANIFEST = "manifest.json"
#: the float model's manifest beside an int8 one (quantised models only)
FLOAT_MANIFEST = "manifest.float.json"
#: which ONNX file of a model folder to load
VARIANTS = ("int8", "float")
#: the longest window a model may read, frames (8 s at 120 fps)
MAX_T = 1000


class ModelError(SpecError):
    """A model artefact cannot be used; the message names the file."""


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def model_file(folder: Path | str, name, where: Path | str | None = None) -> Path:
    """The file ``name`` (as a manifest gives it) inside the model ``folder``.
    ModelError (naming ``where``, default the folder) unless it is a relative path
    that, links followed, resolves inside the folder."""
    folder = Path(folder)
    where = where if where is not None else folder
    if not isinstance(name, str) or not name.strip():
        raise ModelError(f"{where}: a model file name must be a non-empty string, got {name!r}")
    path = folder / name
    root = folder.resolve()
    try:
        inside = not Path(name).is_absolute() and path.resolve().is_relative_to(root) \
            and path.resolve() != root
    except (OSError, RuntimeError):         # a link loop
        inside = False
    if not inside:
        raise ModelError(f"{where}: model file {name!r} resolves outside the model folder "
                         f"{folder}; a manifest names files inside its own folder only")
    return path


def checked_model_file(folder: Path, name, sha256: dict, where) -> Path:
    """The file ``name`` a manifest lists, inside ``folder`` (:func:`model_file`),
    present and with the SHA-256 the manifest's ``sha256`` table gives it; a
    ModelError naming the file if not."""
    path = model_file(folder, name, where)
    if not path.is_file():
        raise ModelError(f"{path}: model file missing")
    want = sha256.get(name) if isinstance(sha256, dict) else None
    got = sha256_file(path)
    if want != got:
        raise ModelError(f"{path}: checksum does not match the manifest (file "
                         f"{got[:12]}..., manifest {str(want)[:12]}...); the file is corrupt, "
                         f"truncated or replaced")
    return path


def read_manifest(path: Path | str) -> tuple[dict, Path]:
    """(manifest, folder) from a model folder or a manifest path; the manifest
    follows the model spec (:func:`read_spec`)."""
    doc, mpath = read_json_doc(path, MANIFEST, FORMAT, VERSION, "model", "manifest", ModelError)
    for key in ("onnx", "sha256", "feature_spec", "input"):
        if key not in doc:
            raise ModelError(f"{mpath}: manifest lacks {key!r}")
    check_manifest_types(doc, mpath)
    try:
        ModelSpec.from_manifest(doc, mpath)
    except SpecError as exc:
        raise ModelError(str(exc)) from None
    return doc, mpath.parent


def read_spec(path: Path | str) -> tuple[ModelSpec, Path]:
    """(spec, manifest file) of a model folder or a manifest path; ModelError naming
    the file and the field when it does not follow the model spec."""
    doc, mpath = read_json_doc(path, MANIFEST, FORMAT, VERSION, "model", "manifest", ModelError)
    check_manifest_types(doc, mpath) if all(k in doc for k in ("onnx", "sha256",
                                                               "feature_spec", "input")) else None
    try:
        return ModelSpec.from_manifest(doc, mpath), mpath
    except SpecError as exc:
        raise ModelError(str(exc)) from None


def _whole(v, lo: int, hi: int) -> bool:
    return not isinstance(v, bool) and isinstance(v, int) and lo <= v <= hi


def check_manifest_types(doc: dict, where) -> None:
    """Each field the loaders read has its type and a sane range, or a ModelError
    names the file, the field and the value: ``onnx`` a file name (null for a rule
    model, which has no ONNX file), ``sha256`` a table
    of names to hex digests, ``feature_spec`` a whole number, ``input.shape`` a batch
    dimension then whole-number sizes, ``T`` (when there) 1..:data:`MAX_T` frames,
    ``kind`` and ``model`` (when there) names."""
    def bad(field, why):
        raise ModelError(f"{where}: {field} {why}, got {doc.get(field)!r}"
                         if "." not in field else f"{where}: {field} {why}")
    onnx = doc["onnx"]
    if not (isinstance(onnx, str) and onnx.strip()) and not (onnx is None
                                                             and doc.get("model") == "rule"):
        bad("onnx", "must be the model file's name (null only for a rule model)")
    sha = doc["sha256"]
    if not isinstance(sha, dict) or not all(isinstance(k, str) and isinstance(v, str)
                                            for k, v in sha.items()):
        bad("sha256", "must map file names to SHA-256 hex digests")
    if not _whole(doc["feature_spec"], 0, 1 << 30):
        bad("feature_spec", "must be a whole number")
    inp = doc["input"]
    shape = inp.get("shape") if isinstance(inp, dict) else None
    if (not isinstance(shape, list) or len(shape) < 2
            or not all(_whole(d, 1, 1 << 30) for d in shape[1:])):
        bad("input.shape", f"must be [batch, size, ...] with whole-number sizes, got "
                           f"{shape if isinstance(inp, dict) else inp!r}")
    if "T" in doc and not _whole(doc["T"], 1, MAX_T):
        bad("T", f"must be a whole number of frames in [1, {MAX_T}]")
    for key in ("kind", "model"):
        if key in doc and not isinstance(doc[key], str):
            bad(key, "must be a name")


def manifest_for(folder: Path | str, variant: str) -> Path:
    """The manifest to load from a model folder: ``manifest.json`` (int8 when the
    model was quantised) or, for the ``float`` variant, ``manifest.float.json`` when
    there is one. A folder with no manifest is returned as it is (the loader then
    names the missing file)."""
    if variant not in VARIANTS:
        raise ValueError(f"variant must be one of {list(VARIANTS)}, got variant={variant!r}")
    folder = Path(folder)
    if variant == "float" and (folder / FLOAT_MANIFEST).is_file():
        return folder / FLOAT_MANIFEST
    return folder / MANIFEST if (folder / MANIFEST).is_file() else folder


def ort_session(model: str | bytes, threads: int = 1):
    """The one ONNX Runtime set-up: a CPU session with ``threads`` intra-op threads,
    one inter-op thread and quiet logging, for a model file path or its bytes."""
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    so.log_severity_level = 3
    return ort.InferenceSession(model, sess_options=so, providers=["CPUExecutionProvider"])


class BoundRun:
    """A session run over a fixed input buffer ``x``: the first call runs it the plain
    way, then the session is bound to ``x`` and to a preallocated output shaped as
    that first output (an ONNX Runtime I/O binding), so later calls read ``x`` in
    place and build no feed dict, input checks or output array. A session without
    I/O binding keeps ``run``. Returns the output (the bound buffer: read it before
    the next call)."""

    def __init__(self, session, input_name: str, x: np.ndarray, output_name: str):
        self.session = session
        self.input_name = input_name
        self.x = x
        self.output_name = output_name
        self._binding = None
        self._out = None

    def __call__(self) -> np.ndarray:
        if self._binding:
            self.session.run_with_iobinding(self._binding)
            return self._out
        out = np.asarray(self.session.run([self.output_name], {self.input_name: self.x})[0])
        if self._binding is None:
            self._bind(out)
        return out

    def _bind(self, out: np.ndarray) -> None:
        try:
            b = self.session.io_binding()
            b.bind_cpu_input(self.input_name, self.x)
            self._out = np.empty(out.shape, out.dtype)
            b.bind_output(self.output_name, "cpu", 0, self._out.dtype, list(self._out.shape),
                          self._out.ctypes.data)
        except Exception:              # a session without I/O binding
            self._binding = False
            return
        self._binding = b


@dataclass
class Model:
    """An ONNX Runtime session (single thread) with its manifest."""
    manifest: dict
    path: Path
    session: object
    input_name: str

    @property
    def spec(self) -> ModelSpec:
        return ModelSpec.from_manifest(self.manifest, self.path / MANIFEST)

    def run(self, x: np.ndarray) -> list[np.ndarray]:
        return self.session.run(None, {self.input_name: x})

    @property
    def kind(self) -> str:
        return self.manifest.get("kind", "")


def load_model(path: Path | str, expect_kind: str | None = None,
               feature_spec: int = FEATURE_SPEC_VERSION, threads: int = 1) -> Model:
    doc, folder = read_manifest(path)
    if int(doc["feature_spec"]) != feature_spec:
        raise ModelError(f"{folder / MANIFEST}: feature-spec version {doc['feature_spec']} "
                         f"does not match this runtime's {feature_spec}; retrain the model")
    if expect_kind is not None and doc.get("kind") != expect_kind:
        raise ModelError(f"{folder / MANIFEST}: kind is {doc.get('kind')!r}, "
                         f"expected {expect_kind!r}")
    onnx_path = checked_model_file(folder, doc["onnx"], doc["sha256"], folder / MANIFEST)
    try:
        sess = ort_session(str(onnx_path), threads)
    except Exception as exc:  # onnxruntime raises its own exception types
        raise ModelError(f"{onnx_path}: ONNX Runtime cannot load it ({exc})") from None
    return Model(doc, folder, sess, sess.get_inputs()[0].name)
