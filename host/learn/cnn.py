"""The paper's CNN over T stacked binary frames, trained with PyTorch on the CPU.

The input is a window of T binary dome crops, downscaled to S x S
(:attr:`host.data.windows.WindowSet.frames`), encoded by the Pi's own
:func:`device.pi.models.window.encode_frames`: (N, T, S, S) float32 in 0..1, the T frames
as input channels (manifest ``input_layout: "frames"``). The network, as in the
paper, uses 8 x 8 filters, a 1000-unit hidden layer and dropout 0.2::

    x (N, T, S, S)
    -> Conv2d(T -> filters, 8 x 8, stride 2, padding 3) -> ReLU -> MaxPool(pool)
    -> flatten (filters * (S/2/pool)^2; 8 * 4 * 4 = 128 for S = 32)
    -> Dropout(0.2) -> Linear(-> hidden = 1000) -> ReLU -> Dropout(0.2)
    -> Linear(-> classes) -> Softmax           (output "probabilities" (N, C))

The convolutional part is kept small (8 filters, stride 2, a 4 x 4 pool) so that
the model stays under 1 MB in float32 with the full 1000-unit layer: about 134k
parameters, ~0.54 MB of ONNX for T = 3 and S = 32. ``hidden`` is a constructor
parameter; ``hidden=256`` gives a ~0.14 MB model for a tighter budget.

Training is deterministic: a fixed seed (weights, batch order and dropout), two
threads (``torch.set_num_threads(2)``) and ``torch.use_deterministic_algorithms``;
the caller's torch RNG, thread count and determinism setting are restored after.
The model is exported with ``torch.onnx.export`` (opset 17, a dynamic batch axis)
and written by :func:`host.learn.onnx_io.write_model` as ONNX + its manifest; the Pi
loads it with :func:`device.pi.models.artefact.load_model`. ONNX Runtime's output is
checked against torch's on training and held-out windows (``ONNX_ATOL``).

PyTorch is optional (the ``cnn`` extra): it is imported only inside functions, and
without it :func:`require_torch` raises an ImportError that says how to install it.
"""
from __future__ import annotations

import os
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from device.checks import finite_number, positive_number
from device.pi.models.manifest import has_manifest, read_spec, write_variant_specs
from host.data.windows import CLASS_TASKS
from host.extras import MissingExtra
from host.learn.metrics import label_metrics
from host.learn.onnx_io import (FLOAT_NAME, INT8_NAME, fill_variants, run_onnx, session,
                                write_model)
from host.learn.quantise import quantise_model
from host.learn.tasks import check_int

__all__ = ["MODEL", "OUTPUT_NAME", "INPUT_NAME", "ONNX_ATOL", "FrameCNN", "require_torch",
           "train_cnn", "cnn_spec_keys", "quantise_cnn", "frames_input"]

MODEL = "cnn"
INPUT_NAME = "x"
OUTPUT_NAME = "probabilities"
OPSET = 17
#: ONNX Runtime and torch must agree this closely (probabilities)
ONNX_ATOL = 1e-4
TRAIN_THREADS = 2
INSTALL_HINT = "pip install .[cnn]   (or: pip install torch==2.13.0, the CPU build)"


def require_torch():
    """Import and return ``torch``, or raise :class:`~host.extras.MissingExtra` (an
    ImportError) naming the ``cnn`` extra."""
    try:
        import torch
    except ImportError as exc:
        raise MissingExtra("torch", "cnn", f"the CNN model needs PyTorch: {INSTALL_HINT}; "
                                           f"missing: {exc}") from exc
    return torch


def frames_input(frames: np.ndarray) -> np.ndarray:
    """(N, T, S, S) uint8 crops -> the CNN input, exactly as the Pi builds it."""
    from device.pi.models.window import encode_frames

    if frames is None:
        raise ValueError("frames is None: the windows carry no binary crops; load the data "
                         "with frame_size > 0 (host.data.load.load_spec(..., frame_size=32))")
    f = np.asarray(frames)
    if f.ndim not in (3, 4) or f.shape[-1] != f.shape[-2]:
        raise ValueError(f"frames must have shape (N, T, S, S) or (T, S, S), got {f.shape}")
    return encode_frames(f)


# ----------------------------------------------------------------------------
# Parameters
# ----------------------------------------------------------------------------

