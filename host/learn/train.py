"""Training, export, int8 quantisation and the simulated benchmarks (``host train``).

:func:`train_model` turns windows (:class:`host.data.windows.WindowSet`) into a deployable
model folder: ONNX (the scaler folded into the graph) + ``manifest.json``, and with
``quantise=True`` an int8 ONNX file beside the float one, checked against it.

Tasks and models (``host train --task T --model M``):

==========  =====================================================================
rule        the paper's rules, no weights (:mod:`device.pi.models.rules`): surface, slip
ridge       Ridge (alpha 150) over all pin vectors of the window: pressure
fnn         MLP over T frames of ``encode_vectors`` (+ IMU when present), two
            hidden layers, logistic (sigmoid) units, standard scaling: surface,
            texture, slip; an MLP regressor for pressure. In the graph:
            [frame-to-frame changes (:class:`TemporalFeatures`, T >= 2)] ->
            standard scaling clipped to +-8 sd (:class:`ClippedScaler`) -> MLP
grid-fnn    the same MLP over ``encode_grids`` (contact-grid maps and their
            frame-to-frame changes): texture, surface, slip
==========  =====================================================================

Every model's input is built by :mod:`device.pi.models.window`, the encoders the Pi runs.
The slip detector is the ``fnn`` (or ``rule``) of task ``slip``: it emits a slip
event (argmax) and a confidence (the slip probability); its detection latency in
frames from the true onset is measured on the held-out trials (:func:`slip_latency`).

Held-out data: ``ws_test`` when given; otherwise a grouped split of the training
trials (25 % of the trials, whole trials only) when there are at least two trials,
else a time split within the trial. ``cv=K`` adds grouped K-fold cross-validation
on the training windows (:func:`host.data.splits.group_kfold`).

Model folder::

    manifest.json          task, classes, T, feature spec, input layout, IMU use,
                           metrics, int8 check, sha256 + size of each file, data summary
    manifest.float.json    (quantised models only) the same, loading the float file
    model.onnx             float32
    model.int8.onnx        (``quantise=True``) static QDQ int8, the default to load

:func:`sim_benchmarks` builds the simulated data sets the issue's accuracy figures
are measured on (randomised scenes, unseen seeds and surface parameters beyond the
training range for the test trials) and measures all four tasks.
"""
from __future__ import annotations

import contextlib
import json
import logging
import math
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from device.pi.models.artefact import FEATURE_SPEC_VERSION, FORMAT, MANIFEST, VERSION, sha256_file
from device.pi.models.window import encode_frames, encode_grids, encode_vectors

__all__ = [
    "TASKS", "MODELS", "TrainError", "QuantisationError", "model_inputs", "train_model",
    "quantise_model", "compare_int8", "int8_saturation", "classification_metrics",
    "regression_metrics", "slip_latency", "cross_validate_model", "sim_benchmarks",
    "bench_scene", "scene_toml", "simulate_scenes",
]

TASKS = ("surface", "texture", "slip", "pressure")
MODELS = ("rule", "ridge", "fnn", "grid-fnn")
#: which models serve which task
TASK_MODELS = {"surface": ("rule", "fnn", "grid-fnn"), "texture": ("fnn", "grid-fnn"),
               "slip": ("rule", "fnn", "grid-fnn"), "pressure": ("ridge", "fnn")}
LAYOUT = {"rule": "vectors", "ridge": "vectors", "fnn": "vectors", "grid-fnn": "grids"}
DEFAULT_HIDDEN = (64, 32)
DEFAULT_ALPHA = {"ridge": 150.0, "fnn": 1e-3, "grid-fnn": 1e-3}
DEFAULT_EPOCHS = 300
FLOAT_NAME = "model.onnx"
INT8_NAME = "model.int8.onnx"
FLOAT_MANIFEST = "manifest.float.json"
MIN_AGREEMENT = 0.99
#: an int8 regressor fails its check when its MAE grows by more than this share of
#: the target range
MAX_REGRESSION_CHANGE = 0.01


class TrainError(ValueError):
    """Bad training input or a failed check; the message names the field and value."""


class QuantisationError(TrainError):
    """The int8 model disagrees with the float model; the int8 file is not kept."""


# ----------------------------------------------------------------------------
# Inputs
# ----------------------------------------------------------------------------

def _check_choice(name: str, value, choices) -> str:
    if value not in choices:
        raise TrainError(f"{name} must be one of {list(choices)}, got {name}={value!r}")
    return value


def model_inputs(ws, layout: str, uses_imu: bool = False) -> np.ndarray:
    """Model inputs of a WindowSet, built by the Pi's encoders: (N, D) float32 for
    ``vectors`` and ``grids``, (N, T, S, S) for ``frames`` (the CNN's)."""
    _check_choice("input_layout", layout, ("vectors", "grids", "frames"))
    if layout == "frames":
        if ws.frames is None:
            raise TrainError("input_layout frames needs the binary crops; these windows have "
                             "none (load them with a frame_size)")
        return encode_frames(ws.frames)
    if layout == "grids":
        if ws.grids is None:
            raise TrainError("input_layout grids needs contact grids; these windows have none "
                             "(an .npz of vectors carries no grids): use --model fnn")
        return encode_grids(ws.grids)
    if uses_imu and ws.imu is None:
        raise TrainError("uses_imu=True but the windows carry no IMU rows")
    return encode_vectors(ws.vectors, ws.imu if uses_imu else None)


def _check_int(name: str, value, lo: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < lo:
        raise TrainError(f"{name} must be a whole number >= {lo}, got {name}={value!r}")
    return int(value)


def _label_ids(labels, classes: list[str]) -> np.ndarray:
    """Class ids of ``labels`` in ``classes``; -1 for a label the model never saw."""
    index = {c: i for i, c in enumerate(classes)}
    return np.array([index.get(str(x), -1) for x in labels], np.int64)


# ----------------------------------------------------------------------------
# Rotation augmentation
# ----------------------------------------------------------------------------

def layout_rotations(layout_px, tol_px: float = 0.5) -> list[tuple[int, np.ndarray]]:
    """The rotations (whole degrees, 1..359) about the layout's centre that map the
    pin layout onto itself, each with its permutation: pin i lands on pin perm[i].
    For the roboskin layout (rings of 12 and 24 on common spokes) these are the
    multiples of 30 degrees."""
    p = np.asarray(layout_px, np.float64).reshape(-1, 2)
    q = p - p.mean(axis=0)
    out = []
    for deg in range(1, 360):
        th = math.radians(deg)
        R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
        r = q @ R.T
        d = np.hypot(r[:, None, 0] - q[None, :, 0], r[:, None, 1] - q[None, :, 1])
        perm = d.argmin(axis=1)
        if d[np.arange(len(q)), perm].max() <= tol_px and len(np.unique(perm)) == len(q):
            out.append((deg, perm))
    return out


def rotate_windows(ws, deg: float, perm: np.ndarray):
    """The windows as if every stimulus had come ``deg`` degrees rotated (image
    axes): pin vectors rotated and moved to the pins ``perm`` says, the IMU's x/y
    accelerations and x/y rates rotated (z unchanged). Grids and frames are dropped
    (None): they are not rotated."""
    from dataclasses import replace

    perm = np.asarray(perm, np.int64)
    if perm.shape != (ws.n_pins,):
        raise TrainError(f"rotation permutation has {perm.size} pins, the windows {ws.n_pins}")
    th = math.radians(deg)
    R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]], np.float32)
    v = np.empty_like(ws.vectors)
    v[:, :, perm] = ws.vectors @ R.T
    lost = np.empty_like(ws.lost)
    lost[:, :, perm] = ws.lost
    imu = None
    if ws.imu is not None:
        imu = ws.imu.copy()
        imu[..., 0:2] = ws.imu[..., 0:2] @ R.T
        imu[..., 3:5] = ws.imu[..., 3:5] @ R.T
    return replace(ws, vectors=v, lost=lost, imu=imu, grids=None, frames=None,
                   source=dict(ws.source, rotated_deg=deg))


def augment_rotations(ws, copies: int, profile: str = "roboskin"):
    """``ws`` plus ``copies`` rotated copies of it (:func:`rotate_windows`), at
    rotations spread evenly over the layout's symmetries; labels, targets and
    groups are kept (a rotated window stays in its trial). For the ``vectors``
    layout only (grids are not rotated)."""
    from dataclasses import replace

    from host.data.extract import layout_for_profile

    copies = _check_int("augment", copies, 0)
    if copies == 0:
        return ws
    lay = layout_for_profile(profile)
    if len(lay) != ws.n_pins:
        raise TrainError(f"augment: profile {profile!r} has {len(lay)} pins, the windows "
                         f"{ws.n_pins}")
    rots = layout_rotations(lay)
    if not rots:
        raise TrainError(f"augment: the pin layout of profile {profile!r} has no rotational "
                         f"symmetry to augment with")
    pick = np.unique(np.linspace(0, len(rots), copies + 1, endpoint=False)[1:].astype(int)
                     ) if copies < len(rots) else np.arange(len(rots))
    parts = [replace(ws, grids=None, frames=None)] + [rotate_windows(ws, *rots[i]) for i in pick]
    cat = {}
    for k in ("vectors", "lost", "imu", "contact", "labels", "targets", "groups", "t_index",
              "trial_len"):
        vals = [getattr(p, k) for p in parts]
        cat[k] = None if vals[0] is None else np.concatenate(vals)
    return replace(ws, **cat, grids=None, frames=None,
                   source=dict(ws.source, augmented_deg=[0] + [rots[i][0] for i in pick]))


# ----------------------------------------------------------------------------
# The FNN's fixed first layer: frame-to-frame changes
# ----------------------------------------------------------------------------

