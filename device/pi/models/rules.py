"""The paper's rules, no training: surface and slip from a window of pin vectors.

A rule model is a manifest with no ONNX file: ``"model": "rule"`` and a ``rule``
table of thresholds, evaluated here with numpy. It has the same ``predict`` as
:class:`device.pi.models.classifier.Classifier`, and takes the same input (the ``vectors``
layout of :mod:`device.pi.models.window`, without IMU).

From the window's T frames of pin vectors (px) the rules measure

* ``magnitude_px``: the mean pin displacement |v| of the last frame (the magnitude
  sum P divided by the pin count), the sensor's pressure;
* the average vector of the last frame: its direction is the shear direction
  (:attr:`RuleClassifier.last`), the paper's first rule;
* ``motion_px``: how far the average vector moved per frame over the window
  (|a_T - a_1| / (T - 1)), the motion the skin shows. With T = 1 no motion is seen
  and the wet rule is off.

and decide, each test a soft step (a stable sigmoid of the margin, so the output is
a confidence, not just a label):

1. ``no-touch`` when ``magnitude_px`` is below ``contact_px``;
2. ``soft`` when the pressure is below ``soft_ratio`` times the pressure expected at
   the commanded load (``expected_mag_px``): the foot was pushed down as hard as on a
   hard floor, but the floor gave way;
3. ``slippery`` when motion is expected (``expected_motion_px`` > 0, from the gait
   context) but less than ``wet_ratio`` of it is seen: the foot moves, the skin
   does not follow;
4. ``hard`` otherwise.

The slip task uses rules 1 and 3 (``slip`` = in contact, motion expected but not
seen). The gait context comes from the locomotion MCU at run time (``predict``'s
``expected_mag_px`` and ``expected_motion_px``); offline, and when the MCU sends
none, the manifest's nominal values stand for it: the pressure and the per-frame
skin motion of a hard floor at the commanded stance load and foot speed, which
``host train --model rule`` sets from the training windows (it picks the thresholds
by a one-dimensional search; nothing else is fitted).

The manifest (the model spec, beside the usual keys; ``onnx`` is null)::

    {"model": "rule", "kind": "surface", "classes": [...], "T": 3,
     "input_layout": "vectors", "uses_imu": false,
     "params": {"n_pins": 133,
                "rule": {"contact_px": 1.0, "expected_mag_px": 6.0, "soft_ratio": 0.6,
                         "expected_motion_px": 0.5, "wet_ratio": 0.3},
                "rule_sha256": "..."}}   # of the canonical JSON of "rule"
"""
from __future__ import annotations

import hashlib
import json
import math

import numpy as np

from device.pi.models.artefact import FEATURE_SPEC_VERSION, ModelError
from device.pi.models.manifest import read_spec
from device.pi.numerics import finite, sigmoid1
from device.pi.protocol import SURFACE_CLASSES  # the SURFACE class ids
from device.pi.vision.features import direction_deg

RULE_TASKS = ("surface", "slip")
SLIP_CLASSES = ("no-slip", "slip")
#: the thresholds a rule table must hold, all finite and >= 0
RULE_KEYS = ("contact_px", "expected_mag_px", "soft_ratio", "expected_motion_px", "wet_ratio")
#: width of each soft step, as a share of its threshold
STEP_WIDTH = 0.1
_EPS = 1e-6


def rule_sha256(rule: dict) -> str:
    """The checksum of a rule table (its canonical JSON)."""
    return hashlib.sha256(json.dumps(rule, sort_keys=True, separators=(",", ":"))
                          .encode()).hexdigest()


def check_rule(rule, where: str = "rule") -> dict:
    """The rule table with every threshold a finite float >= 0; else ValueError
    naming the field and the value."""
    if not isinstance(rule, dict):
        raise ValueError(f"{where}: the rule must be a table of thresholds, got {rule!r}")
    out = {}
    for k in RULE_KEYS:
        v = rule.get(k)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
            raise ValueError(f"{where}: rule.{k} must be a finite number >= 0, got {v!r}")
        out[k] = float(v)
    return out