def conv_out(size: int, kernel: int, stride: int, pool: int) -> int:
    """Side of the feature map after the conv (padding (kernel - stride) // 2) and pool."""
    pad = max(0, (kernel - stride) // 2)
    c = (size + 2 * pad - kernel) // stride + 1
    return c // pool if c > 0 else 0


# ----------------------------------------------------------------------------
# The estimator
# ----------------------------------------------------------------------------

def _build_net(torch, T: int, S: int, n_classes: int, est: "FrameCNN"):
    """The network of the FrameCNN ``est``'s sizes for T frames of S x S."""
    nn = torch.nn
    filters, kernel, stride, pool = est.filters, est.kernel, est.stride, est.pool
    hidden, dropout = est.hidden, est.dropout
    side = conv_out(S, kernel, stride, pool)
    return nn.Sequential(
        nn.Conv2d(T, filters, kernel, stride=stride, padding=max(0, (kernel - stride) // 2)),
        nn.ReLU(),
        nn.MaxPool2d(pool),
        nn.Flatten(),
        nn.Dropout(dropout),
        nn.Linear(filters * side * side, hidden),
        nn.ReLU(),
        nn.Dropout(dropout),
        nn.Linear(hidden, n_classes),
    )


class _TorchState:
    """Fix torch's threads, determinism and RNG for a block; restore them after."""

    def __init__(self, torch, seed: int | None, threads: int):
        self.torch, self.seed, self.threads = torch, seed, threads

    def __enter__(self):
        t = self.torch
        self._threads = t.get_num_threads()
        self._det = t.are_deterministic_algorithms_enabled()
        self._rng = t.random.get_rng_state()
        t.set_num_threads(self.threads)
        t.use_deterministic_algorithms(True)
        if self.seed is not None:
            t.manual_seed(self.seed)
        return self

    def __exit__(self, *exc):
        t = self.torch
        t.random.set_rng_state(self._rng)
        t.use_deterministic_algorithms(self._det)
        t.set_num_threads(self._threads)
        return False


class FrameCNN:
    """The paper's CNN over T stacked binary frames; scikit-learn style.

    ``fit(X, y)`` takes X = :func:`frames_input` of the windows, (N, T, S, S) float32
    in 0..1, and y the labels (N,) (strings). ``predict_proba`` gives softmax
    probabilities over ``classes_``; ``to_onnx`` gives the deployable ONNX model.

    Parameters: ``filters`` 8 x 8 (``kernel``) conv filters with ``stride`` and a
    ``pool`` x ``pool`` max pool; ``hidden`` units (the paper's 1000) with ``dropout``;
    Adam with ``lr`` and ``weight_decay`` for ``epochs`` over batches of
    ``batch_size``; ``seed`` fixes weights, batch order and dropout; ``threads``
    torch threads while training and predicting.
    """

    def __init__(self, filters: int = 8, kernel: int = 8, stride: int = 2, pool: int = 4,
                 hidden: int = 1000, dropout: float = 0.2, epochs: int = 20,
                 batch_size: int = 64, lr: float = 1e-3, weight_decay: float = 1e-4,
                 seed: int = 0, threads: int = TRAIN_THREADS, progress: bool = False):
        self.filters = filters
        self.kernel = kernel
        self.stride = stride
        self.pool = pool
        self.hidden = hidden
        self.dropout = dropout
        self.epochs = epochs
        self.batch_size = batch_size
        self.lr = lr
        self.weight_decay = weight_decay
        self.seed = seed
        self.threads = threads
        self.progress = progress

    def get_params(self) -> dict:
        return {k: getattr(self, k) for k in (
            "filters", "kernel", "stride", "pool", "hidden", "dropout", "epochs",
            "batch_size", "lr", "weight_decay", "seed", "threads")}

    def _check_params(self) -> None:
        for name, lo in (("filters", 1), ("kernel", 1), ("stride", 1), ("pool", 1),
                         ("hidden", 1), ("epochs", 1), ("batch_size", 1), ("seed", 0),
                         ("threads", 1)):
            check_int(name, getattr(self, name), lo)
        finite_number("dropout", self.dropout, 0.0, 1.0, hi_open=True)
        positive_number("lr", self.lr)
        finite_number("weight_decay", self.weight_decay, 0.0)

    @staticmethod
    def _check_X(X, name: str = "X") -> np.ndarray:
        X = np.asarray(X)
        if X.ndim != 4 or X.shape[2] != X.shape[3]:
            raise ValueError(f"{name} must have shape (N, T, S, S) (frames_input of the "
                             f"windows), got {X.shape}")
        X = np.ascontiguousarray(X, dtype=np.float32)
        if not np.isfinite(X).all():
            raise ValueError(f"{name} has {int((~np.isfinite(X)).sum())} non-finite values; "
                             f"build it with frames_input / encode_frames")
        return X

    # -- fitting ---------------------------------------------------------

    def fit(self, X, y, classes=None) -> "FrameCNN":
        torch = require_torch()
        self._check_params()
        X = self._check_X(X)
        y = np.asarray(y).astype(str)
        if y.shape != (len(X),):
            raise ValueError(f"y must have shape ({len(X)},) to match X, got {y.shape}")
        if len(X) == 0:
            raise ValueError("no training windows (X is empty)")
        extra = [] if classes is None else [str(c) for c in classes]
        cls = sorted(set(y.tolist()) | set(extra))
        if len(set(y.tolist())) < 2:
            raise ValueError(f"the CNN needs at least 2 classes in the training data, got "
                             f"{sorted(set(y.tolist()))}")
        N, T, S, _ = X.shape
        side = conv_out(S, self.kernel, self.stride, self.pool)
        if side < 1:
            raise ValueError(f"frames of S={S} px are too small for kernel={self.kernel}, "
                             f"stride={self.stride}, pool={self.pool}")
        self.classes_ = cls
        self.window_ = int(T)
        self.frame_size_ = int(S)
        index = {c: i for i, c in enumerate(cls)}
        yi = np.array([index[v] for v in y], np.int64)
        rng = np.random.default_rng(self.seed)
        self.loss_ = []
        with _TorchState(torch, self.seed, self.threads):
            net = _build_net(torch, T, S, len(cls), self)
            opt = torch.optim.Adam(net.parameters(), lr=self.lr,
                                   weight_decay=self.weight_decay)
            loss_fn = torch.nn.CrossEntropyLoss()
            Xt, yt = torch.from_numpy(X), torch.from_numpy(yi)
            bs = min(self.batch_size, N)
            from tqdm import tqdm

            net.train()
            with tqdm(range(self.epochs), desc="cnn", unit="epoch", file=sys.stderr,
                      disable=not self.progress or None, leave=False) as bar:
                for _ in bar:
                    order = torch.from_numpy(rng.permutation(N))
                    total = 0.0
                    for s in range(0, N, bs):
                        b = order[s:s + bs]
                        if len(b) < 2 and s > 0:   # a batch of one adds only noise
                            continue
                        opt.zero_grad()
                        loss = loss_fn(net(Xt[b]), yt[b])
                        loss.backward()
                        opt.step()
                        total += float(loss.detach()) * len(b)
                    self.loss_.append(total / N)
                    bar.set_postfix(loss=f"{self.loss_[-1]:.4f}")
            net.eval()
        self.net_ = net
        self.n_params_ = int(sum(p.numel() for p in net.parameters()))
        return self

    # -- prediction ------------------------------------------------------

    def _check_fitted(self) -> None:
        if not hasattr(self, "net_"):
            raise RuntimeError("FrameCNN is not fitted; call fit(X, y) first")

    def predict_proba(self, X, batch: int = 512) -> np.ndarray:
        """Softmax probabilities (N, C) float32 over ``classes_``, from torch."""
        self._check_fitted()
        torch = require_torch()
        X = self._check_X(X)
        if X.shape[1:] != (self.window_, self.frame_size_, self.frame_size_):
            raise ValueError(f"X windows have shape {X.shape[1:]}, the model was fitted on "
                             f"{(self.window_, self.frame_size_, self.frame_size_)}")
        out = np.empty((len(X), len(self.classes_)), np.float32)
        with _TorchState(torch, None, self.threads), torch.no_grad():
            self.net_.eval()
            for s in range(0, len(X), batch):
                out[s:s + batch] = torch.softmax(
                    self.net_(torch.from_numpy(X[s:s + batch])), dim=1).numpy()
        return out

    def predict(self, X) -> np.ndarray:
        """The most probable class of each window, (N,) object array of ``classes_``."""
        self._check_fitted()
        return np.asarray(self.classes_, object)[self.predict_proba(X).argmax(axis=1)]

    # -- export ----------------------------------------------------------

    def to_onnx(self):
        """The fitted network with a softmax, as an onnx.ModelProto (opset 17, input
        ``x`` (batch, T, S, S) float32, output ``probabilities`` (batch, C))."""
        self._check_fitted()
        torch = require_torch()
        import onnx

        net = torch.nn.Sequential(self.net_, torch.nn.Softmax(dim=1)).eval()
        dummy = torch.zeros(1, self.window_, self.frame_size_, self.frame_size_)
        with tempfile.TemporaryDirectory(prefix="tacfoot-cnn-") as tmp, \
                _TorchState(torch, None, self.threads), warnings.catch_warnings():
            warnings.simplefilter("ignore")        # the TorchScript exporter's deprecation
            path = os.path.join(tmp, "model.onnx")
            # dynamo=False: the TorchScript exporter needs no onnxscript package
            torch.onnx.export(net, (dummy,), path, dynamo=False, opset_version=OPSET,
                              input_names=[INPUT_NAME], output_names=[OUTPUT_NAME],
                              dynamic_axes={INPUT_NAME: {0: "batch"},
                                            OUTPUT_NAME: {0: "batch"}},
                              do_constant_folding=True)
            model = onnx.load(path)
        model.doc_string = (f"tacfoot CNN: {self.window_} binary frames "
                            f"{self.frame_size_}x{self.frame_size_} -> softmax over "
                            f"{self.classes_}")
        onnx.checker.check_model(model)
        return model


# ----------------------------------------------------------------------------
# Checks
# ----------------------------------------------------------------------------

def _check_rows(n: int, k: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.sort(rng.choice(n, size=min(n, k), replace=False))


# ----------------------------------------------------------------------------
# Training entry point
# ----------------------------------------------------------------------------

def train_cnn(ws_train, ws_test=None, seed: int = 0, out_dir: Path | str | None = None,
              progress: bool = True, made: dict | None = None, check_windows: int = 64,
              **params) -> dict:
    """Train the CNN on ``ws_train`` (a :class:`host.data.windows.WindowSet` of a
    classification task, with frames) and export it.

    ``ws_test``: held-out windows (e.g. from :func:`host.data.splits.split_grouped`); their
    metrics come from ONNX Runtime running the exported model, as on the Pi.
    ``params`` go to :class:`FrameCNN` (``epochs``, default 20, ``hidden``,
    ``filters``, ``lr``, ...). ``out_dir``: write model.onnx + its manifest there
    (kind = the task), a model spec (:func:`cnn_spec_keys`) carrying what ``made``
    holds: ``profile`` (the sensor profile: name, path or record; default roboskin),
    ``trained_on`` and ``config`` (:mod:`device.pi.models.spec`). ``host train``
    writes the folder itself (:func:`host.learn.trainers.train_frames_cnn`).

    Returns a dict: ``task``, ``classes``, ``T``, ``frame_size``, ``params``,
    ``n_params``, ``size_bytes`` (the ONNX), ``train_s``, ``loss`` (per epoch),
    ``metrics`` (``train`` and ``test``: accuracy, per-class F1, confusion
    matrix; ``cv`` None), ``onnx_vs_torch_max_abs``, ``out_dir`` / ``onnx_path`` (None without
    ``out_dir``), ``onnx`` (the onnx.ModelProto) and ``estimator`` (the FrameCNN).
    Raises ValueError if ONNX Runtime and torch differ by more than ``ONNX_ATOL``.
    """
    require_torch()
    t0 = time.perf_counter()
    task = ws_train.task
    if task not in CLASS_TASKS:
        raise ValueError(f"the CNN is a classifier: task must be one of {CLASS_TASKS}, "
                         f"got task={task!r}")
    if ws_train.labels is None:
        raise ValueError("ws_train has no labels")
    if ws_test is not None and (ws_test.task != task or ws_test.window != ws_train.window):
        raise ValueError(f"ws_test is task={ws_test.task!r} T={ws_test.window}, ws_train is "
                         f"task={task!r} T={ws_train.window}")
    check_windows = check_int("check_windows", check_windows, 1)
    X = frames_input(ws_train.frames)
    y = ws_train.labels.astype(str)
    est = FrameCNN(**dict({"epochs": 20}, **params), seed=seed, progress=progress)
    est.fit(X, y, classes=ws_train.classes)
    fit_s = time.perf_counter() - t0
    classes = est.classes_
    T, S = est.window_, est.frame_size_

    onx = est.to_onnx()
    size_bytes = len(onx.SerializeToString())
    sess = session(onx)
    p_train = run_onnx(sess, X)
    metrics = {"train": label_metrics(y, p_train.argmax(1), classes)}
    rows = _check_rows(len(X), check_windows, seed)
    diff = float(np.abs(p_train[rows] - est.predict_proba(X[rows])).max())
    if ws_test is not None:
        if ws_test.labels is None:
            raise ValueError("ws_test has no labels")
        Xt = frames_input(ws_test.frames)
        if Xt.shape[1:] != X.shape[1:]:
            raise ValueError(f"ws_test windows are {Xt.shape[1:]}, ws_train windows "
                             f"{X.shape[1:]}; use the same T and frame_size")
        p_test = run_onnx(sess, Xt)
        yt = ws_test.labels.astype(str)
        metrics["test"] = label_metrics(yt, p_test.argmax(1), classes)
        unseen = sorted(set(yt.tolist()) - set(classes))
        if unseen:
            metrics["test"]["classes_not_in_training"] = unseen
        rows_t = _check_rows(len(Xt), check_windows, seed + 1)
        if len(rows_t):
            diff = max(diff, float(np.abs(p_test[rows_t] - est.predict_proba(Xt[rows_t])).max()))
    if not diff <= ONNX_ATOL:
        raise ValueError(f"exported ONNX model differs from torch by {diff:.3g} "
                         f"(> {ONNX_ATOL}) in probability; the export is broken")

    train_s = round(time.perf_counter() - t0, 2)
    metrics.setdefault("test", None)
    metrics["cv"] = None
    result = {"task": task, "model": MODEL, "classes": list(classes), "T": T,
              "frame_size": S, "params": est.get_params(), "n_params": est.n_params_,
              "size_bytes": int(size_bytes), "train_s": train_s, "fit_s": round(fit_s, 2),
              "loss": [round(v, 6) for v in est.loss_], "metrics": metrics,
              "onnx_vs_torch_max_abs": diff,
              "out_dir": None, "onnx_path": None, "onnx": onx, "estimator": est}
    if out_dir is not None:
        extra = dict(cnn_spec_keys(result), metrics=metrics, variant="float",
                     training={"data": ws_train.summary(), "seed": seed, "train_s": train_s,
                               "test_data": None if ws_test is None else ws_test.summary()},
                     **{k: v for k, v in (made or {}).items()
                        if k in ("profile", "trained_on", "config")})
        out = write_model(onx, out_dir, kind=task, n_features=T * S * S, extra=extra,
                          input_name=INPUT_NAME, input_dims=[T, S, S])
        result["out_dir"] = str(out)
        result["onnx_path"] = str(Path(out) / "model.onnx")
    return result


def cnn_spec_keys(result: dict) -> dict:
    """The spec's fields of a trained CNN (a :func:`train_cnn` result): its task,
    classes, T, frame size, layout, output and network parameters."""
    S = result["frame_size"]
    return {"task": result["task"], "model": MODEL, "classes": list(result["classes"]),
            "T": result["T"], "crop_size": S, "input_layout": "frames", "uses_imu": False,
            "output": OUTPUT_NAME, "output_kind": "probabilities",
            "output_doc": f"{OUTPUT_NAME} (N, {len(result['classes'])}): softmax over "
                          f"classes", "frame_size": S, "opset": OPSET,
            "cnn_params": result["params"], "n_params": result["n_params"],
            "onnx_vs_torch_max_abs": result["onnx_vs_torch_max_abs"]}


def quantise_cnn(float_onnx: Path | str, ws_calib, out_path: Path | str,
                 max_windows: int = 512, seed: int = 0):
    """An int8 copy (static QDQ) of an exported CNN, calibrated on up to
    ``max_windows`` windows of ``ws_calib`` (training windows), built exactly as the
    Pi builds its input. The quantiser is the toolkit's one,
    :func:`host.learn.quantise.quantise_model`; this only prepares its calibration inputs and
    returns what it returns."""
    max_windows = check_int("max_windows", max_windows, 1)
    rows = _check_rows(len(ws_calib), max_windows, seed)
    report = quantise_model(float_onnx, frames_input(ws_calib.frames[rows]), out_path)
    _adopt_int8(Path(out_path), report)
    return report


def _adopt_int8(q: Path, report: dict) -> None:
    """When the int8 file was written into a CNN model folder as model.int8.onnx,
    make it the folder's default as ``host train --quantise`` does: the spec names the
    int8 file (checksums of both) and records the int8 check under ``measured``; the
    float variant gets its own manifest."""
    folder = q.parent
    if q.name != INT8_NAME or not has_manifest(folder) or not (folder / FLOAT_NAME).is_file():
        return
    spec, _ = read_spec(folder)
    if spec.model != MODEL:
        return
    spec.measured.int8 = {k: v for k, v in report.items() if k != "path"}
    fill_variants(folder, spec, int8=True)
    write_variant_specs(folder, spec)
