"""``host train``: windows in, a deployable model folder out.

:func:`train` takes one :class:`~host.learn.config.TrainConfig`, splits the windows
(:func:`split_run`) and hands the :class:`Run` to the trainer of its model kind,
looked up in :data:`TRAINERS` (:mod:`host.learn.trainers`), which writes the model
folder once: ONNX (the scaler folded into the graph) + its manifest, and with
``quantise`` an int8 ONNX file beside the float one, checked against it.
:func:`train_model` is the same for a caller holding windows and keywords.

The tasks and kinds are listed in :mod:`host.learn.tasks`; the fnn's graph is
[frame-to-frame changes (:mod:`host.learn.layers`, T >= 2)] -> standard scaling
clipped to +-8 sd -> MLP (:mod:`host.learn.estimators`). Every model's input is
built by :mod:`device.pi.models.window`, the encoders the Pi runs
(:func:`host.learn.inputs.model_inputs`). The slip detector is the ``fnn`` (or
``rule``) of task ``slip``: it emits a slip event (argmax) and a confidence (the slip
probability); its detection latency in frames from the true onset is measured on
the held-out trials (:func:`host.learn.metrics.slip_latency`).

Held-out data: ``ws_test`` when given; otherwise :func:`host.data.splits.split_holdout`.
The recording is the unit: of a class with two or more recordings, whole recordings
are held out; a class with one recording is tested on its last 30 %, after a gap of T
frames, which is optimistic (the same session). ``metrics.test.held_out`` names the
recordings of each kind (:func:`host.data.splits.held_out_recordings`). A class that
the data or the test windows carry but the training windows do not is a TrainError
that names it. ``cv=K`` adds grouped K-fold cross-validation on the training windows
(:func:`host.learn.cv.cross_validate_model`).

Model folder::

    (the manifest)         task, classes, T, feature spec, input layout, IMU use,
                           metrics, int8 check, sha256 + size of each file, data summary
    manifest.float.json    (quantised models only) the same, loading the float file
    model.onnx             float32
    model.int8.onnx        (``quantise``) static QDQ int8, the default to load
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from host.data.splits import (LATER_FRAMES, held_out_recordings, holdout_protocol,
                              split_holdout)
from host.data.windows import DataError, WindowSet
from host.learn.config import TrainConfig
from host.learn.metrics import class_report, regression_metrics
from host.learn.onnx_io import spec_profile
from host.learn.tasks import TrainError, label_ids
from host.learn.trainers import (MAX_LOST_SHARE, fnn_temporal_spec, recording_lost_pins,
                                 texture_neighbours, train_estimator, train_frames_cnn,
                                 train_rule)

__all__ = ["train", "train_model", "TRAINERS", "Run", "split_run", "check_classes",
           "fnn_temporal_spec", "recording_lost_pins", "texture_neighbours", "MAX_LOST_SHARE"]

#: the trainer of each model kind (host.learn.tasks.MODELS): a function of a Run that
#: writes the model folder once and returns the run's result
TRAINERS = {"rule": train_rule, "ridge": train_estimator, "fnn": train_estimator,
            "grid-fnn": train_estimator, "gbt": train_estimator, "cnn": train_frames_cnn}


@dataclass
class Run:
    """One training run: its config, the split windows (``train``, ``test`` and how
    they were split), the training classes, where it writes and what made it
    (``made``: ``trained_on``, ``config``, the provenance the spec records)."""
    cfg: TrainConfig
    train: WindowSet
    test: WindowSet | None
    holdout: str
    classes: list
    out: Path
    progress: bool = True
    made: dict = field(default_factory=dict)

    @property
    def regression(self) -> bool:
        return self.cfg.task == "pressure"

    def targets(self, ws):
        """Targets (regression) or class ids of ``ws``; None without windows."""
        if ws is None:
            return None
        if self.regression:
            return np.asarray(ws.targets, np.float64)
        return label_ids(ws.labels, self.classes)

    def score(self, ws, y, out) -> dict:
        """The metrics of the model outputs ``out`` on windows ``ws`` (targets ``y``)."""
        if self.regression:
            return regression_metrics(y, out)
        return class_report(self.cfg.task, ws, y, out, self.classes)

    def spec_keys(self) -> dict:
        """The spec's profile, config and what it was trained on (with the split)."""
        trained_on = self.made.get("trained_on") or {}
        return {"profile": spec_profile(self.cfg.profile),
                "config": dict(self.made.get("config") or {}),
                "trained_on": dict({"data": "unknown", "recordings": []}, **trained_on,
                                   split=trained_on.get("split") or self.holdout)}

    def training_info(self, hp: dict) -> dict:
        return {"data": self.train.summary(),
                "test_data": None if self.test is None else self.test.summary(),
                "holdout": self.holdout, "seed": self.cfg.seed, **hp}

    def result(self, metrics: dict, layout: str, int8, identity) -> dict:
        """The run's result around a trainer's ``metrics`` (given the held-out
        protocol, the held-out recordings and the identity warning here)."""
        if "test" in metrics and metrics["test"] is not None:
            metrics["test"].update(self.held_out())
        if identity and identity.get("warning"):
            metrics.setdefault("test", {})["identity_warning"] = identity["warning"]
        out = {"task": self.cfg.task, "model": self.cfg.model, "T": self.train.window,
               "input_layout": layout, "classes": list(self.classes), "seed": self.cfg.seed,
               "holdout": self.holdout, "out_dir": str(self.out), "metrics": metrics,
               "int8": int8}
        if identity is not None:
            out["identity_check"] = identity
        return out

    def held_out(self) -> dict:
        """``protocol``, ``same_recordings`` and ``held_out``: the recordings held out
        whole and those split inside ({recording: test windows})."""
        protocol = holdout_protocol(self.holdout)
        shared = _shares_recordings(self.train, self.test)
        if protocol == "given" and shared:
            protocol = LATER_FRAMES         # a given test set cut from the same recordings
        if protocol == "given" and not _names_recordings(self.train, self.test):
            held = {"whole": {}, "inside": {}, "given": int(len(self.test))}
        else:
            held = held_out_recordings(self.train, self.test)
        return {"protocol": protocol, "same_recordings": bool(held.get("inside")),
                "held_out": held}


