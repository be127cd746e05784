"""``host eval``: a model folder against windows, through the Pi's own loaders.

:func:`evaluate_model` loads the model the way the Pi does
(:class:`device.pi.models.classifier.Classifier`, :class:`device.pi.models.rules.RuleClassifier`
or :class:`device.pi.models.regressor.Regressor`, all through
:func:`device.pi.models.artefact.load_model` with ONNX Runtime on one thread), builds each
window's input with :mod:`device.pi.models.window` and runs one decision per window. It
reports accuracy, per-class F1 and the confusion matrix (slip: also the slip F1 and
the detection latency in frames), or MAE for regression; the latency per decision
(p50 / p99, single thread, one window per call, as on the Pi); the model size in
bytes; and the fraction of windows kept when the data were cut. Accuracy (or MAE)
carries its 95 % block-bootstrap interval, the window count and the same per
recording (``metrics.by_recording``, :func:`host.learn.metrics.add_intervals`).
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from device.errors import InputError
from device.pi.models.artefact import ModelError, model_file
from device.pi.models.manifest import VARIANTS, manifest_for, manifest_path, read_spec
from device.pi.models.classifier import Classifier
from device.pi.models.regressor import Regressor
from device.pi.models.window import encode
from host.data.windows import NO_TOUCH
from host.learn.inputs import model_inputs
from host.learn.metrics import (add_intervals, classification_metrics, regression_metrics,
                                slip_latency)
from host.learn.tasks import label_ids

__all__ = ["evaluate_model", "eval_summary", "load_variant", "percentiles", "variant_manifest", "VARIANTS"]


def variant_manifest(model_dir, variant: str | None) -> Path:
    """The manifest file that loads ``variant`` (None: the default), picked by the
    Pi's :func:`device.pi.models.manifest.manifest_for`. Unlike the Pi, which runs
    the model it has, an evaluation refuses a folder without the variant asked for."""
    spec, mpath = read_spec(model_dir)
    folder = mpath.parent
    if variant is None or spec.model == "rule":
        if variant == "int8" and spec.model == "rule":
            raise ModelError(f"{mpath}: a rule model has no int8 variant")
        return mpath
    picked = manifest_for(folder, variant)          # ValueError for an unknown variant
    if read_spec(picked)[0].variant != variant:
        raise ModelError(f"{mpath}: the model folder has no {variant} model"
                         + (" (train with --quantise)" if variant == "int8" else ""))
    return picked


def load_variant(model_dir, variant: str | None = None):
    """(predictor, spec, kind) for a model folder: a Classifier, RuleClassifier
    or Regressor, loaded with the Pi's code."""
    mpath = variant_manifest(model_dir, variant)
    spec, _ = read_spec(mpath)
    if spec.model == "rule":
        return Classifier.load(mpath), spec, "rule"
    if spec.kind == "pressure":
        return Regressor.load(mpath, kind="pressure"), spec, "regressor"
    return Classifier.load(mpath), spec, "classifier"


def percentiles(ms, mean: bool = True, digits: int | None = 5) -> dict:
    """Median ("p50"), p99, (with ``mean``) the mean, and the count of times in ms,
    rounded to ``digits`` (None: not rounded); None for each when there are none."""
    a = np.asarray(list(ms), np.float64)

    def r(x):
        return None if x is None else (float(x) if digits is None else round(float(x), digits))
    out = {"p50": None, "p99": None}
    if len(a):
        out = {"p50": r(np.percentile(a, 50)), "p99": r(np.percentile(a, 99))}
    if mean:
        out["mean"] = r(a.mean()) if len(a) else None
    out["n"] = int(len(a))
    return out


