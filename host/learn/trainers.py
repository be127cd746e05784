"""The trainer of each model kind, in steps: what :data:`host.learn.train.TRAINERS`
looks a kind up in.

A trainer takes one :class:`host.learn.train.Run` (the :class:`TrainConfig`, the
split windows, the output folder) and returns the run's result (metrics, int8
check, files) after writing the model folder once. The estimator kinds (ridge,
fnn, grid-fnn, gbt) share one trainer of small steps: :func:`plan` (the settings
the kind reads), :func:`encode` (augmented copies, model inputs, targets),
cross-validation, :func:`fit_export`, :func:`int8_step`, the identity check and
:func:`write_folder`. The rule has no weights (:func:`train_rule`); the CNN
(:func:`train_frames_cnn`, PyTorch) is fitted by :mod:`host.learn.cnn` and goes
through the same int8 and write steps.

The fnn's temporal layer: pins a training recording keeps losing are masked
(:func:`recording_lost_pins`), and for texture it reads the roughness of the
displacement field over the layout neighbours (:func:`texture_neighbours`).
"""
from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from device.pi.models.manifest import write_spec, write_variant_specs
from device.pi.vision.neighbours import layout_neighbours
from host.data.dataset import atomic_write
from host.data.extract import layout_for_profile
from host.data.windows import DataError
from host.learn.card import measure_cost
from host.learn.cv import cross_validate_model
from host.learn.estimators import (default_uses_imu, fit_estimator, fit_rule, hyperparameters,
                                   pipeline_to_onnx, rule_probs)
from host.learn.identity import identity_check
from host.learn.inputs import augment_rotations, model_inputs
from host.learn.metrics import add_intervals
from host.learn.onnx_io import FLOAT_NAME, INT8_NAME, fill_variants, new_spec, run_onnx, session
from host.learn.pressure import checked_onnx
from host.learn.quantise import quantise_model
from host.learn.rates import augment_rates
from host.learn.sessions import augment_sessions, session_settings
from host.learn.tasks import (LAYOUT, TASK_HIDDEN, TASK_RATES, TASK_SESSIONS, QuantisationError,
                              TrainError)

__all__ = ["train_estimator", "train_rule", "train_frames_cnn", "fnn_temporal_spec",
           "recording_lost_pins", "texture_neighbours", "MAX_LOST_SHARE"]

#: a pin lost in more than this share of one training recording's windows is ignored
MAX_LOST_SHARE = 0.2
#: the CNN's int8 model is calibrated on at most this many training windows
CNN_CALIBRATION = 512


# -- the fnn's temporal layer --------------------------------------------------------

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
    roughness features. One place, for training and the regulariser comparison
    (:mod:`host.bench.regularise`)."""
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


# -- the steps -----------------------------------------------------------------------

@dataclass
class Plan:
    """What an estimator kind reads: its input layout, the IMU, the temporal layer
    (``tspec``, the pins it ignores), hyperparameters, frame-rate copies and
    recording-session copies (``sessions``: their settings, or False)."""
    layout: str
    uses_imu: bool
    temporal: bool
    tspec: dict | None
    ignored: list
    hp: dict
    rates: tuple
    sessions: dict | bool = False


@dataclass
class Encoded:
    """The model inputs and targets of the fit (``X``, ``y``, augmented copies after
    the ``n0`` original windows) and of the test windows (``Xt``, ``yt``)."""
    ws_fit: object
    X: np.ndarray
    y: np.ndarray
    Xt: np.ndarray | None
    yt: np.ndarray | None
    n0: int


def plan(run) -> Plan:
    """The settings the run's kind reads, checked against the windows."""
    cfg, T = run.cfg, run.train.window
    layout = LAYOUT[cfg.model]
    uses_imu = cfg.uses_imu
    if cfg.model == "rule":
        uses_imu = False
    elif uses_imu is None:
        uses_imu = default_uses_imu(cfg.model, run.train)
    elif uses_imu and layout != "vectors":
        raise TrainError(f"uses_imu=True needs input_layout vectors; {cfg.model} reads {layout}")
    if uses_imu and run.test is not None and run.test.imu is None:
        raise TrainError("the model uses the IMU but the test windows carry none")
    temporal = cfg.model == "fnn" and T >= 2 if cfg.temporal is None else cfg.temporal
    if temporal and (cfg.model != "fnn" or T < 2):
        raise TrainError(f"temporal=True needs the fnn and T >= 2 frames, got "
                         f"model={cfg.model!r} T={T}")
    tspec = (fnn_temporal_spec(cfg.task, run.train, T, uses_imu, cfg.profile)
             if temporal else None)
    ignored = ([m for m, keep in enumerate(tspec["pin_mask"]) if not keep]
               if tspec and tspec["pin_mask"] else [])
    hidden = TASK_HIDDEN.get(cfg.task) if cfg.hidden is None else cfg.hidden
    hp = (hyperparameters(cfg.model, hidden, cfg.alpha, cfg.epochs, tspec, window=T,
                          n_pins=run.train.n_pins) if cfg.model != "rule" else {})
    if cfg.augment and layout != "vectors":
        raise TrainError(f"augment={cfg.augment} rotates pin vectors; {cfg.model} reads "
                         f"{layout}")
    if cfg.augment and cfg.model == "rule":
        raise TrainError("augment: the rule has nothing to learn from rotated copies")
    rates = cfg.rates
    if rates is None:
        rates = TASK_RATES.get(cfg.task, ()) if cfg.model == "fnn" else ()
    return Plan(layout, bool(uses_imu), bool(temporal), tspec, ignored, hp, tuple(rates),
                _sessions(cfg, layout))