def window_measures(vectors: np.ndarray) -> dict:
    """The rules' measures of one window of pin vectors (T, M, 2) px; finite for
    any input (NaN and inf count as no displacement)."""
    v = finite(vectors, dtype=np.float64)
    if v.ndim != 3 or v.shape[2] != 2:
        raise ValueError(f"vectors must have shape (T, M, 2), got {v.shape}")
    T, M = v.shape[0], v.shape[1]
    if T == 0 or M == 0:
        return {"magnitude_px": 0.0, "shear_x_px": 0.0, "shear_y_px": 0.0,
                "direction_deg": 0.0, "motion_px": None}
    last = v[-1]
    # sum / count: the numbers of ndarray.mean without its Python wrapper
    mag = float(np.add.reduce(np.hypot(last[:, 0], last[:, 1])) / M)
    avg = np.add.reduce(v, axis=1) / M                    # (T, 2) average vector per frame
    ax, ay = float(avg[-1, 0]), float(avg[-1, 1])
    motion = (float(np.hypot(ax - float(avg[0, 0]), ay - float(avg[0, 1]))) / (T - 1)
              if T >= 2 else None)
    return {"magnitude_px": mag, "shear_x_px": ax, "shear_y_px": ay,
            "direction_deg": direction_deg(ax, ay), "motion_px": motion}


def _step_below(value: float, threshold: float) -> float:
    """Confidence that ``value`` is below ``threshold`` (a sigmoid step)."""
    w = STEP_WIDTH * threshold + _EPS
    return sigmoid1((threshold - value) / w)


def rule_probabilities(measures: dict, rule: dict, classes, expected_mag_px=None,
                       expected_motion_px=None) -> np.ndarray:
    """Class probabilities (C,) in the order of ``classes`` from a window's
    measures. The expected values are the gait context; None takes the rule's
    nominal ones."""
    mag = float(measures["magnitude_px"])
    motion = measures.get("motion_px")
    exp_mag = rule["expected_mag_px"] if expected_mag_px is None else expected_mag_px
    exp_motion = rule["expected_motion_px"] if expected_motion_px is None else expected_motion_px
    exp_mag = float(exp_mag) if math.isfinite(float(exp_mag)) else rule["expected_mag_px"]
    exp_motion = (float(exp_motion) if math.isfinite(float(exp_motion))
                  else rule["expected_motion_px"])
    p_contact = 1.0 - _step_below(mag, rule["contact_px"])
    p_soft = _step_below(mag, rule["soft_ratio"] * max(exp_mag, 0.0))
    if motion is None or exp_motion <= 0:
        p_still = 0.0
    else:
        p_still = _step_below(motion, rule["wet_ratio"] * exp_motion)
    probs = {"no-touch": 1.0 - p_contact,
             "soft": p_contact * p_soft,
             "slippery": p_contact * (1.0 - p_soft) * p_still,
             "hard": p_contact * (1.0 - p_soft) * (1.0 - p_still),
             "slip": p_contact * p_still,
             "no-slip": 1.0 - p_contact * p_still}
    p = np.array([probs.get(c, 0.0) for c in classes], dtype=np.float64)
    s = p.sum()
    return p / s if s > 0 and math.isfinite(s) else np.full(len(classes), 1.0 / len(classes))


