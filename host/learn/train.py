"""``host train``: windows in, a deployable model folder out.

:func:`train_model` turns windows (:class:`host.data.windows.WindowSet`) into a deployable
model folder: ONNX (the scaler folded into the graph) + its manifest, and with
``quantise=True`` an int8 ONNX file beside the float one, checked against it.

The tasks and models are listed in :mod:`host.learn.tasks`; the fnn's graph is
[frame-to-frame changes (:mod:`host.learn.layers`, T >= 2)] -> standard scaling
clipped to +-8 sd -> MLP (:mod:`host.learn.estimators`). Every model's input is
built by :mod:`device.pi.models.window`, the encoders the Pi runs
(:func:`host.learn.inputs.model_inputs`). The slip detector is the ``fnn`` (or
``rule``) of task ``slip``: it emits a slip event (argmax) and a confidence (the slip
probability); its detection latency in frames from the true onset is measured on
the held-out trials (:func:`host.learn.metrics.slip_latency`).

Held-out data: ``ws_test`` when given; otherwise :func:`host.data.splits.split_holdout`:
about 30 % of the trials, whole trials only, when that keeps every class on both
sides, else the last 30 % of each trial after a gap of T frames. A class that the
data or the test windows carry but the training windows do not is a TrainError
that names it. ``cv=K`` adds grouped K-fold cross-validation
on the training windows (:func:`host.learn.cv.cross_validate_model`).

Model folder::

    (the manifest)         task, classes, T, feature spec, input layout, IMU use,
                           metrics, int8 check, sha256 + size of each file, data summary
    manifest.float.json    (quantised models only) the same, loading the float file
    model.onnx             float32
    model.int8.onnx        (``quantise=True``) static QDQ int8, the default to load
"""
from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from device.pi.models.manifest import write_spec, write_variant_specs
from host.data.dataset import atomic_write
from device.pi.vision.neighbours import layout_neighbours
from host.data.extract import layout_for_profile
from host.data.splits import LATER_FRAMES, holdout_protocol, split_holdout
from host.data.windows import DataError, WindowSet
from host.learn.cv import cross_validate_model
from host.learn.estimators import (default_uses_imu, fit_estimator, fit_rule, hyperparameters,
                                   pipeline_to_onnx, rule_probs)
from host.learn.inputs import augment_rotations, model_inputs
from host.learn.identity import identity_check
from host.learn.metrics import add_intervals, class_report, regression_metrics
from host.learn.card import measure_cost
from host.learn.onnx_io import (FLOAT_NAME, INT8_NAME, fill_variants, new_spec, run_onnx, session,
                                spec_profile)
from host.learn.pressure import checked_onnx
from host.learn.quantise import quantise_model
from host.learn.rates import augment_rates
from host.learn.tasks import (LAYOUT, MIN_AGREEMENT, MODELS, TASK_HIDDEN, TASK_MODELS,
                              TASK_RATES, TASKS,
                              QuantisationError, TrainError, check_choice, check_int,
                              label_ids)

__all__ = ["train_model", "check_classes"]


def _check_windows(ws, task: str, what: str) -> None:
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
    try:
        tr, te, how = split_holdout(ws, 0.3, seed)
    except DataError as exc:
        if len(np.unique(ws.groups)) >= 2 or (ws.t_index >= 0).all():
            raise TrainError(str(exc)) from None
        return ws, None, "none: one trial without time order; metrics on the training windows"
    return ws.subset(tr), ws.subset(te), how


#: a pin lost in more than this share of one training recording's windows is ignored
MAX_LOST_SHARE = 0.2


def texture_neighbours(profile: str, n_pins: int, k: int = 6) -> list[list[int]] | None:
    """The ``k`` layout neighbours (:func:`device.pi.vision.neighbours.layout_neighbours`)
    of the ``profile``'s pins, from which the texture fnn reads the roughness of the
    displacement field; None when the profile's layout is not the windows' M pins."""
    try:
        lay = layout_for_profile(profile)
    except DataError:
        return None
    if len(lay) != n_pins or len(lay) <= k:
        return None
    return layout_neighbours(lay, k)[0].tolist()