def _sessions(cfg, layout: str):
    """The session copies' settings the run fits (:mod:`host.learn.sessions`), or False."""
    if cfg.sessions is None:
        return (session_settings(TASK_SESSIONS.get(cfg.task)) or False) \
            if cfg.model == "fnn" else False
    if cfg.sessions and (layout != "vectors" or cfg.model == "rule"):
        what = "learns no weights" if cfg.model == "rule" else f"reads {layout}"
        raise TrainError(f"sessions: session copies are pin-vector windows to fit; model "
                         f"{cfg.model} {what} (set sessions = false)")
    return cfg.sessions


def encode(run, p: Plan) -> Encoded:
    """The fit's windows (frame-rate and rotated copies added) encoded as the Pi
    encodes them, and the targets; a TrainError when nothing can be learnt."""
    cfg = run.cfg
    ws_fit = augment_rates(run.train, p.rates, cfg.seed) if p.rates else run.train
    if p.sessions:
        ws_fit = augment_sessions(run.train, p.sessions, cfg.profile, cfg.seed, onto=ws_fit)
    ws_fit = augment_rotations(ws_fit, cfg.augment, cfg.profile) if cfg.augment else ws_fit
    X = model_inputs(ws_fit, p.layout, p.uses_imu)
    Xt = model_inputs(run.test, p.layout, p.uses_imu) if run.test is not None else None
    if not np.isfinite(X).all():
        raise TrainError("model inputs hold NaN or inf after encoding")
    if len(X) >= 2 and not (X.std(axis=0) > 0).any():
        raise TrainError(f"every input feature of the {len(X)} training windows has zero "
                         f"variance (the windows are all identical): nothing to learn")
    y, yt = run.targets(ws_fit), run.targets(run.test)
    if run.regression and not (y.std() > 0):
        raise TrainError(f"targets: every training target is {y[0]}; nothing to learn")
    return Encoded(ws_fit, X, y, Xt, yt, len(run.train))


def cross_validation(run, p: Plan) -> dict | None:
    """``cv``: grouped K-fold cross-validation on the training windows, timed."""
    cfg = run.cfg
    if cfg.cv is None:
        return None
    t0 = time.perf_counter()
    out = cross_validate_model(cfg, run.train, p.hp, uses_imu=p.uses_imu,
                               classes=run.classes or None, progress=run.progress)
    out["cv_s"] = round(time.perf_counter() - t0, 3)
    return out


def fit_export(run, p: Plan, e: Encoded) -> tuple[bytes, dict]:
    """The fitted estimator as ONNX bytes (trees checked against scikit-learn) and
    its fit record."""
    cfg = run.cfg
    pipe, fit_info = fit_estimator(cfg.task, cfg.model, e.X, e.y, len(run.classes), p.hp,
                                   cfg.seed, f"{cfg.task} {cfg.model} T={run.train.window}"
                                   if run.progress else None)
    if cfg.model == "gbt":
        onnx_model, fit_info["onnx_parity"] = checked_onnx(pipe, e.X, e.y)
    else:
        onnx_model = pipeline_to_onnx(pipe, e.X.shape[1], cfg.task)
    return onnx_model.SerializeToString(), fit_info