def evaluate_model(model_dir, ws, variant: str | None = None, warmup: int = 20,
                   encode_samples: int = 200) -> dict:
    """Metrics, latency, size and kept fraction of the model in ``model_dir`` on
    the windows ``ws`` (a :class:`host.data.windows.WindowSet` for the model's task and T).

    ``variant``: None (the manifest's default: int8 when the model was quantised),
    ``"float"`` or ``"int8"``. Raises :class:`device.pi.models.artefact.ModelError` for a
    bad model folder and ValueError for windows that do not fit the model, or whose
    labels are not all classes of the model.
    """
    pred_obj, spec, kind = load_variant(model_dir, variant)
    task, T, layout, uses_imu = spec.kind, spec.T, spec.input_layout, spec.uses_imu
    X = _fitting_inputs(pred_obj, spec, kind, ws)
    lat, outs = _decide(pred_obj, kind, X, warmup)
    enc = _encode_times(ws, layout, uses_imu, encode_samples)
    res = {"model_dir": str(model_dir), "task": task, "model": spec.model,
           "variant": spec.variant if kind != "rule" else "rule", "T": T,
           "input_layout": layout, "uses_imu": uses_imu, "n_windows": int(len(ws))}
    if kind == "regressor":
        pred = np.array(outs, np.float64)
        res["metrics"] = regression_metrics(ws.targets, pred)
        add_intervals(res["metrics"], ws, np.abs(pred - np.asarray(ws.targets, np.float64)),
                      key="mae")
        res["faults"] = 0
    else:
        classes = list(pred_obj.classes)
        probs = np.stack([o[1] for o in outs])
        pred = np.array([o[0] for o in outs], np.int64)
        if not np.isfinite(probs).all():
            raise ModelError(f"{model_dir}: non-finite probabilities")  # never expected
        true = label_ids(ws.labels, classes)
        res["classes"] = classes
        res["metrics"] = classification_metrics(true, pred, classes, ws.labels)
        add_intervals(res["metrics"], ws, true == pred)
        if task == "slip" and "slip" in classes:
            res["metrics"]["slip_f1"] = res["metrics"]["per_class"]["slip"]["f1"]
            res["metrics"]["latency"] = slip_latency(ws, pred == classes.index("slip"))
    folder = Path(model_dir) if Path(model_dir).is_dir() else Path(model_dir).parent
    onnx_name = spec.onnx
    res["model_bytes"] = int(model_file(folder, onnx_name).stat().st_size) if onnx_name else 0
    res["manifest_bytes"] = int(manifest_path(folder).stat().st_size)
    res["latency_ms"] = percentiles(lat)
    res["encode_ms"] = percentiles(enc)
    res["threads"] = 1
    res["kept_fraction"] = round(float(ws.kept_fraction), 6)
    res["decision_delay_ms"] = {f"{fps}fps": round(1000.0 * ws.window / fps, 3)
                                for fps in (30, 120)}
    return res


def _fitting_inputs(pred_obj, spec, kind: str, ws) -> np.ndarray:
    """The model inputs of ``ws``, after checking that the windows fit the model
    (task, T, IMU, labels among its classes, input size); ValueError otherwise."""
    task, T, layout, uses_imu = spec.kind, spec.T, spec.input_layout, spec.uses_imu
    if len(ws) == 0:
        raise InputError("ws holds no windows")
    if ws.task != task:
        raise InputError(f"the windows were loaded for task {ws.task!r}, the model is for "
                         f"task {task!r}")
    if T is not None and ws.window != T:
        raise InputError(f"the windows have T={ws.window} frames, the model sees T={T}")
    layout = spec.input_layout
    uses_imu = spec.uses_imu
    if uses_imu and ws.imu is None:
        raise InputError("the model uses the IMU but the windows carry none")
    if kind != "regressor" and ws.labels is not None:
        unknown = sorted({str(x) for x in ws.labels} - {str(c) for c in pred_obj.classes})
        if NO_TOUCH in unknown:
            # not a wrong label: the windows without contact, which the loader labels
            # no-touch, and a model trained on contact windows only (--contact-only)
            raise InputError(
                f"the model has no {NO_TOUCH} class (its classes: {list(pred_obj.classes)}; "
                f"it was trained on contact windows only, e.g. with --contact-only), and "
                f"{int((ws.labels == NO_TOUCH).sum())} of the {len(ws)} windows have no "
                f"contact: evaluate with --contact-only to drop them"
                + (f"; the data also hold label(s) {[u for u in unknown if u != NO_TOUCH]} "
                   f"that the model does not know" if len(unknown) > 1 else ""))
        if unknown:
            raise InputError(f"the data hold label(s) {unknown} that the model does not know "
                             f"(its classes: {list(pred_obj.classes)}); a score over them would "
                             f"mean nothing: fix the labels or evaluate a model trained on them")
    X = model_inputs(ws, layout, uses_imu)
    shape = list(spec.input_dims or [spec.n_inputs])
    if isinstance(spec.features, dict):   # the graph reads features of the window
        shape = [int(getattr(pred_obj, "n_features", spec.features.get("n_inputs")))]
    if int(np.prod(X.shape[1:])) != int(np.prod(shape)):
        prof = spec.profile
        pins = (f"; the windows have {ws.n_pins} pins, the model's sensor profile "
                f"{prof.get('name')!r} has {prof.get('n_pins')}: load the data with the "
                f"model's profile (host eval does, unless --profile says otherwise)"
                if prof and ws.n_pins != prof.get("n_pins") else "")
        raise InputError(f"the windows encode to {tuple(X.shape[1:])} inputs, the model "
                         f"expects {tuple(shape)} (pin count, grid or frame size differs)"
                         + pins)
    return X