def train(cfg: TrainConfig, ws_train, ws_test=None, out_dir=None, progress: bool = True,
          made: dict | None = None) -> dict:
    """Train the kind ``cfg.model`` for ``cfg.task`` on ``ws_train``; evaluate on
    ``ws_test`` (or a held-out part of ``ws_train``, see the module doc); write the
    model folder ``out_dir`` once (ONNX + its manifest, + int8 with ``quantise``).
    ``made``: ``trained_on`` (data real/simulated, recordings with checksums;
    ``split`` is filled with the held-out protocol) and ``config`` (the settings that
    replay the run, :meth:`TrainConfig.replay`), recorded in the spec. Returns the
    result (metrics, int8 check, files, timings) as a JSON-able dict.

    Nothing is written when a check fails (:class:`TrainError`,
    :class:`~host.learn.tasks.QuantisationError`), except with
    ``quantise="if-passes"``: then a failed int8 check keeps the float model as the
    default and records why in ``result["int8"]["failed"]`` (the spec's ``int8``).
    """
    t0 = time.perf_counter()
    if not isinstance(cfg, TrainConfig):
        raise TrainError(f"cfg must be a host.learn.config.TrainConfig, got "
                         f"{type(cfg).__name__}")
    if out_dir is None:
        raise TrainError("out_dir is required: the folder to write the model to")
    run = split_run(cfg, ws_train, ws_test)
    run.out, run.progress, run.made = Path(out_dir), progress, dict(made or {})
    result = TRAINERS[cfg.model](run)
    result["train_s"] = round(time.perf_counter() - t0, 3)
    return result


def train_model(task: str, model: str, ws_train, ws_test=None, *, out_dir=None,
                progress: bool = True, **settings) -> dict:
    """:func:`train` with the config built from keywords: ``settings`` are
    :class:`TrainConfig`'s (``cv``, ``quantise``, ``seed``, ``hidden``, ...), and
    ``trained_on`` and ``config`` the provenance :func:`train` records."""
    made = {k: settings.pop(k) for k in ("trained_on", "config") if k in settings}
    cfg = TrainConfig(task=task, model=model, **settings)
    return train(cfg, ws_train, ws_test, out_dir, progress, made)


def split_run(cfg: TrainConfig, ws_train, ws_test=None) -> Run:
    """The run's windows checked and split (the module doc), and its classes: every
    class of the data and of the test windows must have training windows, two at
    least. ``out`` is not set yet."""
    _check_windows(ws_train, cfg, "ws_train")
    all_classes = [] if cfg.task == "pressure" else sorted({str(x) for x in ws_train.labels})
    if ws_test is None:
        ws_train, ws_test, holdout = _holdout(ws_train, cfg.seed)
    else:
        _check_windows(ws_test, cfg, "ws_test")
        if ws_test.window != ws_train.window:
            raise TrainError(f"ws_test has windows of T={ws_test.window}, ws_train T="
                             f"{ws_train.window}")
        holdout = "given"
    classes: list = []
    if cfg.task != "pressure":
        check_classes(ws_train, ws_test, all_classes)
        classes = sorted({str(x) for x in ws_train.labels})
        if len(classes) < 2:
            raise TrainError(f"labels: task {cfg.task} needs training windows of at least 2 "
                             f"classes, the data hold {len(classes)}: {classes}")
    return Run(cfg, ws_train, ws_test, holdout, classes, Path("."))


def _check_windows(ws, cfg: TrainConfig, what: str) -> None:
    task = cfg.task
    if not isinstance(ws, WindowSet):
        raise TrainError(f"{what} must be a host.data.windows.WindowSet, got {type(ws).__name__}")
    if len(ws) == 0:
        raise TrainError(f"{what} holds no windows")
    if ws.task != task:
        raise TrainError(f"{what} was loaded for task {ws.task!r}, not task={task!r}")
    if cfg.T is not None and ws.window != cfg.T:
        raise TrainError(f"{what} has windows of T={ws.window}, the config T={cfg.T}")
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


def _names_recordings(ws_train, ws_test) -> bool:
    return ws_train.recordings is not None and ws_test.recordings is not None


def _shares_recordings(ws_train, ws_test) -> bool:
    """Whether a given test set holds windows of a recording the training set holds
    (both must name their recordings; trial numbers of two sets are not comparable)."""
    if ws_test is None or not _names_recordings(ws_train, ws_test):
        return False
    return bool(set(map(str, ws_train.recordings)) & set(map(str, ws_test.recordings)))