def int8_step(run, fbytes: bytes, cal: np.ndarray, check: tuple) -> tuple[dict | None, bytes | None]:
    """``quantise``: the int8 copy of ``fbytes`` calibrated on ``cal`` and checked
    on ``check`` = (inputs, targets, windows), with its metrics there. A failed check
    raises, or with ``quantise="if-passes"`` keeps the float model and records why.
    (int8 verdict, int8 bytes or None)."""
    cfg = run.cfg
    if not cfg.quantise:
        return None, None
    X, y, ws = check
    with tempfile.TemporaryDirectory(prefix="tacfoot-int8-") as tmp:
        qpath = Path(tmp) / INT8_NAME
        try:
            int8 = quantise_model(fbytes, cal, qpath, check_inputs=X, check_targets=y,
                                  min_agreement=cfg.min_agreement,
                                  calibrate_method=cfg.calibrate_method)
        except QuantisationError as exc:          # name the file the user asked for
            msg = str(exc).replace(str(qpath), str(run.out / INT8_NAME))
            if cfg.quantise != "if-passes":
                raise exc.with_message(msg) from None
            return {"failed": msg, **exc.fields()}, None      # keep the float model
        qbytes = qpath.read_bytes()
    int8.pop("path", None)
    int8["metrics"] = run.score(ws, y, run_onnx(session(qbytes), X))
    return int8, qbytes


def calibration_rows(run, n: int, cap: int) -> np.ndarray:
    """A seeded random choice of ``min(n, cap)`` of ``n`` fit windows, in order."""
    rng = np.random.default_rng(run.cfg.seed)
    return np.sort(rng.choice(n, min(n, cap), replace=False))


def write_folder(run, spec, fbytes: bytes, qbytes: bytes | None) -> dict:
    """The model folder, once: the float file, the int8 file beside it (a stale one
    removed), then the spec with every file's checksum and, with ``measure``, the
    cost per decision (:func:`measure_cost`). Returns the files' records."""
    out = run.out
    out.mkdir(parents=True, exist_ok=True)
    atomic_write(out / FLOAT_NAME, lambda fh: fh.write(fbytes))
    if qbytes is not None:
        atomic_write(out / INT8_NAME, lambda fh: fh.write(qbytes))
    else:
        (out / INT8_NAME).unlink(missing_ok=True)     # a stale int8 file from an earlier run
    files = fill_variants(out, spec, int8=qbytes is not None)
    if run.cfg.measure:
        spec.measured.cost_per_decision = measure_cost(out, spec)
    write_variant_specs(out, spec)
    return files


def identity_step(run, p: Plan) -> dict | None:
    """``identity``: can the kind tell the recordings of one class apart
    (:mod:`host.learn.identity`)? Its warning also goes to the test metrics."""
    cfg = run.cfg
    if not cfg.identity:
        return None
    return identity_check(run.train, cfg.task, cfg.model, p.hp, p.uses_imu, cfg.seed)


# -- the trainers --------------------------------------------------------------------

def train_estimator(run) -> dict:
    """ridge, fnn, grid-fnn, gbt: plan, encode, cross-validate, fit and export,
    score, int8, identity check, write."""
    p = plan(run)
    e = encode(run, p)
    metrics = _with_cv({}, run, p)
    fbytes, fit_info = fit_export(run, p, e)
    sess = session(fbytes)
    out_train = run_onnx(sess, e.X[:e.n0])
    out_test = run_onnx(sess, e.Xt) if e.Xt is not None else None
    metrics["train"] = run.score(run.train, e.y[:e.n0], out_train)
    if out_test is not None:
        metrics["test"] = run.score(run.test, e.yt, out_test)
    if run.cfg.model == "gbt" and run.cfg.quantise:
        int8, qbytes = {"skipped": "a tree ensemble has no weights to quantise; the float "
                                   "model is the default"}, None
    else:
        check = ((e.Xt, e.yt, run.test) if e.Xt is not None
                 else (e.X[:e.n0], e.y[:e.n0], run.train))
        cal = e.X[calibration_rows(run, len(e.X), run.cfg.calibration_windows)]
        int8, qbytes = int8_step(run, fbytes, cal, check)
    if run.regression:
        _mae_intervals(metrics, run, e, (out_train, out_test))
    ident = identity_step(run, p)
    result = run.result(metrics, p.layout, int8, ident)
    result.update(ignored_pins=p.ignored, uses_imu=p.uses_imu, temporal_features=p.temporal,
                  roughness=bool(p.tspec and p.tspec["neighbours"]), fit=fit_info)
    keys = {"model": run.cfg.model, "classes": run.classes, "T": run.train.window,
            "ignored_pins": p.ignored, "roughness": result["roughness"],
            "input_layout": p.layout, "uses_imu": p.uses_imu,
            "output": "variable" if run.regression else "probabilities",
            "output_kind": "value" if run.regression else "probabilities",
            "variant": "int8" if qbytes is not None else "float",
            "metrics": metrics, "int8": int8, "identity": ident, **run.spec_keys(),
            "training": run.training_info(dict(
                p.hp, **fit_info, augment=run.cfg.augment, rates=list(p.rates),
                augmented_deg=e.ws_fit.source.get("augmented_deg"),
                sessions=e.ws_fit.source.get("augmented_sessions") or False,
                fit_windows=int(len(e.X))))}
    if run.regression:
        keys.update({"target_mean": float(e.y.mean()),
                     "target_range": [float(e.y.min()), float(e.y.max())],
                     "input_clip": [e.X.min(axis=0).tolist(), e.X.max(axis=0).tolist()]})
    spec = new_spec(e.X.shape[1], dict(keys, kind=run.cfg.task), FLOAT_NAME)
    result["files"] = write_folder(run, spec, fbytes, qbytes)
    result["default"] = INT8_NAME if qbytes is not None else FLOAT_NAME
    return result


