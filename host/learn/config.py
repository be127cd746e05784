"""One typed training config: what a ``host train`` run trains, built once.

:class:`TrainConfig` is frozen. ``host train`` builds it from its flags, or from a
model's ``train.toml`` (``--config``, :meth:`TrainConfig.from_replay`), and hands it
to :func:`host.learn.train.train`, which looks the model kind up in one table
(:data:`host.learn.train.TRAINERS`). Every setting is checked here, once, with a
:class:`~host.learn.tasks.TrainError` naming the field and the value.

:meth:`TrainConfig.replay` gives the settings that ``train.toml`` records
(:data:`REPLAY_KEYS`); :meth:`TrainConfig.from_replay` reads them back, so a model
folder's ``train.toml`` replays the run that made it.
"""
from __future__ import annotations

from dataclasses import dataclass, fields, replace
from pathlib import Path

from device.checks import finite_number
from host.learn.sessions import session_settings
from host.learn.tasks import (DEFAULT_MODEL, DEFAULT_WINDOW, MIN_AGREEMENT, MODELS, TASK_MODELS,
                              TASKS, TrainError, check_choice, check_int)

__all__ = ["TrainConfig", "REPLAY_KEYS", "QUANTISE"]

#: the settings a model's train.toml records (replayed by ``host train --config``)
REPLAY_KEYS = ("task", "model", "T", "data", "test", "cv", "quantise", "contact_only",
               "profile", "seed", "sessions")
#: ``quantise``: no int8 file, an int8 file that must pass its check, or one kept only
#: when it passes (else the float model is the default and the manifest says why)
QUANTISE = (False, True, "if-passes")


def _strings(name: str, value) -> tuple[str, ...]:
    if isinstance(value, (str, bytes)) or not isinstance(value, (list, tuple)):
        raise TrainError(f"{name} must be a list of data specs, got {name}={value!r}")
    bad = [v for v in value if not isinstance(v, str) or not v]
    if bad:
        raise TrainError(f"{name} must be a list of data specs (paths), got {bad[0]!r} in it")
    return tuple(value)


