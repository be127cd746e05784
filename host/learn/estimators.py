"""The trainable models: the MLP pipelines of ``fnn`` and ``grid-fnn`` ([temporal
layer ->] clipped scaling -> MLP), Ridge and gradient-boosted trees
(:mod:`host.learn.pressure`) for pressure, their ONNX export, and the
rule model's thresholds fitted to training windows.
"""
from __future__ import annotations

import math
import sys
import time
import warnings

import numpy as np

from device.checks import finite_number
from device.pi.models.rules import RuleClassifier, window_measures
from host.learn.layers import scaler_class, temporal_class
from host.learn.regression import ridge_pipeline
from host.learn.tasks import DEFAULT_ALPHA, DEFAULT_EPOCHS, DEFAULT_HIDDEN, TrainError, check_int
from host.extras import need

__all__ = ["default_uses_imu", "hyperparameters", "fit_mlp", "fit_estimator",
           "pipeline_to_onnx", "best_threshold", "fit_rule", "rule_probs"]


def default_uses_imu(model: str, ws) -> bool:
    return model == "fnn" and ws.imu is not None


def hyperparameters(model: str, hidden=None, alpha=None, epochs=None, temporal=None,
                    window=None, n_pins=None) -> dict:
    """The settings :func:`fit_estimator` reads. ``gbt`` (scikit-learn's
    GradientBoostingRegressor with its default settings) takes no hidden, alpha or
    epochs; it needs the windows' ``window`` (T) and ``n_pins`` (M) for its
    :class:`host.learn.pressure.TrackedPins` layer."""
    if model == "gbt":
        given = {k: v for k, v in (("hidden", hidden), ("alpha", alpha), ("epochs", epochs))
                 if v is not None}
        if given:
            raise TrainError(f"model gbt uses GradientBoostingRegressor's default settings; "
                             f"it takes no {sorted(given)}, got {given}")
        return {"temporal": None, "window": check_int("window", window, 1),
                "n_pins": check_int("n_pins", n_pins, 1)}
    hidden = tuple(DEFAULT_HIDDEN if hidden is None else hidden)
    if len(hidden) != 2 or not all(isinstance(h, (int, np.integer)) and h >= 1 for h in hidden):
        raise TrainError(f"hidden must be two layer sizes >= 1, got hidden={hidden!r}")
    alpha = DEFAULT_ALPHA.get(model, 0.0) if alpha is None else alpha
    alpha = finite_number("alpha", alpha, 0, error=TrainError)
    epochs = check_int("epochs", DEFAULT_EPOCHS if epochs is None else epochs, 1)
    return {"hidden": [int(h) for h in hidden], "alpha": float(alpha), "epochs": epochs,
            "temporal": temporal}