def _mae_intervals(metrics: dict, run, e: Encoded, outs: tuple) -> None:
    """A regressor's MAE intervals (a classifier's come from class_report)."""
    pairs = (("train", run.train, e.y[:e.n0], outs[0]), ("test", run.test, e.yt, outs[1]))
    for name, ws, y, out in pairs:
        if name in metrics:
            add_intervals(metrics[name], ws, np.abs(np.asarray(out).reshape(-1) - y),
                          key="mae")


def _with_cv(metrics: dict, run, p: Plan) -> dict:
    cv = cross_validation(run, p)
    return metrics if cv is None else dict(metrics, cv=cv)


def train_rule(run) -> dict:
    """The paper's rules: thresholds from the training windows, no weights, no ONNX
    file; only the spec is written."""
    cfg = run.cfg
    p = plan(run)
    e = encode(run, p)
    rc = fit_rule(cfg.task, run.train, run.classes)
    metrics = _with_cv({"train": run.score(run.train, e.y, rule_probs(rc, e.X))}, run, p)
    if run.test is not None:
        metrics["test"] = run.score(run.test, e.yt, rule_probs(rc, e.Xt))
    int8 = {"skipped": "a rule has no weights to quantise"} if cfg.quantise else None
    result = run.result(metrics, p.layout, int8, None)
    result.update(rule=rc.rule, ignored_pins=[], uses_imu=False, temporal_features=False,
                  roughness=False)
    mpath = write_spec(run.out, new_spec(e.X.shape[1], {
        **rc.spec_fields(), "metrics": metrics, **run.spec_keys(),
        "training": run.training_info({})}))
    result["files"] = {mpath.name: {"size_bytes": mpath.stat().st_size}}
    return result


def train_frames_cnn(run) -> dict:
    """The paper's CNN over stacked binary frames (:mod:`host.learn.cnn`, PyTorch):
    fitted and exported there, then the same int8 and write steps as the others,
    so its folder is written once too."""
    from host.learn.cnn import INPUT_NAME, cnn_spec_keys, frames_input, train_cnn
    cfg = run.cfg
    unread = [k for k in ("cv", "augment", "rates", "sessions", "uses_imu", "temporal", "alpha",
                          "hidden")
              if getattr(cfg, k) not in (None, 0, False, ())]
    if unread:
        raise TrainError(f"model cnn: the CNN does not take {', '.join(unread)}; drop "
                         f"{'it' if len(unread) == 1 else 'them'} or choose another kind")
    kw = {} if cfg.epochs is None else {"epochs": cfg.epochs}
    res = train_cnn(run.train, run.test, seed=cfg.seed, progress=run.progress, **kw)
    run.classes = list(res["classes"])         # the network's outputs, in its order
    fbytes = res.pop("onnx").SerializeToString()
    res.pop("estimator", None)
    X = frames_input(run.train.frames)
    Xt = frames_input(run.test.frames) if run.test is not None else None
    y, yt = run.targets(run.train), run.targets(run.test)
    check = (Xt, yt, run.test) if Xt is not None else (X, y, run.train)
    int8, qbytes = int8_step(run, fbytes, X[calibration_rows(
        run, len(X), min(cfg.calibration_windows, CNN_CALIBRATION))], check)
    sess = session(fbytes)                     # scored as the other kinds, by ONNX Runtime
    metrics = dict(res["metrics"], train=run.score(run.train, y, run_onnx(sess, X)))
    if Xt is not None:
        metrics["test"] = run.score(run.test, yt, run_onnx(sess, Xt))
    result = dict(res, **run.result(metrics, "frames", int8, None))
    T, S = res["T"], res["frame_size"]
    keys = dict(cnn_spec_keys(res), metrics=metrics, int8=int8, **run.spec_keys(),
                variant="int8" if qbytes is not None else "float",
                training=run.training_info({"train_s": res["train_s"]}))
    spec = new_spec(T * S * S, dict(keys, kind=cfg.task), FLOAT_NAME, input_name=INPUT_NAME,
                    input_dims=[T, S, S])
    result["files"] = write_folder(run, spec, fbytes, qbytes)
    result["default"] = INT8_NAME if qbytes is not None else FLOAT_NAME
    return result
