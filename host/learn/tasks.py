"""Tasks, models and their defaults (``host train --task T --model M``), the
training errors and the argument checks the training modules share.

==========  =====================================================================
rule        the paper's rules, no weights (:mod:`device.pi.models.rules`): surface, slip
ridge       Ridge (alpha 150) over all pin vectors of the window: pressure
gbt         gradient-boosted trees over all pin vectors of the window, untracked
            pins filled from the tracked ones (:mod:`host.learn.pressure`):
            pressure (default)
fnn         MLP over T frames of ``encode_vectors`` (+ IMU when present), two
            hidden layers, logistic (sigmoid) units, standard scaling: surface,
            texture, slip; an MLP regressor for pressure. For texture its first
            layer also reads the roughness of the displacement field
            (:class:`host.learn.layers.TemporalFeatures` ``neighbours``)
grid-fnn    the same MLP over ``encode_grids`` (contact-grid maps and their
            frame-to-frame changes): texture, surface, slip
cnn         the paper's CNN over T stacked binary frames (:mod:`host.learn.cnn`,
            PyTorch, the ``cnn`` extra): texture, surface, slip
==========  =====================================================================
"""
from __future__ import annotations

import numpy as np

from device.checks import whole_number
from device.errors import TacfootError

__all__ = ["TASKS", "MODELS", "TASK_MODELS", "OPTIONAL_MODELS", "DEFAULT_MODEL",
           "DEFAULT_WINDOW", "TASK_HIDDEN", "TASK_RATES", "TASK_SESSIONS", "LAYOUT", "TrainError",
           "QuantisationError", "check_choice", "check_int", "label_ids"]

TASKS = ("surface", "texture", "slip", "pressure")
MODELS = ("rule", "ridge", "fnn", "grid-fnn", "gbt", "cnn")
#: which models serve which task (the trainer of each kind: host.learn.train.TRAINERS)
TASK_MODELS = {"surface": ("rule", "fnn", "grid-fnn", "cnn"),
               "texture": ("fnn", "grid-fnn", "cnn"),
               "slip": ("rule", "fnn", "grid-fnn", "cnn"), "pressure": ("gbt", "ridge", "fnn")}
#: the kinds that need an optional extra (the CNN: PyTorch)
OPTIONAL_MODELS = ("cnn",)
#: ``host train`` without ``--model``: the kind that does best on real recordings where
#: they exist (texture: roboskin clips; pressure: the hard-plate vectors, grouped 5-fold
#: CV MAE 55.5 for gbt against 70.1 for ridge, ``python -m host.learn.pressure``), else
#: on simulated data (surface, slip); see docs/accuracy-vs-time.md
DEFAULT_MODEL = {"surface": "fnn", "texture": "fnn", "slip": "fnn", "pressure": "gbt"}
#: ``host train`` without ``--window``: frames per window T
DEFAULT_WINDOW = {"surface": 3, "texture": 15, "slip": 3, "pressure": 1}
LAYOUT = {"rule": "vectors", "ridge": "vectors", "fnn": "vectors", "grid-fnn": "grids",
          "gbt": "vectors", "cnn": "frames"}
DEFAULT_HIDDEN = (64, 32)
#: tasks whose MLP has other hidden layers by default: texture reads T = 15 frames
#: (about 8000 inputs with its temporal layer); (16, 16) keeps it under 1 MB and fast
TASK_HIDDEN = {"texture": (16, 16)}
#: tasks whose fnn trains by default on copies of its windows re-cut at other frame
#: rates (:func:`host.learn.rates.augment_rates`, e.g. ``("3of5", "3of5+drop10")``).
#: Texture: the camera's rate differs between recordings and drops frames, and without
#: these copies the fnn counted frames (Lego replayed at 3 of 5 frames: 0.20). Over seeds
#: 0-2 the copies raise later frames (Lego vs smooth 0.93-0.95 -> 0.95-0.97) and the
#: 3-of-5 replays, and lower the gain 0.8 / gamma 0.7 exposure proxies
#: (``python -m host.bench.texture_robust --rates ...``; docs/BENCHMARKS.md)
TASK_RATES: dict = {"texture": ("3of5", "3of5+drop10")}
#: tasks whose fnn trains by default on copies of its windows as other recording
#: sessions would give them (:func:`host.learn.sessions.augment_sessions`: exposure,
#: pin layout offset, lost pins; ``True`` = its default settings). Texture: recordings
#: of one surface are told apart by exactly these (host.learn.identity), and a second
#: session of a surface scored below later frames of the first (docs/BENCHMARKS.md)
TASK_SESSIONS: dict = {"texture": True}
DEFAULT_ALPHA = {"ridge": 150.0, "fnn": 1e-3, "grid-fnn": 1e-3}
DEFAULT_EPOCHS = 300
MIN_AGREEMENT = 0.99
#: an int8 regressor fails its check when its MAE grows by more than this share of
#: the target range
MAX_REGRESSION_CHANGE = 0.01


class TrainError(TacfootError, ValueError):
    """Bad training input or a failed check; the message names the field and value."""


class QuantisationError(TrainError):
    """The int8 model disagrees with the float model; the int8 file is not kept.

    ``kind`` is ``"classifier"`` or ``"regressor"``; ``agreement`` the argmax
    agreement reached and ``required`` the bar (classifiers); ``mae_change`` and
    ``mae_change_of_range`` (regressors); ``path`` the int8 file not written.
    """

    #: the verdict's fields, as the manifest's ``int8`` records them
    FIELDS = ("kind", "agreement", "required", "mae_change", "mae_change_of_range")

    def __init__(self, message: str, *, path: str | None = None, **verdict):
        unknown = sorted(set(verdict) - set(self.FIELDS))
        if unknown:
            raise TypeError(f"QuantisationError: unknown field(s) {unknown}")
        super().__init__(message)
        for k in self.FIELDS:
            setattr(self, k, verdict.get(k))
        self.path = path

    def fields(self) -> dict:
        """The verdict's fields (all but ``path``)."""
        return {k: getattr(self, k) for k in self.FIELDS}

    def with_message(self, message: str) -> "QuantisationError":
        """The same verdict with another message (e.g. naming another file)."""
        return QuantisationError(message, **self.fields(), path=self.path)


def check_choice(name: str, value, choices) -> str:
    """``value``, or a TrainError naming the field when it is not one of ``choices``."""
    if value not in choices:
        raise TrainError(f"{name} must be one of {list(choices)}, got {name}={value!r}")
    return value


def check_int(name: str, value, lo: int) -> int:
    """``value`` as an int, or a TrainError naming the field when it is not a whole
    number >= ``lo``."""
    return whole_number(name, value, lo, error=TrainError)


def label_ids(labels, classes: list[str]) -> np.ndarray:
    """Class ids of ``labels`` in ``classes``; -1 for a label the model never saw."""
    index = {c: i for i, c in enumerate(classes)}
    return np.array([index.get(str(x), -1) for x in labels], np.int64)