@dataclass(frozen=True)
class TrainConfig:
    """The settings of one training run.

    ``task`` and ``model`` (None: the task's default kind, :data:`DEFAULT_MODEL`);
    ``T`` frames per window (None: the windows' own; ``host train`` fills the
    task's default); ``data`` and ``test`` the data specs the windows were loaded
    from (empty when windows are handed in directly), ``contact_only`` how;
    ``profile`` the sensor profile every feature is computed with; ``seed``; ``cv``
    grouped K-fold CV (None: none); ``quantise`` one of :data:`QUANTISE`;
    ``identity`` run the recording-identity check; ``measure`` time the cost per
    decision. The fit: ``augment`` rotated copies, ``rates`` frame-keeping rules
    (None: the task's), ``sessions`` recording-session copies (None: the task's,
    False: none, True or a table: :func:`host.learn.sessions.session_settings`),
    ``uses_imu`` and ``temporal`` (None: the kind's default),
    ``hidden``, ``alpha``, ``epochs`` (None: the kind's); the int8 calibration:
    ``calibration_windows``, ``calibrate_method``, ``min_agreement``.
    """

    task: str
    model: str | None = None
    T: int | None = None
    data: tuple = ()
    test: tuple = ()
    contact_only: bool = False
    profile: str = "roboskin"
    seed: int = 0
    cv: int | None = None
    quantise: bool | str = False
    identity: bool = False
    measure: bool = False
    augment: int = 0
    rates: tuple | None = None
    sessions: bool | dict | None = None
    uses_imu: bool | None = None
    temporal: bool | None = None
    hidden: tuple | None = None
    alpha: float | None = None
    epochs: int | None = None
    calibration_windows: int = 2000
    calibrate_method: str = "minmax"
    min_agreement: float = MIN_AGREEMENT

    def __post_init__(self):
        check_choice("task", self.task, TASKS)
        model = DEFAULT_MODEL[self.task] if self.model is None else self.model
        check_choice("model", model, MODELS)
        if model not in TASK_MODELS[self.task]:
            raise TrainError(f"model={model!r} does not serve task={self.task!r}; task "
                             f"{self.task} takes {list(TASK_MODELS[self.task])}")
        if not (isinstance(self.quantise, bool) or self.quantise == "if-passes"):
            raise TrainError(f"quantise must be True, False or 'if-passes', got "
                             f"{self.quantise!r}")
        if not 0.0 < finite_number("min_agreement", self.min_agreement, error=TrainError) <= 1:
            raise TrainError(f"min_agreement must be in (0, 1], got min_agreement="
                             f"{self.min_agreement!r}")
        if not isinstance(self.profile, str) or not self.profile:
            raise TrainError(f"profile must be a profile name or a .toml path, got "
                             f"profile={self.profile!r}")
        for name in ("contact_only", "identity", "measure"):
            if not isinstance(getattr(self, name), bool):
                raise TrainError(f"{name} must be true or false, got "
                                 f"{name}={getattr(self, name)!r}")
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731 (frozen)
        set_("model", model)
        set_("seed", check_int("seed", self.seed, 0))
        set_("augment", check_int("augment", self.augment, 0))
        set_("calibration_windows", check_int("calibration_windows",
                                              self.calibration_windows, 1))
        set_("data", _strings("data", self.data))
        set_("test", _strings("test", self.test))
        set_("sessions", session_settings(self.sessions))
        if self.T is not None:
            set_("T", check_int("T", self.T, 1))
        if self.cv is not None:
            set_("cv", check_int("cv", self.cv, 2))
        for name in ("rates", "hidden"):
            v = getattr(self, name)
            if v is not None:
                set_(name, tuple(v) if isinstance(v, (list, tuple)) else v)

    @property
    def window(self) -> int:
        """T, or the task's default (:data:`DEFAULT_WINDOW`)."""
        return DEFAULT_WINDOW[self.task] if self.T is None else self.T

    def replay(self) -> dict:
        """The settings train.toml records (:data:`REPLAY_KEYS`): data paths and a
        .toml profile made absolute, so the file replays from anywhere."""
        def absolute(specs):
            return [d if "://" in d else str(Path(d).resolve()) for d in specs]
        prof = self.profile
        return {"task": self.task, "model": self.model, "T": self.window,
                "data": absolute(self.data), "test": absolute(self.test), "cv": self.cv,
                "quantise": bool(self.quantise), "contact_only": self.contact_only,
                "profile": str(Path(prof).resolve()) if prof.endswith(".toml") else prof,
                "seed": self.seed,
                "sessions": None if self.sessions is None else
                (dict(self.sessions) if self.sessions else False)}

    @classmethod
    def from_replay(cls, doc: dict, source: str, **run) -> "TrainConfig":
        """The config of a train.toml's settings ``doc`` (read from ``source``), with
        the run's own settings ``run`` (e.g. ``identity``, ``measure``). A TrainError
        names the file and the setting it does not know or cannot use."""
        unknown = sorted(set(doc) - set(REPLAY_KEYS))
        if unknown:
            raise TrainError(f"--config {source}: unknown setting(s) {unknown}; host train "
                             f"replays {sorted(REPLAY_KEYS)}")
        data = doc.get("data")
        if not isinstance(data, list) or not data:
            raise TrainError(f"--config {source}: data must be a non-empty list of data "
                             f"specs")
        if doc.get("task") not in DEFAULT_MODEL:
            raise TrainError(f"--config {source}: task must be one of "
                             f"{sorted(DEFAULT_MODEL)}, got {doc.get('task')!r}")
        kw = {k: v for k, v in doc.items() if v is not None}
        kw["test"] = kw.get("test") or ()
        try:
            return cls(**kw, **run)
        except TrainError as exc:
            raise TrainError(f"--config {source}: {exc}") from None

    def but(self, **changes) -> "TrainConfig":
        """A copy with ``changes`` (checked again)."""
        return replace(self, **changes)

    @classmethod
    def settings(cls) -> tuple[str, ...]:
        """The names of every setting."""
        return tuple(f.name for f in fields(cls))