class RuleClassifier:
    """A rule model: same ``predict`` as :class:`device.pi.models.classifier.Classifier`.

    ``rule`` holds the thresholds (:data:`RULE_KEYS`), ``classes`` the output
    order, ``T`` and ``n_pins`` the window the rule decodes from its input.
    :attr:`last` holds the measures of the last window (direction, pressure, motion).
    """

    def __init__(self, rule: dict, classes, T: int, n_pins: int, task: str = "surface",
                 spec=None, path=None):
        if task not in RULE_TASKS:
            raise ValueError(f"task must be one of {list(RULE_TASKS)}, got task={task!r}")
        known = SURFACE_CLASSES if task == "surface" else SLIP_CLASSES
        classes = list(classes)
        bad = [c for c in classes if c not in known]
        if len(classes) < 2 or bad:
            raise ValueError(f"classes must be at least 2 of {list(known)}, got {classes!r}")
        twice = sorted({c for c in classes if classes.count(c) > 1})
        if twice:          # a repeated class would share its probability between slots
            raise ValueError(f"classes must each be named once, got {classes!r} "
                             f"({', '.join(twice)} repeated)")
        if isinstance(T, bool) or not isinstance(T, (int, np.integer)) or T < 1:
            raise ValueError(f"T must be a whole number >= 1, got T={T!r}")
        if isinstance(n_pins, bool) or not isinstance(n_pins, (int, np.integer)) or n_pins < 1:
            raise ValueError(f"n_pins must be a whole number >= 1, got n_pins={n_pins!r}")
        self.rule = check_rule(rule)
        self.classes = classes
        self.task = task
        self.T = int(T)
        self.n_pins = int(n_pins)
        self.input_layout = "vectors"
        self.uses_imu = False
        self.n_features = self.T * self.n_pins * 2
        self.input_shape = (self.n_features,)
        #: the spec it was loaded from (None for a rule built from the leg config)
        self.spec = spec
        self.path = path
        self.fault = False
        self.last: dict = {}

    @classmethod
    def load(cls, path, expect_kind: str | None = None) -> "RuleClassifier":
        spec, mpath = read_spec(path)
        where = str(mpath)
        if spec.model != "rule":
            raise ModelError(f"{where}: not a rule model (model {spec.model!r})")
        if spec.feature_spec != FEATURE_SPEC_VERSION:
            raise ModelError(f"{where}: feature-spec version {spec.feature_spec} does not "
                             f"match this runtime's {FEATURE_SPEC_VERSION}; rebuild the rule")
        if expect_kind is not None and spec.kind != expect_kind:
            raise ModelError(f"{where}: kind is {spec.kind!r}, expected {expect_kind!r}")
        p = spec.params                 # RuleParams, typed by the one parse
        if p.rule_sha256 != rule_sha256(p.rule):
            raise ModelError(f"{where}: the rule table does not match its checksum "
                             f"rule_sha256; the manifest is corrupt or was edited")
        if spec.uses_imu:
            raise ModelError(f"{where}: a rule model reads no IMU (uses_imu must be false)")
        try:
            return cls(p.rule, spec.classes, spec.T, p.n_pins, task=spec.kind, spec=spec,
                       path=mpath.parent)
        except ValueError as exc:
            raise ModelError(f"{where}: {exc}") from None

    @property
    def n_classes(self) -> int:
        return len(self.classes)

    def spec_fields(self) -> dict:
        """The spec's fields and parameters of this rule, for a writer
        (:func:`host.learn.onnx_io.new_spec`)."""
        return {"model": "rule", "kind": self.task, "classes": list(self.classes),
                "T": self.T, "input_layout": "vectors", "uses_imu": False,
                "n_pins": self.n_pins, "rule": dict(self.rule),
                "rule_sha256": rule_sha256(self.rule)}

    def predict(self, window_input, expected_mag_px: float | None = None,
                expected_motion_px: float | None = None) -> tuple[int, np.ndarray]:
        """(class id, probabilities (C,)) for one encoded window (the ``vectors``
        layout, (D,) or (1, D)); the expected values are the gait context."""
        a = np.asarray(window_input, dtype=np.float64)
        if a.size != self.n_features:
            raise ModelError(f"{self.path}: the rule expects {self.n_features} values "
                             f"(T={self.T} x {self.n_pins} pins x 2), got {a.size}")
        m = window_measures(a.reshape(self.T, self.n_pins, 2))
        self.last = m
        p = rule_probabilities(m, self.rule, self.classes, expected_mag_px, expected_motion_px)
        self.fault = not np.isfinite(p).all()
        return int(np.argmax(p)), p

    def predict_window(self, window, **context) -> tuple[int, np.ndarray]:
        if window.T != self.T:
            raise ModelError(f"{self.path}: the rule sees T={self.T} frames, the window holds "
                             f"{window.T}")
        return self.predict(window.encode("vectors"), **context)
