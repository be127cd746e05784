"""Deployable model artefacts: one ONNX file plus a JSON manifest.

A pickle is never loaded on the Pi. The manifest names the ONNX file, its SHA-256,
the feature-spec version the model was trained against, and the input layout.
:func:`load_model` refuses a model whose checksum or feature-spec version does not
match, whose files are missing, truncated or corrupt, or whose manifest names a file
that resolves outside the model folder (an absolute path, ``..``, or a link leading
out), with a message that names the file.

The manifest follows the model spec (:mod:`device.pi.models.spec`) and is read by
:mod:`device.pi.models.manifest`, the one module that names the file; a loaded
:class:`Model` carries its :class:`~device.pi.models.spec.ModelSpec`.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from device.pi.models.manifest import read_spec
from device.pi.models.spec import FORMAT, MAX_T, ModelError, ModelSpec

__all__ = ["FORMAT", "MAX_T", "FEATURE_SPEC_VERSION", "ModelError", "Model", "load_model",
           "model_file", "checked_model_file", "sha256_file", "ort_session", "BoundRun"]

#: bump when the feature code changes what a model sees
FEATURE_SPEC_VERSION = 1


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
    """An ONNX Runtime session (single thread) with its spec; ``path`` is the model
    folder and ``source`` the manifest file it was loaded from."""
    spec: ModelSpec
    path: Path
    session: object
    input_name: str
    source: Path

    def run(self, x: np.ndarray) -> list[np.ndarray]:
        return self.session.run(None, {self.input_name: x})

    @property
    def kind(self) -> str:
        return self.spec.kind


def load_model(path: Path | str, expect_kind: str | None = None,
               feature_spec: int = FEATURE_SPEC_VERSION, threads: int = 1) -> Model:
    """The model of a folder or manifest path: its spec, its ONNX file checked
    against the spec's checksum, in a session. ModelError naming the manifest
    actually read (``manifest.float.json`` for the float variant)."""
    spec, mpath = read_spec(path)
    folder = mpath.parent
    if spec.feature_spec != feature_spec:
        raise ModelError(f"{mpath}: feature-spec version {spec.feature_spec} does not match "
                         f"this runtime's {feature_spec}; retrain the model")
    if expect_kind is not None and spec.kind != expect_kind:
        raise ModelError(f"{mpath}: kind is {spec.kind!r}, expected {expect_kind!r}")
    onnx_path = checked_model_file(folder, spec.onnx, spec.sha256, mpath)
    try:
        sess = ort_session(str(onnx_path), threads)
    except Exception as exc:  # onnxruntime raises its own exception types
        raise ModelError(f"{onnx_path}: ONNX Runtime cannot load it ({exc})") from None
    return Model(spec, folder, sess, sess.get_inputs()[0].name, mpath)