def fnn_temporal_spec(task: str, ws, T: int, uses_imu: bool, profile: str) -> dict:
    """The settings of the fnn's temporal layer (:class:`TemporalFeatures`) for
    training windows ``ws``: pins a training recording keeps losing masked (not for
    the pressure regression), and for texture the layout neighbours of the
    roughness features. One place, for :func:`train_model` and the regulariser
    comparison (:mod:`host.bench.regularise`)."""
    ignored = set(recording_lost_pins(ws)) if task != "pressure" else set()
    return {"T": T, "n_pins": ws.n_pins, "uses_imu": bool(uses_imu),
            "pin_mask": (None if not ignored else
                         [0 if m in ignored else 1 for m in range(ws.n_pins)]),
            "neighbours": (texture_neighbours(profile, ws.n_pins)
                           if task == "texture" else None)}


def recording_lost_pins(ws) -> list[int]:
    """The layout pins that some training recording (trial) loses in more than
    ``MAX_LOST_SHARE`` of its windows' frames. A pin that glare hides in one
    recording and not in another is a fingerprint of the recording, not of the
    surface; the fnn ignores these pins (``TemporalFeatures.pin_mask``)."""
    if len(ws) == 0:
        return []
    lost = ws.lost.mean(axis=1)                        # (N, M): share of frames lost
    out = np.zeros(ws.n_pins, bool)
    for g in np.unique(ws.groups):
        out |= lost[ws.groups == g].mean(axis=0) > MAX_LOST_SHARE
    return [int(i) for i in np.flatnonzero(out)]


def check_classes(ws_train, ws_test, classes_wanted) -> None:
    """A TrainError naming every class that the test windows or the data carry but
    the training windows do not."""
    have = {str(x) for x in ws_train.labels}
    wanted = {str(x) for x in classes_wanted}
    if ws_test is not None and ws_test.labels is not None:
        wanted |= {str(x) for x in ws_test.labels}
    missing = sorted(wanted - have)
    if missing:
        raise TrainError(f"class(es) {missing} have no training windows (training classes: "
                         f"{sorted(have)}); add training data for them or drop them")