def _mlp(task: str, hidden, alpha: float, seed: int, n: int):
    from sklearn.neural_network import MLPClassifier, MLPRegressor

    # mini-batches of 128, smaller for small sets so an epoch takes >= 8 steps
    kw = dict(hidden_layer_sizes=tuple(hidden), activation="logistic", solver="adam",
              alpha=alpha, batch_size=int(min(128, max(4, n // 8))), learning_rate_init=1e-3,
              random_state=seed, shuffle=True)
    return MLPRegressor(**kw) if task == "pressure" else MLPClassifier(**kw)


class Plateau:
    """Early stopping on a training loss: :meth:`reached` is True once the loss has
    not improved on its best by ``tol`` for ``patience`` epochs in a row."""

    def __init__(self, tol: float, patience: int):
        self.tol, self.patience = float(tol), int(patience)
        self.best, self.stale = math.inf, 0

    def reached(self, loss: float) -> bool:
        if loss < self.best - self.tol:
            self.best, self.stale = loss, 0
            return False
        self.stale += 1
        return self.stale >= self.patience


#: the MLP stops when its training loss has not improved by PLATEAU_TOL for
#: PLATEAU_PATIENCE epochs in a row
PLATEAU_TOL, PLATEAU_PATIENCE = 1e-4, 15


def fit_mlp(task: str, X: np.ndarray, y: np.ndarray, n_classes: int, hp: dict, seed: int,
            desc: str | None = None):
    """[TemporalFeatures +] scaler + MLP (``hp``: ``hidden``, ``alpha``, ``epochs``,
    ``temporal``, :func:`hyperparameters`), the MLP fitted epoch by epoch
    (``partial_fit``) with a tqdm bar named ``desc`` (None: no bar); stops when the
    training loss has not improved by :data:`PLATEAU_TOL` for
    :data:`PLATEAU_PATIENCE` epochs. Returns (pipeline, epochs run, final loss)."""
    from sklearn.pipeline import Pipeline
    tqdm = need("tqdm").tqdm

    hidden, alpha, epochs, temporal = hp["hidden"], hp["alpha"], hp["epochs"], hp.get("temporal")
    steps = []
    if temporal:
        tf = temporal_class()(**temporal).fit(X)
        X = tf.transform(X)
        steps.append(("temporal", tf))
    scaler = scaler_class()().fit(X)
    Xs = scaler.transform(X)
    mlp = _mlp(task, hidden, alpha, seed, len(X))
    plateau, n = Plateau(PLATEAU_TOL, PLATEAU_PATIENCE), 0
    classes = np.arange(n_classes)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with tqdm(total=epochs, desc=desc, unit="epoch", disable=desc is None or None,
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
                if plateau.reached(loss):
                    break
    return Pipeline(steps + [("scaler", scaler), ("mlp", mlp)]), n, float(mlp.loss_)


def fit_estimator(task: str, model: str, X: np.ndarray, y: np.ndarray, n_classes: int, hp: dict,
                  seed: int, desc: str | None = None):
    """A fitted sklearn Pipeline (scaler + estimator) and fit info; an MLP shows a
    progress bar named ``desc`` (None: none)."""
    t0 = time.perf_counter()
    if model == "ridge":
        pipe = ridge_pipeline(hp["alpha"]).fit(X, y)
        info = {}
    elif model == "gbt":
        from host.learn.pressure import fit_pressure
        if task != "pressure":
            raise TrainError(f"model gbt regresses pressure, got task={task!r}")
        pipe, _ = fit_pressure("gbt", X, y, None, hp["window"], hp["n_pins"], seed)
        info = {}
    else:
        pipe, epochs, loss = fit_mlp(task, X, y, n_classes, hp, seed, desc)
        info = {"epochs": epochs, "loss": round(loss, 6)}
    info["fit_s"] = round(time.perf_counter() - t0, 3)
    return pipe, info


def pipeline_to_onnx(pipe, n_features: int, task: str):
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


def best_threshold(values: np.ndarray, positive: np.ndarray) -> float:
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


def fit_rule(task: str, ws, classes: list[str]):
    """A RuleClassifier with thresholds set from the training windows (a 1-D
    search per threshold; the rule has no weights)."""
    ms = [window_measures(v) for v in ws.vectors]
    mag = np.array([m["magnitude_px"] for m in ms])
    motion = np.array([np.nan if m["motion_px"] is None else m["motion_px"] for m in ms])
    lab = ws.labels.astype(str)
    if task == "surface":
        contact = lab != "no-touch"
    else:
        contact = np.asarray(ws.contact, bool)
    contact_px = best_threshold(mag, ~contact) if (~contact).any() and contact.any() else 1.0
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
        soft_ratio = best_threshold(mag[sel], lab[sel] == "soft") / expected_mag
    expected_motion = wet_ratio = 0.0
    if ws.window >= 2 and still_neg.any():
        expected_motion = float(np.nanmedian(motion[still_neg]))
        if still_pos.any() and expected_motion > 0:
            sel = still_pos | still_neg
            wet_ratio = best_threshold(motion[sel], still_pos[sel]) / expected_motion
    rule = {"contact_px": contact_px, "expected_mag_px": expected_mag,
            "soft_ratio": soft_ratio, "expected_motion_px": expected_motion,
            "wet_ratio": wet_ratio}
    rule = {k: round(float(max(v, 0.0)), 6) for k, v in rule.items()}
    return RuleClassifier(rule, classes, ws.window, ws.n_pins, task=task)


def rule_probs(rc, X: np.ndarray) -> np.ndarray:
    return np.stack([rc.predict(x)[1] for x in X]) if len(X) else np.zeros((0, rc.n_classes))