def _decide(pred_obj, kind: str, X: np.ndarray, warmup: int) -> tuple[list, list]:
    """(latency ms, output) of one decision per window, timed as on the Pi after
    ``warmup`` untimed ones."""
    if kind == "regressor":
        def call(x):
            return pred_obj.predict_one(x)
    else:
        def call(x):
            return pred_obj.predict(x)
    for i in range(min(warmup, len(X))):
        call(X[i])
    lat, outs = [], []
    clock = time.perf_counter
    for i in range(len(X)):
        t0 = clock()
        o = call(X[i])
        lat.append((clock() - t0) * 1e3)
        outs.append(o)
    return lat, outs


def _encode_times(ws, layout: str, uses_imu: bool, samples: int) -> list:
    """The time (ms) the Pi's encoder takes on ``samples`` windows spread over ``ws``."""
    clock = time.perf_counter
    enc = []
    idx = np.linspace(0, len(ws) - 1, min(samples, len(ws))).astype(int)
    for i in idx:
        parts = {"vectors": ws.vectors[i], "grids": None if ws.grids is None else ws.grids[i],
                 "frames": None if ws.frames is None else ws.frames[i],
                 "imu": ws.imu[i] if uses_imu else None}
        t0 = clock()
        encode(layout, **parts)
        enc.append((clock() - t0) * 1e3)
    return enc


def eval_summary(res: dict) -> str:
    """A short text summary of an :func:`evaluate_model` result (``host eval`` prints it
    without ``--json``): the model, the headline figure with its interval and number of
    windows, per-class recall, the latency, and the recording-identity check's verdict
    lines when the result carries one."""
    m = res.get("metrics") or {}
    head = f"{res.get('model_dir')} ({res.get('task')} {res.get('model')}, " \
           f"{res.get('variant')}, T={res.get('T')}) on {res.get('n_windows')} windows:"
    figs = []
    for k in ("accuracy", "macro_f1", "mae"):
        if isinstance(m.get(k), (int, float)):
            ci = m.get(f"{k}_ci95")
            figs.append(f"{k} {m[k]:.4g}" + (f" [{ci[0]:.4g}, {ci[1]:.4g}] (95 %)"
                                             if isinstance(ci, list) and len(ci) == 2 else ""))
    lines = [f"{head} " + ", ".join(figs or ["no metrics"])]
    per = m.get("per_class")
    if isinstance(per, dict) and per:
        lines.append("  recall: " + ", ".join(
            f"{c} {v['recall']:.3g}" for c, v in per.items()
            if isinstance(v, dict) and isinstance(v.get("recall"), (int, float))))
    lat = res.get("latency_ms") or {}
    if lat.get("p50") is not None:
        lines.append(f"  latency: median {lat['p50']:.3g} ms, p99 {lat['p99']:.3g} ms "
                     f"(one thread); --json prints every figure")
    check = res.get("identity_check")
    if isinstance(check, dict):
        from host.learn.identity import verdict_lines
        lines += [f"  identity check: {line}" for line in verdict_lines(check)]
    return "\n".join(lines)