def _temporal_class():
    """:class:`TemporalFeatures`, defined on first use (sklearn is host-only)."""
    global TemporalFeatures
    if "TemporalFeatures" in globals():
        return TemporalFeatures
    from sklearn.base import BaseEstimator, TransformerMixin

    class TemporalFeatures(TransformerMixin, BaseEstimator):
        """The FNN's first, fixed layer over a ``vectors`` window input: it keeps
        the input and appends, from the T frames of M pin vectors,

        * the per-pin frame-to-frame changes, (T-1) x M x 2;
        * the average vector of each frame, T x 2, and its changes, (T-1) x 2;
        * the length of each average-vector change, T-1 (how far the patch moved);
        * the mean length of the per-pin changes, T-1 (how much the pins shook);
        * the mean pin displacement |v| of each frame, T (the pressure).

        Texture shake, slip and a wet floor show in these changes, which are small
        next to the vectors themselves; given explicitly, the MLP finds them from
        few trials. No weights: in ONNX it is Slice / Sub / ReduceMean /
        ReduceSumSquare / Sqrt / Concat (:func:`_temporal_to_onnx`), left in float
        by the int8 quantiser.
        """

        def __init__(self, T: int = 3, n_pins: int = 133, uses_imu: bool = False):
            self.T = T
            self.n_pins = n_pins
            self.uses_imu = uses_imu

        def _n_in(self) -> int:
            return self.T * self.n_pins * 2 + (6 * self.T if self.uses_imu else 0)

        def fit(self, X, y=None):
            X = np.asarray(X)
            if X.ndim != 2 or X.shape[1] != self._n_in():
                raise TrainError(f"temporal features: expected (N, {self._n_in()}) inputs for "
                                 f"T={self.T}, {self.n_pins} pins, imu={self.uses_imu}, got "
                                 f"{X.shape}")
            T, M = self.T, self.n_pins
            self.n_features_in_ = X.shape[1]
            self.n_features_out_ = (X.shape[1] + (T - 1) * M * 2 + 2 * T + 2 * (T - 1)
                                    + 2 * (T - 1) + T)
            return self

        def transform(self, X):
            X = np.asarray(X, np.float32)
            T, M, N = self.T, self.n_pins, X.shape[0]
            v = X[:, :T * M * 2].reshape(N, T, M, 2)
            avg = v.mean(axis=2, dtype=np.float32)
            parts = [X]
            dv = v[:, 1:] - v[:, :-1]
            davg = avg[:, 1:] - avg[:, :-1]
            parts += [dv.reshape(N, -1), avg.reshape(N, -1), davg.reshape(N, -1),
                      np.sqrt((davg * davg).sum(axis=2)),
                      np.sqrt((dv * dv).sum(axis=3)).mean(axis=2),
                      np.sqrt((v * v).sum(axis=3)).mean(axis=2)]
            return np.concatenate(parts, axis=1).astype(np.float32)

    globals()["TemporalFeatures"] = TemporalFeatures
    _register_temporal(TemporalFeatures)
    return TemporalFeatures


#: standardised MLP inputs are clipped to this many standard deviations
SCALED_CLIP = 8.0


def _scaler_class():
    """:class:`ClippedScaler`, defined on first use (sklearn is host-only)."""
    global ClippedScaler
    if "ClippedScaler" in globals():
        return ClippedScaler
    from sklearn.base import BaseEstimator, TransformerMixin
    from sklearn.preprocessing import StandardScaler

    class ClippedScaler(TransformerMixin, BaseEstimator):
        """Standard scaling (sklearn's: a zero-variance feature keeps scale 1), then
        every value clipped to +-``clip`` standard deviations. The clip bounds what
        an extreme window can do to the MLP and keeps one outlying feature from
        stretching the int8 range of the first layer's input for all the others.
        In ONNX: Sub, Mul, Clip (standard ops)."""

        def __init__(self, clip: float = SCALED_CLIP):
            self.clip = clip

        def fit(self, X, y=None):
            sc = StandardScaler().fit(X)
            self.mean_ = sc.mean_.astype(np.float32)
            self.scale_ = sc.scale_
            self.inv_scale_ = (1.0 / sc.scale_).astype(np.float32)
            self.n_features_in_ = sc.n_features_in_
            return self

        def transform(self, X):
            z = (np.asarray(X, np.float32) - self.mean_) * self.inv_scale_
            return np.clip(z, -self.clip, self.clip).astype(np.float32)

    globals()["ClippedScaler"] = ClippedScaler
    from onnx import TensorProto
    from skl2onnx import update_registered_converter
    from skl2onnx.common.data_types import FloatTensorType

    def shape(operator):
        operator.outputs[0].type = FloatTensorType([None, operator.raw_operator.n_features_in_])

    def convert(scope, operator, container):
        op = operator.raw_operator

        def init(values, dims):
            name = scope.get_unique_variable_name("c")
            container.add_initializer(name, TensorProto.FLOAT, dims,
                                      np.asarray(values, np.float32).ravel().tolist())
            return name

        def node(op_type, inputs, out=None):
            out = out or scope.get_unique_variable_name(op_type.lower())
            container.add_node(op_type, inputs, out,
                               name=scope.get_unique_operator_name(op_type))
            return out

        D = int(op.n_features_in_)
        z = node("Mul", [node("Sub", [operator.inputs[0].full_name, init(op.mean_, [D])]),
                         init(op.inv_scale_, [D])])
        node("Clip", [z, init([-op.clip], []), init([op.clip], [])],
             operator.outputs[0].full_name)

    update_registered_converter(ClippedScaler, "TacfootClippedScaler", shape, convert)
    return ClippedScaler


def _register_temporal(cls) -> None:
    from skl2onnx import update_registered_converter
    from skl2onnx.common.data_types import FloatTensorType

    def shape(operator):
        operator.outputs[0].type = FloatTensorType([None, operator.raw_operator.n_features_out_])

    update_registered_converter(cls, "TacfootTemporalFeatures", shape, _temporal_to_onnx)


def _temporal_to_onnx(scope, operator, container):
    """ONNX for :class:`TemporalFeatures` (the same numbers as its transform)."""
    from onnx import TensorProto

    op = operator.raw_operator
    T, M = int(op.T), int(op.n_pins)

    def const(values):
        name = scope.get_unique_variable_name("c")
        container.add_initializer(name, TensorProto.INT64, [len(values)], list(values))
        return name

    def node(op_type, inputs, **attrs):
        out = scope.get_unique_variable_name(op_type.lower())
        container.add_node(op_type, inputs, out, name=scope.get_unique_operator_name(op_type),
                           **attrs)
        return out

    def frames(a, lo, hi):          # a[:, lo:hi] along axis 1
        return node("Slice", [a, const([lo]), const([hi]), const([1])])

    def flat(a, width):
        return node("Reshape", [a, const([-1, width])])

    x = operator.inputs[0].full_name
    v = node("Reshape", [node("Slice", [x, const([0]), const([T * M * 2]), const([1])]),
                         const([-1, T, M, 2])])
    avg = node("ReduceMean", [v], axes=[2], keepdims=0)                       # (N, T, 2)
    dv = node("Sub", [frames(v, 1, T), frames(v, 0, T - 1)])                  # (N, T-1, M, 2)
    davg = node("Sub", [frames(avg, 1, T), frames(avg, 0, T - 1)])            # (N, T-1, 2)
    parts = [x, flat(dv, (T - 1) * M * 2), flat(avg, 2 * T), flat(davg, 2 * (T - 1)),
             node("Sqrt", [node("ReduceSumSquare", [davg], axes=[2], keepdims=0)]),
             node("ReduceMean", [node("Sqrt", [node("ReduceSumSquare", [dv], axes=[3],
                                                    keepdims=0)])], axes=[2], keepdims=0),
             node("ReduceMean", [node("Sqrt", [node("ReduceSumSquare", [v], axes=[3],
                                                   keepdims=0)])], axes=[2], keepdims=0)]
    container.add_node("Concat", parts, operator.outputs[0].full_name, axis=1,
                       name=scope.get_unique_operator_name("Concat"))


# ----------------------------------------------------------------------------
# Estimators
# ----------------------------------------------------------------------------