def train_model(task: str, model: str, ws_train, ws_test=None, cv: int | None = None,
                quantise: bool | str = False, seed: int = 0, out_dir=None,
                progress: bool = True,
                *, uses_imu: bool | None = None, hidden=None, alpha: float | None = None,
                epochs: int | None = None, temporal: bool | None = None, augment: int = 0,
                rates=None, profile: str = "roboskin", trained_on: dict | None = None,
                config: dict | None = None,
                calibration_windows: int = 2000, calibrate_method: str = "minmax",
                min_agreement: float = MIN_AGREEMENT, identity: bool = False,
                measure: bool = False) -> dict:
    """Train ``model`` for ``task`` on ``ws_train``; evaluate on ``ws_test`` (or a
    held-out part of ``ws_train``, see the module doc); write the model folder
    ``out_dir`` (ONNX + its manifest, + int8 when ``quantise``). Returns the
    result (metrics, int8 check, files, timings) as a JSON-able dict; it is also
    the manifest's core.

    ``uses_imu``: None = the fnn uses the IMU when the windows carry it.
    ``hidden``, ``alpha``, ``epochs``: MLP layer sizes (default (64, 32); texture
    (16, 16), :data:`host.learn.tasks.TASK_HIDDEN`), L2
    penalty (MLP 1e-3, ridge 150) and most epochs (300, with early stopping on the
    training loss). ``temporal``: the fnn's fixed first layer of frame-to-frame
    changes (:class:`TemporalFeatures`); None = on for the fnn when T >= 2.
    ``augment``: add this many rotated copies of the training
    windows (:func:`augment_rotations`, rotations that map the ``profile``'s pin
    layout onto itself), so a model need not see every drag direction; ``vectors``
    layout only. ``rates``: frame-keeping rules (:mod:`host.learn.rates`) whose
    re-cut copies of the training windows are added, so the model sees several
    frame intervals (e.g. ``("3of5", "3of5+drop10")``); None =
    :data:`host.learn.tasks.TASK_RATES` for the fnn (none). ``calibration_windows``
    training windows (a seeded random choice) calibrate the int8 model with
    ``calibrate_method`` (minmax, percentile or entropy); ``min_agreement`` is the
    argmax agreement it must reach on the
    held-out windows. Nothing is written when a check fails (:class:`TrainError`,
    :class:`QuantisationError`), except with ``quantise="if-passes"``: then a failed
    int8 check keeps the float model as the default and records why in
    ``result["int8"]["failed"]`` (the manifest's ``int8``).

    The manifest is a model spec (:mod:`device.pi.models.spec`): it carries the
    sensor ``profile`` (every feature, the texture roughness neighbours included,
    is computed with it), ``trained_on`` (data real/simulated, recordings with
    checksums; ``split`` is filled with the held-out protocol) and ``config`` (the
    training config that made it, see ``host train --config``). Its ``measured``
    record holds the int8 and identity verdicts, the training data and, with
    ``measure``, the cost per decision (:func:`host.learn.card.measure_cost`): the
    manifest is written once, with all of them.
    """
    if quantise not in (True, False, "if-passes"):
        raise TrainError(f"quantise must be True, False or 'if-passes', got {quantise!r}")

    t_start = time.perf_counter()
    check_choice("task", task, TASKS)
    check_choice("model", model, MODELS + ("cnn",))
    if model == "cnn":
        raise TrainError("model=cnn is trained by host.learn.cnn (PyTorch), not host.learn.train")
    if model not in TASK_MODELS[task]:
        raise TrainError(f"model={model!r} does not serve task={task!r}; task {task} takes "
                         f"{list(TASK_MODELS[task])}")
    seed = check_int("seed", seed, 0)
    if out_dir is None:
        raise TrainError("out_dir is required: the folder to write the model to")
    _check_windows(ws_train, task, "ws_train")
    holdout = "given"
    all_classes = [] if task == "pressure" else sorted({str(x) for x in ws_train.labels})
    if ws_test is None:
        ws_train, ws_test, holdout = _holdout(ws_train, seed)
    else:
        _check_windows(ws_test, task, "ws_test")
        if ws_test.window != ws_train.window:
            raise TrainError(f"ws_test has windows of T={ws_test.window}, ws_train T="
                             f"{ws_train.window}")
    if cv is not None:
        cv = check_int("cv", cv, 2)
    if not (0.0 < min_agreement <= 1.0):
        raise TrainError(f"min_agreement must be in (0, 1], got min_agreement={min_agreement!r}")
    T = ws_train.window
    layout = LAYOUT[model]
    if model == "rule":
        uses_imu = False
    elif uses_imu is None:
        uses_imu = default_uses_imu(model, ws_train)
    elif uses_imu and layout != "vectors":
        raise TrainError(f"uses_imu=True needs input_layout vectors; {model} reads {layout}")
    if uses_imu and ws_test is not None and ws_test.imu is None:
        raise TrainError("the model uses the IMU but the test windows carry none")
    if temporal is None:
        temporal = model == "fnn" and T >= 2
    if temporal and (model != "fnn" or T < 2):
        raise TrainError(f"temporal=True needs the fnn and T >= 2 frames, got model={model!r} "
                         f"T={T}")
    tspec = fnn_temporal_spec(task, ws_train, T, uses_imu, profile) if temporal else None
    ignored = ([m for m, keep in enumerate(tspec["pin_mask"]) if not keep]
               if tspec and tspec["pin_mask"] else [])
    if hidden is None:
        hidden = TASK_HIDDEN.get(task)
    hp = (hyperparameters(model, hidden, alpha, epochs, tspec, window=T,
                          n_pins=ws_train.n_pins) if model != "rule" else {})
    regression = task == "pressure"

    augment = check_int("augment", augment, 0)
    if augment and layout != "vectors":
        raise TrainError(f"augment={augment} rotates pin vectors; {model} reads {layout}")
    if augment and model == "rule":
        raise TrainError("augment: the rule has nothing to learn from rotated copies")
    if rates is None:
        rates = TASK_RATES.get(task, ()) if model == "fnn" else ()
    rates = tuple(rates)
    ws_fit = augment_rates(ws_train, rates, seed) if rates else ws_train
    ws_fit = augment_rotations(ws_fit, augment, profile) if augment else ws_fit
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
        check_classes(ws_train, ws_test, all_classes)
        classes = sorted({str(x) for x in ws_train.labels})
        if len(classes) < 2:
            raise TrainError(f"labels: task {task} needs training windows of at least 2 "
                             f"classes, the data hold {len(classes)}: {classes}")
        y = label_ids(ws_fit.labels, classes)
        yt = None if ws_test is None else label_ids(ws_test.labels, classes)
    spec_keys = {"profile": spec_profile(profile), "config": dict(config or {}),
                 "trained_on": dict({"data": "unknown", "recordings": []}, **(trained_on or {}),
                                    split=(trained_on or {}).get("split") or holdout)}
    result = {"task": task, "model": model, "T": T, "input_layout": layout,
              "ignored_pins": ignored,
              "uses_imu": bool(uses_imu), "temporal_features": bool(temporal),
              "roughness": bool(tspec and tspec["neighbours"]),
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
        rc = fit_rule(task, ws_train, classes)
        metrics["train"] = class_report(task, ws_train, y, rule_probs(rc, X), classes)
        if ws_test is not None:
            metrics["test"] = class_report(task, ws_test, yt, rule_probs(rc, Xt), classes)
        result["rule"] = rc.rule
        result["metrics"] = metrics
        result["int8"] = ({"skipped": "a rule has no weights to quantise"} if quantise
                          else None)
        mpath = write_spec(out, new_spec(X.shape[1], {
            **rc.spec_fields(), "metrics": metrics, **spec_keys,
            "training": _training_info(ws_train, ws_test, holdout, seed, {})}))
        result["files"] = {mpath.name: {"size_bytes": mpath.stat().st_size}}
        result["train_s"] = round(time.perf_counter() - t_start, 3)
        return result

    pipe, fit_info = fit_estimator(task, model, X, y, len(classes), hp, seed, progress,
                                   f"{task} {model} T={T}")
    if model == "gbt":      # trees: ONNX of the pipeline, checked against sklearn
        onnx_model, fit_info["onnx_parity"] = checked_onnx(pipe, X, y)
    else:
        onnx_model = pipeline_to_onnx(pipe, X.shape[1], task)
    fbytes = onnx_model.SerializeToString()
    sess = session(fbytes)
    n0 = len(ws_train)                     # the original windows come first in X
    out_train = run_onnx(sess, X[:n0])
    out_test = run_onnx(sess, Xt) if Xt is not None else None
    if regression:
        metrics["train"] = regression_metrics(y[:n0], out_train)
        if out_test is not None:
            metrics["test"] = regression_metrics(yt, out_test)
    else:
        metrics["train"] = class_report(task, ws_train, y[:n0], out_train, classes)
        if out_test is not None:
            metrics["test"] = class_report(task, ws_test, yt, out_test, classes)

    # -- int8 ------------------------------------------------------------------
    int8 = None
    qbytes = None
    if quantise and model == "gbt":
        int8 = {"skipped": "a tree ensemble has no weights to quantise; the float model "
                           "is the default"}
    elif quantise:
        rng = np.random.default_rng(seed)
        n_cal = min(len(X), check_int("calibration_windows", calibration_windows, 1))
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
                    raise exc.with_message(msg) from None
                # keep the float model, say why
                int8 = {"failed": msg, **exc.fields()}
        if qbytes is not None:
            int8.pop("path", None)
            q_out = run_onnx(session(qbytes), check_X)
            if regression:
                int8["metrics"] = regression_metrics(check_y, q_out)
            else:
                int8["metrics"] = class_report(task, ws_test if Xt is not None else ws_train,
                                               check_y, q_out, classes)
    _finish_metrics(metrics, result, holdout, ws_train, ws_test, regression, y[:n0], out_train,
                    yt, out_test)
    if identity:        # host train --no-identity-check skips it (host.learn.identity)
        result["identity_check"] = identity_check(ws_train, task, model, hp, uses_imu, seed)
        if result["identity_check"]["warning"]:
            metrics.setdefault("test", {})["identity_warning"] = \
                result["identity_check"]["warning"]
    result["metrics"] = metrics
    result["int8"] = int8
    result["fit"] = fit_info

    # -- write -----------------------------------------------------------------
    out.mkdir(parents=True, exist_ok=True)
    default = INT8_NAME if qbytes is not None else FLOAT_NAME
    extra = {"model": model, "task": task, "classes": classes, "T": T, "ignored_pins": ignored,
             "roughness": result["roughness"],
             "input_layout": layout, "uses_imu": bool(uses_imu),
             "output": "variable" if regression else "probabilities",
             "output_kind": "value" if regression else "probabilities",
             "variant": "int8" if qbytes is not None else "float",
             "metrics": metrics, "int8": int8, "identity": result.get("identity_check"),
             **spec_keys,
             "training": _training_info(ws_train, ws_test, holdout, seed,
                                        dict(hp, **fit_info, augment=augment,
                                             rates=list(rates),
                                             augmented_deg=ws_fit.source.get("augmented_deg"),
                                             fit_windows=int(len(X))))}
    if regression:
        extra.update({"target_mean": float(y.mean()),
                      "target_range": [float(y.min()), float(y.max())],
                      "input_clip": [X.min(axis=0).tolist(), X.max(axis=0).tolist()]})
    # the float file, the int8 file beside it, then the spec with the checksum and size
    # of every file and what was measured, written once
    atomic_write(out / FLOAT_NAME, lambda fh: fh.write(fbytes))
    if qbytes is not None:
        atomic_write(out / INT8_NAME, lambda fh: fh.write(qbytes))
    else:
        (out / INT8_NAME).unlink(missing_ok=True)     # a stale int8 file from an earlier run
    spec = new_spec(X.shape[1], dict(extra, kind=task), FLOAT_NAME)
    files = fill_variants(out, spec, int8=qbytes is not None)
    if measure:
        spec.measured.cost_per_decision = measure_cost(out, spec)
    write_variant_specs(out, spec)
    result["files"] = files
    result["default"] = default
    result["train_s"] = round(time.perf_counter() - t_start, 3)
    return result


def _finish_metrics(metrics, result, holdout, ws_train, ws_test, regression, y, out_train,
                    yt, out_test) -> None:
    """The held-out protocol (``metrics.test.protocol``, ``same_recordings``) and, for
    a regressor, the MAE's intervals (a classifier's come from class_report)."""
    if regression:
        add_intervals(metrics["train"], ws_train, np.abs(np.asarray(out_train).reshape(-1) - y),
                      key="mae")
        if "test" in metrics:
            add_intervals(metrics["test"], ws_test,
                          np.abs(np.asarray(out_test).reshape(-1) - yt), key="mae")
    if "test" in metrics:
        protocol = holdout_protocol(holdout)
        if protocol == "given" and _shares_recordings(ws_train, ws_test):
            protocol = LATER_FRAMES         # a given test set cut from the same recordings
        metrics["test"]["protocol"] = protocol
        metrics["test"]["same_recordings"] = protocol == LATER_FRAMES


def _shares_recordings(ws_train, ws_test) -> bool:
    """Whether a given test set holds windows of a recording the training set holds
    (both must name their recordings; trial numbers of two sets are not comparable)."""
    if ws_test is None or ws_train.recordings is None or ws_test.recordings is None:
        return False
    return bool(set(map(str, ws_train.recordings)) & set(map(str, ws_test.recordings)))


def _training_info(ws_train, ws_test, holdout: str, seed: int, hp: dict) -> dict:
    return {"data": ws_train.summary(),
            "test_data": None if ws_test is None else ws_test.summary(),
            "holdout": holdout, "seed": seed, **hp}