def _mlp(task: str, hidden, alpha: float, seed: int, n: int):
    from sklearn.neural_network import MLPClassifier, MLPRegressor

    # mini-batches of 128, smaller for small sets so an epoch takes >= 8 steps
    kw = dict(hidden_layer_sizes=tuple(hidden), activation="logistic", solver="adam",
              alpha=alpha, batch_size=int(min(128, max(4, n // 8))), learning_rate_init=1e-3,
              random_state=seed, shuffle=True)
    return MLPRegressor(**kw) if task == "pressure" else MLPClassifier(**kw)


def _fit_mlp(task: str, X: np.ndarray, y: np.ndarray, n_classes: int, hidden, alpha: float,
             seed: int, epochs: int, progress: bool, desc: str, temporal: dict | None = None,
             patience: int = 15, tol: float = 1e-4):
    """[TemporalFeatures +] scaler + MLP, the MLP fitted epoch by epoch
    (``partial_fit``) with a tqdm bar; stops when the training loss has not
    improved by ``tol`` for ``patience`` epochs. Returns (pipeline, epochs run,
    final loss)."""
    from sklearn.pipeline import Pipeline
    from tqdm import tqdm

    steps = []
    if temporal:
        tf = _temporal_class()(**temporal).fit(X)
        X = tf.transform(X)
        steps.append(("temporal", tf))
    scaler = _scaler_class()().fit(X)
    Xs = scaler.transform(X)
    mlp = _mlp(task, hidden, alpha, seed, len(X))
    best, stale, n = math.inf, 0, 0
    classes = np.arange(n_classes)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with tqdm(total=epochs, desc=desc, unit="epoch", disable=not progress or None,
                  file=sys.stderr, leave=False) as bar:
            for n in range(1, epochs + 1):
                if task == "pressure":
                    mlp.partial_fit(Xs, y)
                else:
                    mlp.partial_fit(Xs, y, classes=classes)
                loss = float(mlp.loss_)
                bar.set_postfix(loss=f"{loss:.4f}")
                bar.update(1)
                if not math.isfinite(loss):
                    raise TrainError(f"training diverged (loss {loss}) after {n} epochs")
                if loss < best - tol:
                    best, stale = loss, 0
                else:
                    stale += 1
                    if stale >= patience:
                        break
    return Pipeline(steps + [("scaler", scaler), ("mlp", mlp)]), n, float(mlp.loss_)


def _fit(task: str, model: str, X: np.ndarray, y: np.ndarray, n_classes: int, hp: dict,
         seed: int, progress: bool, desc: str):
    """A fitted sklearn Pipeline (scaler + estimator) and fit info."""
    t0 = time.perf_counter()
    if model == "ridge":
        from host.learn.regression import ridge_pipeline

        pipe = ridge_pipeline(hp["alpha"]).fit(X, y)
        info = {}
    else:
        pipe, epochs, loss = _fit_mlp(task, X, y, n_classes, hp["hidden"], hp["alpha"], seed,
                                      hp["epochs"], progress, desc, hp.get("temporal"))
        info = {"epochs": epochs, "loss": round(loss, 6)}
    info["fit_s"] = round(time.perf_counter() - t0, 3)
    return pipe, info


def _to_onnx(pipe, n_features: int, task: str):
    """The fitted pipeline as ONNX: input ``x`` (N, D) float32; classifiers output
    ``label`` and ``probabilities`` (no ZipMap), regressors ``variable`` (N, 1) from a
    plain MatMul + Add (so the int8 quantiser can reach it)."""
    from skl2onnx import convert_sklearn
    from skl2onnx.common.data_types import FloatTensorType

    est = pipe.steps[-1][1]
    kw = {}
    if task == "pressure":
        kw["black_op"] = {"LinearRegressor"}
    else:
        kw["options"] = {id(est): {"zipmap": False}}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = convert_sklearn(pipe, initial_types=[("x", FloatTensorType([None, n_features]))],
                            target_opset=17, **kw)
    # declare the type of the (ai.onnx.ml) Scaler's output, which ONNX shape inference
    # cannot work out: without it the int8 quantiser leaves the next MatMul's input
    # in float (weight-only int8)
    from onnx import TensorProto, helper

    typed = {v.name for v in m.graph.value_info} | {o.name for o in m.graph.output}
    for node in m.graph.node:
        if node.op_type == "Scaler" and node.output[0] not in typed:
            m.graph.value_info.append(helper.make_tensor_value_info(
                node.output[0], TensorProto.FLOAT, [None, None]))
    return m


# ----------------------------------------------------------------------------
# Running ONNX on the host
# ----------------------------------------------------------------------------

def _session(model, threads: int = 1):
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    so.log_severity_level = 3
    src = model.SerializeToString() if hasattr(model, "SerializeToString") else (
        model if isinstance(model, bytes) else str(model))
    return ort.InferenceSession(src, sess_options=so, providers=["CPUExecutionProvider"])


def _run(sess, X: np.ndarray, batch: int = 1024) -> np.ndarray:
    """The probabilities (classifier) or values (regressor, (N,)) for X."""
    names = [o.name for o in sess.get_outputs()]
    out = "probabilities" if "probabilities" in names else names[0]
    inp = sess.get_inputs()[0].name
    parts = [sess.run([out], {inp: np.ascontiguousarray(X[i:i + batch], np.float32)})[0]
             for i in range(0, len(X), batch)]
    res = np.concatenate(parts) if parts else np.zeros((0,), np.float32)
    return res.astype(np.float64) if out == "probabilities" else res.reshape(-1).astype(
        np.float64)


def _is_classifier(sess) -> bool:
    return "probabilities" in [o.name for o in sess.get_outputs()]


# ----------------------------------------------------------------------------
# Metrics
# ----------------------------------------------------------------------------

def classification_metrics(true_ids: np.ndarray, pred_ids: np.ndarray, classes: list[str],
                           true_labels=None) -> dict:
    """Accuracy, macro F1, per-class precision / recall / F1 and the confusion
    matrix (rows: true class, columns: predicted) over ``classes``; true labels
    the model never saw (id -1) count as errors and get their own row."""
    true_ids = np.asarray(true_ids, np.int64)
    pred_ids = np.asarray(pred_ids, np.int64)
    n = len(true_ids)
    C = len(classes)
    rows = list(classes)
    unknown = []
    if true_labels is not None and (true_ids < 0).any():
        unknown = sorted({str(x) for x, t in zip(true_labels, true_ids) if t < 0})
        rows += unknown
    conf = np.zeros((len(rows), C), np.int64)
    for t, p, lab in zip(true_ids, pred_ids,
                         true_labels if true_labels is not None else [None] * n):
        r = t if t >= 0 else (C + unknown.index(str(lab)) if lab is not None else None)
        if r is not None and 0 <= p < C:
            conf[r, p] += 1
    per = {}
    for i, c in enumerate(classes):
        tp = int(conf[i, i])
        fp = int(conf[:, i].sum() - tp)
        fn = int(conf[i].sum() - tp)
        prec = tp / (tp + fp) if tp + fp else 0.0
        rec = tp / (tp + fn) if tp + fn else 0.0
        f1 = 2 * prec * rec / (prec + rec) if prec + rec else 0.0
        per[c] = {"precision": round(prec, 6), "recall": round(rec, 6), "f1": round(f1, 6),
                  "support": int(conf[i].sum())}
    present = [c for c in classes if per[c]["support"] > 0]
    macro = float(np.mean([per[c]["f1"] for c in present])) if present else 0.0
    acc = float((true_ids == pred_ids).mean()) if n else 0.0
    return {"n": int(n), "accuracy": round(acc, 6), "macro_f1": round(macro, 6),
            "per_class": per, "confusion": {"labels": rows, "predicted": list(classes),
                                            "matrix": conf.tolist()}}


def regression_metrics(y: np.ndarray, pred: np.ndarray) -> dict:
    """MAE, RMSE, the target range and MAE as a share of it."""
    y = np.asarray(y, np.float64)
    pred = np.asarray(pred, np.float64)
    err = pred - y
    rng = float(y.max() - y.min()) if len(y) else 0.0
    mae = float(np.abs(err).mean()) if len(y) else 0.0
    return {"n": int(len(y)), "mae": round(mae, 6),
            "rmse": round(float(np.sqrt((err ** 2).mean())) if len(y) else 0.0, 6),
            "target_range": round(rng, 6),
            "mae_of_range": round(mae / rng, 6) if rng > 0 else None,
            "mae_predict_mean": round(float(np.abs(y - y.mean()).mean()) if len(y) else 0.0, 6)}


def slip_latency(ws, slip_pred, slip_label: str = "slip") -> dict:
    """Detection latency of slip onsets, in frames.

    An onset is a window whose label is ``slip_label`` while the window ending one
    frame earlier in the same trial is not. It is detected at the first window of
    its slip run (same trial, consecutive frames, slip label) that ``slip_pred``
    marks as slip; the latency is that window's last frame minus the onset frame
    (0: the decision made on the onset frame itself). A run with no such window is
    missed. Windows without a time order (``t_index`` -1) are skipped.
    """
    slip_pred = np.asarray(slip_pred, bool)
    if ws.labels is None:
        raise TrainError("slip_latency needs labelled windows (task slip)")
    is_slip = np.array([str(x) == slip_label for x in ws.labels])
    lat, missed = [], 0
    for g in np.unique(ws.groups):
        idx = np.flatnonzero((ws.groups == g) & (ws.t_index >= 0))
        if len(idx) < 2:
            continue
        idx = idx[np.argsort(ws.t_index[idx], kind="stable")]
        t = ws.t_index[idx]
        s = is_slip[idx]
        p = slip_pred[idx]
        for k in range(1, len(idx)):
            if not (s[k] and not s[k - 1] and t[k] == t[k - 1] + 1):
                continue
            j, found = k, None
            while j < len(idx) and s[j] and (j == k or t[j] == t[j - 1] + 1):
                if p[j]:
                    found = int(t[j] - t[k])
                    break
                j += 1
            if found is None:
                missed += 1
            else:
                lat.append(found)
    a = np.asarray(lat, np.float64)
    return {"onsets": len(lat) + missed, "detected": len(lat), "missed": missed,
            "median_frames": float(np.median(a)) if len(a) else None,
            "p90_frames": float(np.percentile(a, 90)) if len(a) else None,
            "max_frames": int(a.max()) if len(a) else None,
            "latencies_frames": [int(x) for x in lat]}


def _class_report(task: str, ws, true_ids, probs, classes) -> dict:
    pred = np.argmax(probs, axis=1) if len(probs) else np.zeros(0, np.int64)
    m = classification_metrics(true_ids, pred, classes, ws.labels)
    if task == "slip" and "slip" in classes:
        m["slip_f1"] = m["per_class"]["slip"]["f1"]
        m["latency"] = slip_latency(ws, pred == classes.index("slip"))
    return m


# ----------------------------------------------------------------------------
# The rule model
# ----------------------------------------------------------------------------

def _best_threshold(values: np.ndarray, positive: np.ndarray) -> float:
    """The threshold t for 'positive when value < t' with the best balanced
    accuracy, over the midpoints of the sorted values."""
    v = np.asarray(values, np.float64)
    pos = np.asarray(positive, bool)
    if not pos.any() or pos.all():
        return 0.0
    cand = np.unique(np.quantile(v, np.linspace(0, 1, 401)))
    cand = np.concatenate([cand, (cand[1:] + cand[:-1]) / 2]) if len(cand) > 1 else cand
    best_t, best = 0.0, -1.0
    for t in cand:
        below = v < t
        score = below[pos].mean() + (~below[~pos]).mean()
        if score > best:
            best, best_t = score, float(t)
    return best_t


def _fit_rule(task: str, ws, classes: list[str]):
    """A RuleClassifier with thresholds set from the training windows (a 1-D
    search per threshold; the rule has no weights)."""
    from device.pi.models.rules import RuleClassifier, window_measures

    ms = [window_measures(v) for v in ws.vectors]
    mag = np.array([m["magnitude_px"] for m in ms])
    motion = np.array([np.nan if m["motion_px"] is None else m["motion_px"] for m in ms])
    lab = ws.labels.astype(str)
    if task == "surface":
        contact = lab != "no-touch"
    else:
        contact = np.asarray(ws.contact, bool)
    contact_px = _best_threshold(mag, ~contact) if (~contact).any() and contact.any() else 1.0
    if task == "surface":
        ref = contact & np.isin(lab, ["hard", "slippery"])
        still_pos, still_neg = lab == "slippery", lab == "hard"
    else:
        ref = contact
        still_pos, still_neg = contact & (lab == "slip"), contact & (lab != "slip")
    ref = ref if ref.any() else contact
    expected_mag = float(np.median(mag[ref])) if ref.any() else 0.0
    soft_ratio = 0.0
    if task == "surface" and (lab == "soft").any() and expected_mag > 0:
        sel = contact
        soft_ratio = _best_threshold(mag[sel], lab[sel] == "soft") / expected_mag
    expected_motion = wet_ratio = 0.0
    if ws.window >= 2 and still_neg.any():
        expected_motion = float(np.nanmedian(motion[still_neg]))
        if still_pos.any() and expected_motion > 0:
            sel = still_pos | still_neg
            wet_ratio = _best_threshold(motion[sel], still_pos[sel]) / expected_motion
    rule = {"contact_px": contact_px, "expected_mag_px": expected_mag,
            "soft_ratio": soft_ratio, "expected_motion_px": expected_motion,
            "wet_ratio": wet_ratio}
    rule = {k: round(float(max(v, 0.0)), 6) for k, v in rule.items()}
    return RuleClassifier(rule, classes, ws.window, ws.n_pins, task=task)


def _rule_probs(rc, X: np.ndarray) -> np.ndarray:
    return np.stack([rc.predict(x)[1] for x in X]) if len(X) else np.zeros((0, rc.n_classes))


# ----------------------------------------------------------------------------
# Int8 quantisation
# ----------------------------------------------------------------------------

@contextlib.contextmanager
def _quiet_logging():
    root = logging.getLogger()
    level = root.level
    root.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            yield
    finally:
        root.setLevel(level)


def _calibration_reader(X: np.ndarray, input_name: str, batch: int = 64):
    """Calibration batches of exactly ``batch`` windows (the histogram calibrators
    need equal shapes): the last, short batch is filled with earlier windows."""
    if len(X) > batch and len(X) % batch:
        X = np.concatenate([X, X[:batch - len(X) % batch]])
    batch = min(batch, len(X))
    from onnxruntime.quantization import CalibrationDataReader

    class _Reader(CalibrationDataReader):
        """Feeds the calibration windows in batches."""

        def __init__(self):
            self._it = iter(range(0, len(X), batch))

        def get_next(self):
            i = next(self._it, None)
            return None if i is None else {input_name: np.ascontiguousarray(
                X[i:i + batch], np.float32)}

        def rewind(self):
            self._it = iter(range(0, len(X), batch))

    return _Reader()


def _model_bytes(m) -> bytes:
    if hasattr(m, "SerializeToString"):
        return m.SerializeToString()
    if isinstance(m, bytes):
        return m
    return Path(m).read_bytes()


def int8_saturation(float_onnx, int8_onnx, X: np.ndarray) -> dict:
    """Share of the values reaching each quantised activation (run through the float
    model on X) that fall outside the int8 range calibrated for it: the inputs the
    int8 model clips. Returns the overall share, the worst tensor and its share."""
    import onnx
    from onnx import numpy_helper

    q = onnx.load_from_string(_model_bytes(int8_onnx))
    init = {i.name: numpy_helper.to_array(i) for i in q.graph.initializer}
    ranges = {}
    for node in q.graph.node:
        if node.op_type != "QuantizeLinear" or node.input[0] in init:
            continue
        scale = float(np.asarray(init[node.input[1]]).reshape(-1)[0])
        zp_arr = init.get(node.input[2]) if len(node.input) > 2 else None
        zp = 0 if zp_arr is None else int(np.asarray(zp_arr).reshape(-1)[0])
        lo_q, hi_q = (-128, 127) if (zp_arr is not None and zp_arr.dtype == np.int8) else (0, 255)
        ranges[node.input[0]] = ((lo_q - zp) * scale - scale / 2, (hi_q - zp) * scale + scale / 2)
    f = onnx.load_from_string(_model_bytes(float_onnx))
    known = {o for n in f.graph.node for o in n.output} | {i.name for i in f.graph.input}
    names = [n for n in ranges if n in known]
    if not names or len(X) == 0:
        return {"tensors": 0, "share_outside": 0.0, "worst_tensor": None, "worst_share": 0.0}
    have = {o.name for o in f.graph.output}
    for n in names:
        if n not in have:
            f.graph.output.append(onnx.helper.make_tensor_value_info(n, onnx.TensorProto.FLOAT,
                                                                     None))
    sess = _session(f)
    inp = sess.get_inputs()[0].name
    outside = {n: 0 for n in names}
    total = {n: 0 for n in names}
    for i in range(0, len(X), 1024):
        vals = sess.run(names, {inp: np.ascontiguousarray(X[i:i + 1024], np.float32)})
        for n, v in zip(names, vals):
            lo, hi = ranges[n]
            v = np.asarray(v, np.float64)
            outside[n] += int(((v < lo) | (v > hi)).sum())
            total[n] += int(v.size)
    share = {n: outside[n] / total[n] if total[n] else 0.0 for n in names}
    worst = max(names, key=lambda n: share[n])
    return {"tensors": len(names), "share_outside": round(sum(outside.values())
                                                          / max(sum(total.values()), 1), 8),
            "worst_tensor": worst, "worst_share": round(share[worst], 8)}


def compare_int8(float_onnx, int8_onnx, X: np.ndarray, y=None,
                 min_agreement: float = MIN_AGREEMENT,
                 max_regression_change: float = MAX_REGRESSION_CHANGE) -> dict:
    """Int8 against float on windows X (held out): for classifiers the argmax
    agreement, the largest probability difference and (with class ids ``y``) the
    accuracy change; for regressors the largest output difference and (with
    targets ``y``) the MAE change. ``passed`` says whether it meets the bar
    (agreement >= ``min_agreement``; MAE change <= ``max_regression_change`` x the
    target range)."""
    X = np.asarray(X, np.float32)
    if X.ndim < 2 or len(X) == 0:
        raise TrainError(f"compare_int8 needs held-out windows (N, D) or (N, C, H, W), got "
                         f"shape {X.shape}")
    sf, sq = _session(_model_bytes(float_onnx)), _session(_model_bytes(int8_onnx))
    pf, pq = _run(sf, X), _run(sq, X)
    if not np.isfinite(pq).all():
        return {"n": int(len(X)), "passed": False, "finite": False,
                "why": "the int8 model gives NaN or inf"}
    if pf.shape != pq.shape:
        return {"n": int(len(X)), "passed": False,
                "why": f"output shapes differ: float {pf.shape}, int8 {pq.shape}"}
    if _is_classifier(sf):
        af, aq = pf.argmax(axis=1), pq.argmax(axis=1)
        agree = float((af == aq).mean())
        res = {"n": int(len(X)), "kind": "classifier", "agreement": round(agree, 6),
               "max_prob_diff": round(float(np.abs(pf - pq).max()), 6),
               "min_agreement": min_agreement}
        if y is not None:
            y = np.asarray(y)
            res["accuracy_float"] = round(float((af == y).mean()), 6)
            res["accuracy_int8"] = round(float((aq == y).mean()), 6)
            res["accuracy_change"] = round(res["accuracy_int8"] - res["accuracy_float"], 6)
        res["passed"] = agree >= min_agreement
        return res
    res = {"n": int(len(X)), "kind": "regressor",
           "max_abs_diff": round(float(np.abs(pf - pq).max()), 6)}
    res["passed"] = True
    if y is not None:
        y = np.asarray(y, np.float64)
        mf, mq = float(np.abs(pf - y).mean()), float(np.abs(pq - y).mean())
        rng = float(y.max() - y.min()) if len(y) else 0.0
        res.update({"mae_float": round(mf, 6), "mae_int8": round(mq, 6),
                    "mae_change": round(mq - mf, 6),
                    "mae_change_of_range": round((mq - mf) / rng, 6) if rng > 0 else None})
        res["passed"] = (mq - mf) <= max_regression_change * max(rng, 1e-12)
    return res


def quantise_model(float_onnx, calibration_inputs, out_path, check_inputs=None,
                   check_targets=None, min_agreement: float = MIN_AGREEMENT,
                   calibrate_method: str = "minmax", per_channel: bool = True) -> dict:
    """Static int8 quantisation (QDQ, uint8 activations, int8 weights) of the
    MatMuls, Gemms and Convs of ``float_onnx`` (a path, bytes or ModelProto),
    calibrated on ``calibration_inputs`` training windows (N, D), or (N, T, H, W)
    frame stacks for the CNN; writes ``out_path``.

    Then checks the int8 model against the float one on ``check_inputs`` (held-out
    windows; default: the calibration windows) with :func:`compare_int8`, and
    measures int8 saturation (:func:`int8_saturation`) on both sets. When the check
    fails, ``out_path`` is removed and :class:`QuantisationError` raised. Returns the
    report (agreement, largest probability difference or regression error change,
    saturation, sizes).
    """
    from onnxruntime.quantization import (CalibrationMethod, QuantFormat, QuantType,
                                          quantize_static)

    methods = {"minmax": CalibrationMethod.MinMax, "percentile": CalibrationMethod.Percentile,
               "entropy": CalibrationMethod.Entropy}
    _check_choice("calibrate_method", calibrate_method, tuple(methods))
    Xc = np.asarray(calibration_inputs, np.float32)
    if Xc.ndim < 2 or len(Xc) == 0:
        raise TrainError(f"calibration_inputs must be windows (N, D) or (N, C, H, W) with "
                         f"N >= 1, got shape {Xc.shape}")
    if not np.isfinite(Xc).all():
        raise TrainError("calibration_inputs hold NaN or inf; encode them with "
                         "device.pi.models.window")
    fbytes = _model_bytes(float_onnx)
    out_path = Path(out_path)
    input_name = _session(fbytes).get_inputs()[0].name
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="tacfoot-q-") as tmp:
        fpath = Path(tmp) / "float.onnx"
        fpath.write_bytes(fbytes)
        qpath = Path(tmp) / "int8.onnx"
        with _quiet_logging():
            quantize_static(str(fpath), str(qpath), _calibration_reader(Xc, input_name),
                            quant_format=QuantFormat.QDQ, activation_type=QuantType.QUInt8,
                            weight_type=QuantType.QInt8, per_channel=per_channel,
                            op_types_to_quantize=["MatMul", "Gemm", "Conv"],
                            calibrate_method=methods[calibrate_method])
        qbytes = qpath.read_bytes()
    quant_s = time.perf_counter() - t0
    Xh = Xc if check_inputs is None else np.asarray(check_inputs, np.float32)
    report = compare_int8(fbytes, qbytes, Xh, check_targets, min_agreement=min_agreement)
    report["checked_on"] = "calibration windows" if check_inputs is None else "held-out windows"
    report["saturation"] = {"calibration": int8_saturation(fbytes, qbytes, Xc),
                            "held_out": int8_saturation(fbytes, qbytes, Xh)}
    report.update({"calibration_windows": int(len(Xc)), "calibrate_method": calibrate_method,
                   "format": "QDQ u8 activations / s8 weights" + (" per channel"
                                                                   if per_channel else ""),
                   "float_bytes": len(fbytes), "int8_bytes": len(qbytes),
                   "quantise_s": round(quant_s, 3)})
    if not report["passed"]:
        with contextlib.suppress(FileNotFoundError):
            out_path.unlink()
        if report.get("kind") == "classifier":
            why = (f"agrees with the float model on {report['agreement']:.2%} of "
                   f"{report['n']} {report['checked_on']} (argmax), below the required "
                   f"{min_agreement:.2%}; largest probability difference "
                   f"{report['max_prob_diff']:.3f}")
        elif "why" in report:
            why = report["why"]
        else:
            why = (f"raises the MAE by {report.get('mae_change')} "
                   f"({report.get('mae_change_of_range')} of the target range), more than "
                   f"{MAX_REGRESSION_CHANGE:.0%}")
        raise QuantisationError(f"int8 check failed: {out_path} {why}; the int8 model was "
                                f"not kept (ship the float model, or calibrate on more "
                                f"windows)")
    from host.data.dataset import atomic_write

    out_path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(out_path, lambda fh: fh.write(qbytes))
    report["path"] = str(out_path)
    return report


# ----------------------------------------------------------------------------
# Cross-validation
# ----------------------------------------------------------------------------

def cross_validate_model(task: str, model: str, ws, k: int, seed: int = 0,
                         uses_imu: bool | None = None, progress: bool = True,
                         classes: list[str] | None = None, augment: int = 0,
                         profile: str = "roboskin", **hp) -> dict:
    """Grouped K-fold CV (whole trials per fold, :func:`host.data.splits.group_kfold`):
    pooled held-out metrics plus each fold's accuracy (or MAE). ``augment``
    rotated copies are added to each fold's training part only."""
    from tqdm import tqdm

    from host.data.splits import group_kfold
    from host.data.windows import DataError

    k = _check_int("cv", k, 2)
    if len(ws) < k:
        raise TrainError(f"cv={k} folds need at least {k} windows, the data have {len(ws)}")
    try:
        folds = list(group_kfold(ws, k, seed))
    except DataError as exc:
        raise TrainError(f"cv={k}: {exc}") from None
    layout = LAYOUT[model]
    uses_imu = _default_imu(model, ws) if uses_imu is None else uses_imu
    X = model_inputs(ws, layout, uses_imu)
    hp = _hyper(model, **hp)
    regression = task == "pressure"
    if not regression:
        classes = classes or sorted({str(x) for x in ws.labels})
        y = _label_ids(ws.labels, classes)
        pooled = np.zeros((len(ws), len(classes)))
    else:
        y = np.asarray(ws.targets, np.float64)
        pooled = np.zeros(len(ws))
    per_fold = []
    for f, (tr, te) in enumerate(tqdm(folds, desc=f"cv {k} folds", unit="fold",
                                      disable=not progress or None, file=sys.stderr,
                                      leave=False)):
        if not regression:
            present = np.unique(y[tr])
            if len(present) < 2:
                raise TrainError(f"cv={k}: fold {f} trains on one class only "
                                 f"({classes[int(present[0])]!r}); use fewer folds or more "
                                 f"trials per class")
        if model == "rule":
            rc = _fit_rule(task, ws.subset(tr), classes)
            out = _rule_probs(rc, X[te])
        else:
            Xf, yf = X[tr], y[tr]
            if augment:
                a = augment_rotations(ws.subset(tr), augment, profile)
                Xf = model_inputs(a, layout, uses_imu)
                yf = (np.asarray(a.targets, np.float64) if regression
                      else _label_ids(a.labels, classes))
            pipe, _ = _fit(task, model, Xf, yf, 0 if regression else len(classes), hp,
                           seed, False, f"fold {f}")
            if regression:
                out = pipe.predict(X[te]).reshape(-1)
            else:
                out = np.zeros((len(te), len(classes)))
                out[:, pipe.steps[-1][1].classes_.astype(int)] = pipe.predict_proba(X[te])
        pooled[te] = out
        if regression:
            per_fold.append(regression_metrics(y[te], out)["mae"])
        else:
            per_fold.append(float((np.argmax(out, 1) == y[te]).mean()))
    if regression:
        res = regression_metrics(y, pooled)
        res["fold_mae"] = [round(x, 6) for x in per_fold]
    else:
        res = _class_report(task, ws, y, pooled, classes)
        res["fold_accuracy"] = [round(x, 6) for x in per_fold]
    res.update({"folds": k, "grouped": True,
                "fold_mean": round(float(np.mean(per_fold)), 6),
                "fold_std": round(float(np.std(per_fold)), 6)})
    return res


# ----------------------------------------------------------------------------
# Training
# ----------------------------------------------------------------------------

def _default_imu(model: str, ws) -> bool:
    return model == "fnn" and ws.imu is not None


def _hyper(model: str, hidden=None, alpha=None, epochs=None, temporal=None) -> dict:
    hidden = tuple(DEFAULT_HIDDEN if hidden is None else hidden)
    if len(hidden) != 2 or not all(isinstance(h, (int, np.integer)) and h >= 1 for h in hidden):
        raise TrainError(f"hidden must be two layer sizes >= 1, got hidden={hidden!r}")
    alpha = DEFAULT_ALPHA.get(model, 0.0) if alpha is None else alpha
    if isinstance(alpha, bool) or not isinstance(alpha, (int, float)) or not (
            math.isfinite(alpha) and alpha >= 0):
        raise TrainError(f"alpha must be a finite number >= 0, got alpha={alpha!r}")
    epochs = _check_int("epochs", DEFAULT_EPOCHS if epochs is None else epochs, 1)
    return {"hidden": [int(h) for h in hidden], "alpha": float(alpha), "epochs": epochs,
            "temporal": temporal}


def _check_windows(ws, task: str, what: str) -> None:
    from host.data.windows import WindowSet

    if not isinstance(ws, WindowSet):
        raise TrainError(f"{what} must be a host.data.windows.WindowSet, got {type(ws).__name__}")
    if len(ws) == 0:
        raise TrainError(f"{what} holds no windows")
    if ws.task != task:
        raise TrainError(f"{what} was loaded for task {ws.task!r}, not task={task!r}")
    if task == "pressure":
        if ws.targets is None:
            raise TrainError(f"{what}: task pressure needs targets")
        if not np.isfinite(ws.targets).all():
            raise TrainError(f"{what}: {int((~np.isfinite(ws.targets)).sum())} targets are "
                             f"NaN or inf")
    elif ws.labels is None:
        raise TrainError(f"{what}: task {task} needs labels")


def _holdout(ws, seed: int):
    """(train, test, how) when no test windows were given."""
    from host.data.splits import split_grouped, split_time
    from host.data.windows import DataError

    if len(np.unique(ws.groups)) >= 2:
        tr, te = split_grouped(ws, 0.25, seed)
        return ws.subset(tr), ws.subset(te), "grouped split: 25% of the trials held out"
    try:
        tr, te = split_time(ws, 0.7)
        return ws.subset(tr), ws.subset(te), "time split: last 30% of the trial held out"
    except DataError:
        return ws, None, "none: one trial without time order; metrics on the training windows"


def train_model(task: str, model: str, ws_train, ws_test=None, cv: int | None = None,
                quantise: bool | str = False, seed: int = 0, out_dir=None,
                progress: bool = True,
                *, uses_imu: bool | None = None, hidden=None, alpha: float | None = None,
                epochs: int | None = None, temporal: bool | None = None, augment: int = 0,
                profile: str = "roboskin",
                calibration_windows: int = 2000, calibrate_method: str = "minmax",
                min_agreement: float = MIN_AGREEMENT) -> dict:
    """Train ``model`` for ``task`` on ``ws_train``; evaluate on ``ws_test`` (or a
    held-out part of ``ws_train``, see the module doc); write the model folder
    ``out_dir`` (ONNX + manifest.json, + int8 when ``quantise``). Returns the
    result (metrics, int8 check, files, timings) as a JSON-able dict; it is also
    the manifest's core.

    ``uses_imu``: None = the fnn uses the IMU when the windows carry it.
    ``hidden``, ``alpha``, ``epochs``: MLP layer sizes (default (64, 32)), L2
    penalty (MLP 1e-3, ridge 150) and most epochs (300, with early stopping on the
    training loss). ``temporal``: the fnn's fixed first layer of frame-to-frame
    changes (:class:`TemporalFeatures`); None = on for the fnn when T >= 2.
    ``augment``: add this many rotated copies of the training
    windows (:func:`augment_rotations`, rotations that map the ``profile``'s pin
    layout onto itself), so a model need not see every drag direction; ``vectors``
    layout only. ``calibration_windows`` training windows (a seeded random
    choice) calibrate the int8 model with ``calibrate_method`` (minmax, percentile
    or entropy); ``min_agreement`` is the argmax agreement it must reach on the
    held-out windows. Nothing is written when a check fails (:class:`TrainError`,
    :class:`QuantisationError`), except with ``quantise="if-passes"``: then a failed
    int8 check keeps the float model as the default and records why in
    ``result["int8"]["failed"]`` (the manifest's ``int8``).
    """
    if quantise not in (True, False, "if-passes"):
        raise TrainError(f"quantise must be True, False or 'if-passes', got {quantise!r}")
    from host.data.dataset import atomic_write, atomic_write_text
    from host.learn.onnx_io import write_model

    t_start = time.perf_counter()
    _check_choice("task", task, TASKS)
    _check_choice("model", model, MODELS + ("cnn",))
    if model == "cnn":
        raise TrainError("model=cnn is trained by host.learn.cnn (PyTorch), not host.learn.train")
    if model not in TASK_MODELS[task]:
        raise TrainError(f"model={model!r} does not serve task={task!r}; task {task} takes "
                         f"{list(TASK_MODELS[task])}")
    seed = _check_int("seed", seed, 0)
    if out_dir is None:
        raise TrainError("out_dir is required: the folder to write the model to")
    _check_windows(ws_train, task, "ws_train")
    holdout = "given"
    if ws_test is None:
        ws_train, ws_test, holdout = _holdout(ws_train, seed)
    else:
        _check_windows(ws_test, task, "ws_test")
        if ws_test.window != ws_train.window:
            raise TrainError(f"ws_test has windows of T={ws_test.window}, ws_train T="
                             f"{ws_train.window}")
    if cv is not None:
        cv = _check_int("cv", cv, 2)
    if not (0.0 < min_agreement <= 1.0):
        raise TrainError(f"min_agreement must be in (0, 1], got min_agreement={min_agreement!r}")
    T = ws_train.window
    layout = LAYOUT[model]
    if model == "rule":
        uses_imu = False
    elif uses_imu is None:
        uses_imu = _default_imu(model, ws_train)
    elif uses_imu and layout != "vectors":
        raise TrainError(f"uses_imu=True needs input_layout vectors; {model} reads {layout}")
    if uses_imu and ws_test is not None and ws_test.imu is None:
        raise TrainError("the model uses the IMU but the test windows carry none")
    if temporal is None:
        temporal = model == "fnn" and T >= 2
    if temporal and (model != "fnn" or T < 2):
        raise TrainError(f"temporal=True needs the fnn and T >= 2 frames, got model={model!r} "
                         f"T={T}")
    tspec = ({"T": T, "n_pins": ws_train.n_pins, "uses_imu": bool(uses_imu)} if temporal
             else None)
    hp = _hyper(model, hidden, alpha, epochs, tspec) if model != "rule" else {}
    regression = task == "pressure"

    augment = _check_int("augment", augment, 0)
    if augment and layout != "vectors":
        raise TrainError(f"augment={augment} rotates pin vectors; {model} reads {layout}")
    if augment and model == "rule":
        raise TrainError("augment: the rule has nothing to learn from rotated copies")
    ws_fit = augment_rotations(ws_train, augment, profile) if augment else ws_train
    X = model_inputs(ws_fit, layout, uses_imu)
    Xt = model_inputs(ws_test, layout, uses_imu) if ws_test is not None else None
    if not np.isfinite(X).all():
        raise TrainError("model inputs hold NaN or inf after encoding")
    if len(X) >= 2 and not (X.std(axis=0) > 0).any():
        raise TrainError(f"every input feature of the {len(X)} training windows has zero "
                         f"variance (the windows are all identical): nothing to learn")
    if regression:
        y = np.asarray(ws_fit.targets, np.float64)
        classes = []
        yt = None if ws_test is None else np.asarray(ws_test.targets, np.float64)
        if not (y.std() > 0):
            raise TrainError(f"targets: every training target is {y[0]}; nothing to learn")
    else:
        classes = sorted({str(x) for x in ws_train.labels})
        if len(classes) < 2:
            raise TrainError(f"labels: task {task} needs training windows of at least 2 "
                             f"classes, the data hold {len(classes)}: {classes}")
        y = _label_ids(ws_fit.labels, classes)
        yt = None if ws_test is None else _label_ids(ws_test.labels, classes)
    result = {"task": task, "model": model, "T": T, "input_layout": layout,
              "uses_imu": bool(uses_imu), "temporal_features": bool(temporal),
              "classes": classes, "seed": seed,
              "holdout": holdout, "out_dir": str(out_dir)}
    metrics: dict = {}
    if cv is not None:
        t0 = time.perf_counter()
        metrics["cv"] = cross_validate_model(task, model, ws_train, cv, seed, uses_imu, progress,
                                             classes=classes or None, augment=augment,
                                             profile=profile, **hp)
        metrics["cv"]["cv_s"] = round(time.perf_counter() - t0, 3)

    # -- fit and export ------------------------------------------------------
    out = Path(out_dir)
    if model == "rule":
        rc = _fit_rule(task, ws_train, classes)
        metrics["train"] = _class_report(task, ws_train, y, _rule_probs(rc, X), classes)
        if ws_test is not None:
            metrics["test"] = _class_report(task, ws_test, yt, _rule_probs(rc, Xt), classes)
        result["rule"] = rc.rule
        result["metrics"] = metrics
        result["int8"] = ({"skipped": "a rule has no weights to quantise"} if quantise
                          else None)
        doc = {"format": FORMAT, "version": VERSION, "feature_spec": FEATURE_SPEC_VERSION,
               "onnx": None, "sha256": {}, "size_bytes": 0,
               "input": {"name": "x", "shape": [None, int(X.shape[1])], "dtype": "float32"},
               **rc.to_manifest(), "metrics": metrics,
               "training": _training_info(ws_train, ws_test, holdout, seed, {})}
        out.mkdir(parents=True, exist_ok=True)
        atomic_write_text(out / MANIFEST, json.dumps(doc, indent=1, default=_plain))
        result["files"] = {MANIFEST: {"size_bytes": (out / MANIFEST).stat().st_size}}
        result["train_s"] = round(time.perf_counter() - t_start, 3)
        return result

    pipe, fit_info = _fit(task, model, X, y, len(classes), hp, seed, progress,
                          f"{task} {model} T={T}")
    onnx_model = _to_onnx(pipe, X.shape[1], task)
    fbytes = onnx_model.SerializeToString()
    sess = _session(fbytes)
    n0 = len(ws_train)                     # the original windows come first in X
    out_train = _run(sess, X[:n0])
    out_test = _run(sess, Xt) if Xt is not None else None
    if regression:
        metrics["train"] = regression_metrics(y[:n0], out_train)
        if out_test is not None:
            metrics["test"] = regression_metrics(yt, out_test)
    else:
        metrics["train"] = _class_report(task, ws_train, y[:n0], out_train, classes)
        if out_test is not None:
            metrics["test"] = _class_report(task, ws_test, yt, out_test, classes)

    # -- int8 ------------------------------------------------------------------
    int8 = None
    qbytes = None
    if quantise:
        rng = np.random.default_rng(seed)
        n_cal = min(len(X), _check_int("calibration_windows", calibration_windows, 1))
        cal = X[np.sort(rng.choice(len(X), n_cal, replace=False))]
        check_X = Xt if Xt is not None else X[:n0]
        check_y = yt if Xt is not None else y[:n0]
        with tempfile.TemporaryDirectory(prefix="tacfoot-int8-") as tmp:
            qpath = Path(tmp) / INT8_NAME
            try:
                int8 = quantise_model(fbytes, cal, qpath, check_inputs=check_X,
                                      check_targets=check_y, min_agreement=min_agreement,
                                      calibrate_method=calibrate_method)
                qbytes = qpath.read_bytes()
            except QuantisationError as exc:      # name the file the user asked for
                msg = str(exc).replace(str(qpath), str(out / INT8_NAME))
                if quantise != "if-passes":
                    raise QuantisationError(msg) from None
                int8 = {"failed": msg}            # keep the float model, say why
        if qbytes is not None:
            int8.pop("path", None)
            q_out = _run(_session(qbytes), check_X)
            if regression:
                int8["metrics"] = regression_metrics(check_y, q_out)
            else:
                int8["metrics"] = _class_report(task, ws_test if Xt is not None else ws_train,
                                                check_y, q_out, classes)
    result["metrics"] = metrics
    result["int8"] = int8
    result["fit"] = fit_info

    # -- write -----------------------------------------------------------------
    import onnx

    out.mkdir(parents=True, exist_ok=True)
    default = INT8_NAME if qbytes is not None else FLOAT_NAME
    extra = {"model": model, "task": task, "classes": classes, "T": T,
             "input_layout": layout, "uses_imu": bool(uses_imu),
             "output": "variable" if regression else "probabilities",
             "output_kind": "value" if regression else "probabilities",
             "variant": "int8" if qbytes is not None else "float",
             "metrics": metrics, "int8": int8,
             "training": _training_info(ws_train, ws_test, holdout, seed,
                                        dict(hp, **fit_info, augment=augment,
                                             augmented_deg=ws_fit.source.get("augmented_deg"),
                                             fit_windows=int(len(X))))}
    if regression:
        extra.update({"target_mean": float(y.mean()),
                      "target_range": [float(y.min()), float(y.max())],
                      "input_clip": [X.min(axis=0).tolist(), X.max(axis=0).tolist()]})
    # the default file and a first manifest, then the float file beside an int8
    # default, then the manifest again with the checksum and size of every file
    write_model(onnx_model if qbytes is None else onnx.load_from_string(qbytes), out,
                kind=task, n_features=X.shape[1], extra=extra, onnx_name=default)
    names = {FLOAT_NAME: "float"}
    if qbytes is not None:
        atomic_write(out / FLOAT_NAME, lambda fh: fh.write(fbytes))
        names[INT8_NAME] = "int8"
    else:
        with contextlib.suppress(FileNotFoundError):
            (out / INT8_NAME).unlink()        # a stale int8 file from an earlier run
        with contextlib.suppress(FileNotFoundError):
            (out / FLOAT_MANIFEST).unlink()
    files = {name: {"variant": v, "size_bytes": (out / name).stat().st_size,
                    "sha256": sha256_file(out / name)} for name, v in names.items()}
    doc = json.loads((out / MANIFEST).read_text())
    doc.update({"sha256": {n: f["sha256"] for n, f in files.items()}, "files": files,
                "variants": {f["variant"]: n for n, f in files.items()},
                "size_bytes": files[default]["size_bytes"]})
    atomic_write_text(out / MANIFEST, json.dumps(doc, indent=1, default=_plain))
    if qbytes is not None:
        doc.update({"onnx": FLOAT_NAME, "variant": "float",
                    "size_bytes": files[FLOAT_NAME]["size_bytes"]})
        atomic_write_text(out / FLOAT_MANIFEST, json.dumps(doc, indent=1, default=_plain))
    result["files"] = files
    result["default"] = default
    result["train_s"] = round(time.perf_counter() - t_start, 3)
    return result


def _training_info(ws_train, ws_test, holdout: str, seed: int, hp: dict) -> dict:
    return {"data": ws_train.summary(),
            "test_data": None if ws_test is None else ws_test.summary(),
            "holdout": holdout, "seed": seed, **hp}


def _plain(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(type(o).__name__)


# ----------------------------------------------------------------------------
# Simulated benchmark data
# ----------------------------------------------------------------------------

BENCH_FPS = 120
#: surface parameters per scene kind: (training range, test range beyond it).
#: The gait (depth, speeds, timings, direction) has one range for both. Friction
#: has one range for hard and soft, and one for the three textures, so that it
#: tells nothing about the class; wet is low friction by definition.
SURFACE_RANGES = {
    "hard": {"preset": "hard", "stiffness_n_per_mm": ((100, 300), (50, 600)),
             "mu": ((0.6, 1.0), (0.5, 1.2))},
    "soft": {"preset": "soft", "stiffness_n_per_mm": ((1.0, 2.0), (0.8, 2.4)),
             "mu": ((0.6, 1.0), (0.5, 1.2))},
    "wet": {"preset": "wet", "stiffness_n_per_mm": ((100, 300), (50, 600)),
            "mu": ((0.04, 0.12), (0.02, 0.15))},
    "no-touch": {"preset": "hard"},
    "smooth": {"preset": "smooth", "mu": ((0.45, 0.75), (0.35, 0.85))},
    "lego": {"preset": "lego", "mu": ((0.45, 0.75), (0.35, 0.85)),
             "texture_amplitude_mm": ((0.2, 0.3), (0.15, 0.35)),
             "stud_pitch_mm": ((7.0, 9.0), (6.0, 10.0))},
    "concrete": {"preset": "concrete", "mu": ((0.45, 0.75), (0.35, 0.85)),
                 "texture_amplitude_mm": ((0.1, 0.15), (0.08, 0.18))},
    "slip": {"preset": "hard", "mu": ((0.3, 0.6), (0.25, 0.7)),
             "wet_mu": ((0.03, 0.1), (0.02, 0.14))},
    "press-hard": {"preset": "hard", "stiffness_n_per_mm": ((100, 300), (50, 600))},
    "press-soft": {"preset": "soft", "stiffness_n_per_mm": ((1.0, 2.0), (0.8, 2.4))},
}
BENCH_KINDS = tuple(SURFACE_RANGES)


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return repr(round(float(v), 6))
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(f"cannot write {type(v).__name__} to a scene file")


def scene_toml(doc: dict) -> str:
    """A scene dict (top-level keys, tables, a ``timeline`` list and an optional
    ``surfaces`` table of tables) as scene-file TOML (docs/simulator.md)."""
    lines = []
    for k, v in doc.items():
        if not isinstance(v, dict) and k != "timeline":
            lines.append(f"{k} = {_toml_value(v)}")
    for k, v in doc.items():
        if isinstance(v, dict) and k != "surfaces":
            lines.append(f"\n[{k}]")
            lines += [f"{kk} = {_toml_value(vv)}" for kk, vv in v.items()]
    for name, table in doc.get("surfaces", {}).items():
        lines.append(f"\n[surfaces.{name}]")
        lines += [f"{kk} = {_toml_value(vv)}" for kk, vv in table.items()]
    for a in doc.get("timeline", []):
        lines.append("\n[[timeline]]")
        lines += [f"{kk} = {_toml_value(vv)}" for kk, vv in a.items()]
    return "\n".join(lines) + "\n"


def bench_scene(kind: str, rng: np.random.Generator, beyond: bool = False) -> dict:
    """A randomised scene (a dict for :func:`scene_toml`) of one kind:

    * ``hard``, ``soft``, ``wet``, ``no-touch``: a step. The foot comes down while
      still moving sideways (a touchdown with foot speed, as in a gait: one-frame
      lower and drag steps in turn, so friction acts from the first touch), drags
      through the stance, and lifts; ``no-touch`` swings the same way in the air;
    * ``smooth``, ``lego``, ``concrete``: a press and a long drag that slides;
    * ``slip``: the ``slip-onset`` scene randomised: a drag on a hard floor until
      friction saturates and the patch slips, a lift, then a wet patch that slips
      almost at once;
    * ``press-hard``, ``press-soft``: presses to two random depths with holds
      (pressure).

    Surface parameters (mu, stiffness, texture amplitude, stud pitch) come from the
    training range, or with ``beyond=True`` from the wider test range
    (:data:`SURFACE_RANGES`); camera noise too. The gait (depths, speeds, timings,
    directions) has one range for both.
    """
    _check_choice("kind", kind, BENCH_KINDS)
    spec = SURFACE_RANGES[kind]

    def U(lo, hi):
        return float(rng.uniform(lo, hi))

    def surf(key):
        lo, hi = spec[key][1 if beyond else 0]
        return U(lo, hi)

    noise = U(0.5, 4.0) if beyond else U(1.0, 3.0)
    doc = {"name": f"bench-{kind}", "description": f"benchmark {kind} scene (host.learn.train)",
           "hover_mm": U(1.5, 2.5),
           "effects": ["glare", {"name": "camera_noise", "sigma": round(noise, 3)},
                       "imu_noise"],
           "sensor": {"profile": "roboskin", "fps": BENCH_FPS}}
    surface = {"preset": spec["preset"]}
    for key in ("stiffness_n_per_mm", "mu", "texture_amplitude_mm", "stud_pitch_mm"):
        if key in spec:
            surface[key] = surf(key)
    doc["surface"] = surface
    theta = U(0.0, 360.0)
    step = 1.0 / BENCH_FPS
    tl = [{"action": "hold", "duration_s": U(0.03, 0.08)}]
    if kind in ("hard", "soft", "wet", "no-touch"):
        speed = U(8.0, 14.0)
        if kind == "no-touch":
            tl += [{"action": "drag", "direction_deg": theta, "speed_mm_s": speed,
                    "duration_s": U(0.3, 0.45)},
                   {"action": "lift", "height_mm": U(0.5, 2.0), "duration_s": 0.1},
                   {"action": "drag", "direction_deg": (theta + 180) % 360,
                    "speed_mm_s": speed, "duration_s": U(0.1, 0.2)}]
        else:
            depth = U(2.3, 3.0)
            n_low = int(round(U(0.06, 0.1) * BENCH_FPS))
            tl.append({"action": "lower", "depth_mm": 0.0, "duration_s": U(0.03, 0.06)})
            for k in range(1, n_low + 1):
                tl.append({"action": "lower", "depth_mm": depth * k / n_low, "duration_s": step})
                tl.append({"action": "drag", "direction_deg": theta, "speed_mm_s": 2 * speed,
                           "duration_s": step})
            tl += [{"action": "drag", "direction_deg": theta, "speed_mm_s": speed,
                    "duration_s": U(0.3, 0.45)},
                   {"action": "lift", "height_mm": doc["hover_mm"], "duration_s": U(0.06, 0.1)},
                   {"action": "hold", "duration_s": U(0.03, 0.06)}]
    elif kind in ("smooth", "lego", "concrete"):
        tl += [{"action": "lower", "depth_mm": U(1.5, 2.5), "duration_s": U(0.1, 0.15)},
               {"action": "drag", "direction_deg": theta, "speed_mm_s": U(15.0, 25.0),
                "duration_s": U(0.6, 0.9)},
               {"action": "lift", "height_mm": doc["hover_mm"], "duration_s": U(0.1, 0.15)}]
    elif kind == "slip":
        wet = {"preset": "wet", "mu": surf("wet_mu")}
        doc["surfaces"] = {"patch": wet}
        speed = U(6.0, 10.0)
        tl += [{"action": "lower", "depth_mm": U(2.0, 3.0), "duration_s": U(0.15, 0.25)},
               {"action": "drag", "direction_deg": theta, "speed_mm_s": speed,
                "duration_s": U(0.5, 0.8)},
               {"action": "lift", "height_mm": doc["hover_mm"], "duration_s": U(0.15, 0.25)},
               {"action": "lower", "surface": "patch", "depth_mm": U(2.0, 3.0),
                "duration_s": U(0.15, 0.25)},
               {"action": "drag", "direction_deg": (theta + U(90, 270)) % 360,
                "speed_mm_s": U(6.0, 10.0), "duration_s": U(0.3, 0.5)},
               {"action": "lift", "height_mm": doc["hover_mm"], "duration_s": U(0.15, 0.25)}]
    else:                                   # press-hard, press-soft
        d1, d2 = U(0.5, 3.5), U(0.5, 3.5)
        tl += [{"action": "lower", "depth_mm": d1, "duration_s": U(0.1, 0.3)},
               {"action": "hold", "duration_s": U(0.05, 0.15)},
               {"action": "lower", "depth_mm": d2, "duration_s": U(0.1, 0.2)},
               {"action": "hold", "duration_s": U(0.05, 0.15)},
               {"action": "lift", "height_mm": doc["hover_mm"], "duration_s": U(0.1, 0.3)}]
    doc["timeline"] = tl
    return doc


def simulate_scenes(out_dir, kinds, n_per_kind: int, seed: int, beyond: bool = False,
                    progress: bool = True) -> Path:
    """A dataset folder of ``n_per_kind`` randomised trials of each kind, the scene
    files beside it (``out_dir/scenes``). Trial k of a kind uses simulator seed
    ``seed * 100000 + k`` and its parameters come from a random stream of
    (``seed``, kind, k), so two calls with different seeds share nothing.
    Reuses a complete folder written with the same arguments."""
    from tqdm import tqdm

    from host.data.simulate import simulate_to_dataset
    from host.data.dataset import atomic_write_text, is_dataset

    kinds = [_check_choice("kind", k, BENCH_KINDS) for k in kinds]
    n_per_kind = _check_int("n_per_kind", n_per_kind, 1)
    seed = _check_int("seed", seed, 0)
    out = Path(out_dir)
    data = out / "data"
    key = {"kinds": kinds, "n_per_kind": n_per_kind, "seed": seed, "beyond": bool(beyond),
           "ranges": json.loads(json.dumps({k: SURFACE_RANGES[k] for k in kinds})),
           "version": 1}
    stamp = out / "bench.json"
    if stamp.is_file() and is_dataset(data):
        try:
            if json.loads(stamp.read_text()) == key:
                return data
        except json.JSONDecodeError:
            pass
    import shutil

    if data.exists():
        shutil.rmtree(data)
    scenes = out / "scenes"
    scenes.mkdir(parents=True, exist_ok=True)
    jobs = [(kind, k) for k in range(n_per_kind) for kind in kinds]
    for kind, k in tqdm(jobs, desc=f"simulate {out.name}", unit="trial",
                        disable=not progress or None, file=sys.stderr, leave=False):
        rng = np.random.default_rng([seed, BENCH_KINDS.index(kind), k, int(beyond)])
        path = scenes / f"{kind}_{k:03d}.toml"
        path.write_text(scene_toml(bench_scene(kind, rng, beyond)))
        simulate_to_dataset(str(path), data, seed=seed * 100000 + k, trials=1, progress=False)
    atomic_write_text(stamp, json.dumps(key))
    return data


# ----------------------------------------------------------------------------
# The simulated benchmarks
# ----------------------------------------------------------------------------

#: trials per kind (train, test) for the full and the quick benchmark
BENCH_TRIALS = {
    "full": {"surface": (24, 8), "texture": (16, 6), "slip": (30, 10), "pressure": (30, 10)},
    "quick": {"surface": (8, 3), "texture": (6, 3), "slip": (10, 4), "pressure": (10, 4)},
}
BENCH_TARGETS = {"surface_accuracy": 0.99, "lego_vs_smooth_accuracy": 0.99,
                 "concrete_vs_smooth_accuracy": 0.99, "slip_f1": 0.95,
                 "slip_median_latency_frames": 3.0, "pressure_mae_of_range": 0.05}
#: the benchmark's model per task (the MLPs are regularised harder than the
#: defaults: the test surfaces lie beyond the training range; surface and texture
#: add 3 rotated copies of each training window, so the drag direction is no clue).
#: Texture uses the fnn (frame-to-frame layer + IMU): the grid FNN reached 50 %
#: (Lego) and 75 % (concrete) on sliding windows in the same benchmark.
BENCH_MODELS = {"surface": ("fnn", {"alpha": 0.1, "augment": 3}),
                "texture": ("fnn", {"alpha": 0.01, "augment": 3}),
                "slip": ("fnn", {"alpha": 0.01}), "pressure": ("ridge", {})}


def _trial_scene(ws) -> np.ndarray:
    """The scene kind of each window's trial (``bench-lego`` -> ``lego``)."""
    names = {int(t["group"]): str(t.get("scene") or "").removeprefix("bench-")
             for t in ws.source.get("trials", [])}
    return np.array([names.get(int(g), "") for g in ws.groups], object)


def _subset_accuracy(model_dir, ws, mask, variant=None) -> dict | None:
    from host.learn.evaluate import evaluate_model

    if not mask.any():
        return None
    ev = evaluate_model(model_dir, ws.subset(np.flatnonzero(mask)), variant=variant)
    return {"n": ev["n_windows"], "accuracy": ev["metrics"]["accuracy"],
            "macro_f1": ev["metrics"]["macro_f1"], "confusion": ev["metrics"]["confusion"]}


def sim_benchmarks(out_dir, quick: bool = False, T: int = 3, seed: int = 0,
                   progress: bool = True) -> dict:
    """The issue's simulated accuracy figures, measured end to end.

    For each task it simulates training trials (surface parameters in the
    training range, seeds of one stream) and test trials (unseen seeds, surface
    parameters drawn from a wider range that reaches beyond the training range;
    :data:`SURFACE_RANGES`), cuts windows of T frames with the Pi's pipeline,
    trains, exports, quantises (int8, checked against float) and evaluates the
    shipped (int8) model on the test windows through the Pi's loader:

    * surface: 4-class FNN (vectors + IMU) on hard / soft / wet / no-touch steps;
    * texture: grid FNN, Lego vs smooth and concrete vs smooth, each a model of
      {texture, smooth, no-touch}; accuracy on all test windows, on contact
      windows, and on contact windows while the foot slides (a texture is only felt
      while sliding; in the stick phase Lego and smooth are the same surface);
    * slip: FNN slip detector on randomised ``slip-onset`` scenes; slip F1 and the
      detection latency in frames from each true onset;
    * pressure: Ridge on all vectors of press scenes; MAE as a share of the range.

    Data and models go under ``out_dir`` (data folders are reused when present);
    the result is also written to ``out_dir/benchmarks.json``.
    """
    from host.data.load import load_spec
    from host.data.dataset import atomic_write_text
    from host.learn.evaluate import evaluate_model

    T = _check_int("T", T, 1)
    seed = _check_int("seed", seed, 0)
    counts = BENCH_TRIALS["quick" if quick else "full"]
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    res: dict = {"T": T, "quick": bool(quick), "seed": seed, "fps": BENCH_FPS,
                 "trials": counts, "targets": BENCH_TARGETS,
                 "surface_ranges": {k: {kk: vv for kk, vv in v.items()}
                                    for k, v in SURFACE_RANGES.items()},
                 "command": f"python -c \"from host.learn.train import sim_benchmarks; "
                            f"sim_benchmarks('{out}', quick={bool(quick)}, T={T})\""}
    figures: dict = {}
    cache: dict = {}
    t_all = time.perf_counter()

    def data(task, kinds):
        n_tr, n_te = counts[task]
        t0 = time.perf_counter()
        tr = simulate_scenes(out / f"{task}-train", kinds, n_tr, 10 * seed + 1, False, progress)
        te = simulate_scenes(out / f"{task}-test", kinds, n_te, 10 * seed + 2, True, progress)
        sim_s = time.perf_counter() - t0
        return tr, te, sim_s

    def load(path, task, **kw):
        return load_spec(str(path), task, T, progress=False, cache=cache, **kw)

    def train(task, ws_tr, ws_te, name, model=None, **kw):
        m, hp = BENCH_MODELS[task]
        m = model or m
        args = dict(seed=seed, out_dir=out / "models" / name, progress=progress, **dict(hp, **kw))
        # a failed int8 check is reported, and the float model measured
        r = train_model(task, m, ws_tr, ws_te, quantise="if-passes", **args)
        return r, out / "models" / name

    def summary(r, ev):
        return {"model": r["model"], "uses_imu": r["uses_imu"], "fit": r.get("fit"),
                "train_s": r["train_s"], "variant": ev["variant"],
                "int8_check": {k: r["int8"][k] for k in ("agreement", "max_prob_diff",
                                                          "max_abs_diff", "mae_change",
                                                          "saturation", "failed")
                               if k in r["int8"]},
                "float_bytes": r["files"][FLOAT_NAME]["size_bytes"],
                "int8_bytes": r["files"].get(INT8_NAME, {}).get("size_bytes"),
                "latency_ms": ev["latency_ms"], "encode_ms": ev["encode_ms"]}

    def float_eval(mdir, ws):
        """The float model's evaluation (the same as the default without int8)."""
        return evaluate_model(mdir, ws, variant="float")

    # -- surface -------------------------------------------------------------
    tr, te, sim_s = data("surface", ["hard", "soft", "wet", "no-touch"])
    t0 = time.perf_counter()
    ws_tr, ws_te = load(tr, "surface"), load(te, "surface")
    load_s = time.perf_counter() - t0
    r, mdir = train("surface", ws_tr, ws_te, "surface")
    ev = evaluate_model(mdir, ws_te)
    evf = float_eval(mdir, ws_te)
    res["surface"] = dict(summary(r, ev), accuracy_int8=ev["metrics"]["accuracy"],
                          accuracy_float=evf["metrics"]["accuracy"],
                          per_class=ev["metrics"]["per_class"],
                          confusion=ev["metrics"]["confusion"],
                          windows={"train": len(ws_tr), "test": len(ws_te)},
                          sim_s=round(sim_s, 1), load_s=round(load_s, 1))
    figures["surface_accuracy"] = ev["metrics"]["accuracy"]

    # -- texture -------------------------------------------------------------
    tr, te, sim_s = data("texture", ["smooth", "lego", "concrete"])
    t0 = time.perf_counter()
    tx_tr, tx_te = load(tr, "texture"), load(te, "texture")
    sl_te = load(te, "slip", min_classes=1)
    load_s = time.perf_counter() - t0
    if not (np.array_equal(sl_te.groups, tx_te.groups)
            and np.array_equal(sl_te.t_index, tx_te.t_index)):
        raise TrainError("texture and slip windows of the same trials differ")   # never
    sliding = sl_te.labels.astype(str) == "slip"
    kind_tr, kind_te = _trial_scene(tx_tr), _trial_scene(tx_te)
    res["texture"] = {"sim_s": round(sim_s, 1), "load_s": round(load_s, 1)}
    for other in ("lego", "concrete"):
        name = f"{other}-vs-smooth"
        a = tx_tr.subset(np.isin(kind_tr, [other, "smooth"]))
        keep_te = np.isin(kind_te, [other, "smooth"])
        b = tx_te.subset(keep_te)
        contact = b.contact
        slide = sliding[keep_te] & contact
        r, mdir = train("texture", a, b, name)
        ev = evaluate_model(mdir, b)
        evf = float_eval(mdir, b)
        entry = dict(summary(r, ev), accuracy_all_int8=ev["metrics"]["accuracy"],
                     accuracy_all_float=evf["metrics"]["accuracy"],
                     contact=_subset_accuracy(mdir, b, contact),
                     sliding=_subset_accuracy(mdir, b, slide),
                     windows={"train": len(a), "test": len(b), "test_contact": int(contact.sum()),
                              "test_sliding": int(slide.sum())})
        res["texture"][name] = entry
        figures[f"{other}_vs_smooth_accuracy"] = (entry["sliding"] or {}).get("accuracy")
        figures[f"{other}_vs_smooth_accuracy_contact"] = (entry["contact"] or {}).get("accuracy")
        figures[f"{other}_vs_smooth_accuracy_all"] = entry["accuracy_all_int8"]

    # -- slip ------------------------------------------------------------------
    tr, te, sim_s = data("slip", ["slip"])
    t0 = time.perf_counter()
    ws_tr, ws_te = load(tr, "slip"), load(te, "slip")
    load_s = time.perf_counter() - t0
    r, mdir = train("slip", ws_tr, ws_te, "slip")
    ev = evaluate_model(mdir, ws_te)
    res["slip"] = dict(summary(r, ev), slip_f1=ev["metrics"]["slip_f1"],
                       accuracy=ev["metrics"]["accuracy"], latency=ev["metrics"]["latency"],
                       confusion=ev["metrics"]["confusion"],
                       windows={"train": len(ws_tr), "test": len(ws_te)},
                       sim_s=round(sim_s, 1), load_s=round(load_s, 1))
    res["slip"]["latency"].pop("latencies_frames", None)
    figures["slip_f1"] = ev["metrics"]["slip_f1"]
    figures["slip_median_latency_frames"] = ev["metrics"]["latency"]["median_frames"]

    # -- pressure --------------------------------------------------------------
    tr, te, sim_s = data("pressure", ["press-hard", "press-soft"])
    t0 = time.perf_counter()
    ws_tr, ws_te = load(tr, "pressure"), load(te, "pressure")
    load_s = time.perf_counter() - t0
    r, mdir = train("pressure", ws_tr, ws_te, "pressure")
    ev = evaluate_model(mdir, ws_te)
    evf = float_eval(mdir, ws_te)
    res["pressure"] = dict(summary(r, ev), int8=ev["metrics"], float=evf["metrics"],
                           windows={"train": len(ws_tr), "test": len(ws_te)},
                           sim_s=round(sim_s, 1), load_s=round(load_s, 1))
    figures["pressure_mae_of_range"] = ev["metrics"]["mae_of_range"]
    figures["pressure_mae_n"] = ev["metrics"]["mae"]

    def ok(key, value):
        if value is None:
            return False
        want = BENCH_TARGETS[key]
        return value <= want if key in ("slip_median_latency_frames",
                                        "pressure_mae_of_range") else value >= want

    res["figures"] = figures
    res["met"] = {k: ok(k, figures.get(k)) for k in BENCH_TARGETS}
    res["total_s"] = round(time.perf_counter() - t_all, 1)
    atomic_write_text(out / "benchmarks.json", json.dumps(res, indent=1, default=_plain))
    return res
