"""The leg runtime's decisions: surface class, slip and texture from the rolling
windows, with the gait context the MCU sends.

The rule classifier always runs (it sees the gait context: the load and the foot
motion the gait expects). A learned surface model, when loaded, makes the call; with
a fresh gait context the rule's probabilities are blended in with the weight
``decision.gait_rule_weight``, as the learned model cannot see the gait. Slip comes
from a slip model, else from the rule's ``slippery`` probability. A texture is only
decided in contact. Probabilities are in the SURFACE class order
(:data:`device.pi.protocol.SURFACE_CLASSES`). The learned models due on a frame run
as one call of the fused graph when the model set has one
(:mod:`device.pi.models.fused`), else one session each; the results are the same.

A frame with the ``frame`` fault (implausible for the sensor: noise, black, white,
bad pixel values) holds "no touch": class no-touch with all its probability, no
contact, no slip, no texture and no pressure; no model runs on it and the runtime
does not push it into the windows. The fault bit travels with the SURFACE packet.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from device.pi.models.rules import RuleClassifier
from device.pi.runtime.config import DecisionConfig
from device.pi.protocol import PHASE_STANCE, SURFACE_CLASSES

NO_TOUCH = SURFACE_CLASSES.index("no-touch")
SLIPPERY = SURFACE_CLASSES.index("slippery")
#: the slip flag is set in contact from this slip confidence on
SLIP_THRESHOLD = 0.5


@dataclass
class GaitContext:
    """The MCU's latest gait context (t = clock time it was sent: the runtime
    judges its age from when the MCU sent it, not from when it was decoded)."""
    stance: bool
    load_n: float
    vel_mm_s: float
    t: float


def finite_float(x, default: float = 0.0) -> float:
    """``x`` as a float, or ``default`` when it is not a finite number."""
    try:
        x = float(x)
    except (TypeError, ValueError):
        return default
    return x if math.isfinite(x) else default


def gait_from_message(msg, t: float) -> GaitContext:
    """The gait context of a GAIT message (device.pi.protocol.Gait): the
    foot's expected speed is the length of its horizontal velocity."""
    v = msg.vel_mm_s
    vel = (math.hypot(finite_float(v[0]), finite_float(v[1])) if len(v) >= 2
           else abs(finite_float(v[0])))
    return GaitContext(stance=int(msg.phase) == PHASE_STANCE,
                       load_n=max(0.0, finite_float(msg.load_n)), vel_mm_s=vel, t=t)


def expected_context(gait: GaitContext | None, now: float, dc: DecisionConfig, fps: float):
    """(expected_mag_px, expected_motion_px, gait dict | None) from a gait context
    fresher than ``dc.gait_timeout_ms``, or (None, None, None): the rule's nominal
    values."""
    age_ms = (now - gait.t) * 1e3 if gait is not None else math.inf
    if age_ms > dc.gait_timeout_ms:
        return None, None, None
    load = gait.load_n if gait.stance else 0.0
    mag = max(0.0, load) * dc.mag_px_per_n
    motion = abs(gait.vel_mm_s) * dc.motion_px_per_mm / fps if gait.stance else 0.0
    return mag, motion, {"stance": gait.stance, "load_n": round(gait.load_n, 3),
                         "vel_mm_s": round(gait.vel_mm_s, 3), "age_ms": round(max(0.0, age_ms), 1)}


def no_touch_probs() -> np.ndarray:
    """All the probability on no-touch: the call before the rule's window is full."""
    p = np.zeros(len(SURFACE_CLASSES))
    p[NO_TOUCH] = 1.0
    return p


@functools.lru_cache(maxsize=32)
def _surface_ids(classes: tuple) -> tuple[tuple[tuple[int, int], ...], bool]:
    """((index in the model's classes, SURFACE class id), ...) of the classes the link
    has an id for, and whether that is all of them: worked out once per class list."""
    pairs = tuple((i, SURFACE_CLASSES.index(c)) for i, c in enumerate(classes)
                  if c in SURFACE_CLASSES)
    return pairs, len(pairs) == len(classes)


def surface_probs_of_model(classes, p) -> np.ndarray:
    """A learned surface model's probabilities, listed in its manifest's class order,
    as SURFACE class ids (classes it does not know get 0; renormalised, uniform when
    nothing is left)."""
    out = np.zeros(len(SURFACE_CLASSES))
    n = len(p)
    for i, j in _surface_ids(tuple(classes))[0]:
        if i < n:
            out[j] = p[i]
    s = out.sum()
    return out / s if s > 0 else np.full(len(SURFACE_CLASSES), 1.0 / len(SURFACE_CLASSES))


def unknown_class_wins(classes, p) -> bool:
    """True when a surface model's most likely class is not a SURFACE class (a label
    the link has no id for): the decision then carries a model fault instead of
    quietly taking the best of the classes left."""
    if _surface_ids(tuple(classes))[1]:
        return False                  # every class has an id
    p = np.asarray(p, np.float64)
    return bool(p.size) and str(classes[int(np.argmax(p))]) not in SURFACE_CLASSES


def _result(ran, task: str, model, due: dict, **ctx):
    """A model's result this frame: from the fused graph's run when it ran the
    model, else from the model's own session."""
    if ran is not None and task in ran:
        return ran[task]
    return model.predict_window(due[task], **ctx)


@dataclass
class Decision:
    class_id: int
    probs: np.ndarray                 # SURFACE class order
    contact: bool
    slip: bool
    slip_conf: float
    texture: tuple | None             # (name, confidence, id)
    pressure: float | None
    model_fault: bool
    model_probs: np.ndarray | None    # the learned surface model's, when it ran
    rule_probs: np.ndarray
    measures: dict                    # the rule's window measures ({} before it ran)


def decide(models, windows: dict, *, contact_seen: bool, referenced: bool,
           expected_mag_px, expected_motion_px, gait, gait_rule_weight: float,
           frame_ok: bool = True) -> Decision:
    """One decision from the filled windows (``windows[T]`` holds T frames).
    ``contact_seen`` is the marker pipeline's contact; ``referenced`` says the
    pipeline has a reference frame (no pressure without one); ``frame_ok`` False
    (the frame fault) gives the "no touch" decision without running a model."""
    if not frame_ok:
        return Decision(NO_TOUCH, no_touch_probs(), False, False, 0.0, None, None, False,
                        None, no_touch_probs(), {})
    m = models
    model_fault = False
    rwin = windows[m.rule.T]
    learned_surface = m.surface is not None and m.surface is not m.rule
    # the learned models that decide this frame, each with its full window
    due = {}
    if learned_surface and windows[m.surface.T].full:
        due["surface"] = windows[m.surface.T]
    if m.texture is not None and contact_seen and windows[m.texture.T].full:
        due["texture"] = windows[m.texture.T]
    if m.slip is not None and windows[m.slip.T].full:
        due["slip"] = windows[m.slip.T]
    if m.pressure is not None and referenced and windows[m.pressure.T].full:
        due["pressure"] = windows[m.pressure.T]
    fused = getattr(m, "fused", None)
    ran = None
    if fused is not None:
        # one graph for every learned model due (rules are not in it)
        ran = fused.run({t: w for t, w in due.items() if t in fused.tasks})
    probs_rule = None
    if rwin.full:
        _, probs_rule = m.rule.predict(rwin.encode("vectors"), expected_mag_px=expected_mag_px,
                                       expected_motion_px=expected_motion_px)
    rule_probs = no_touch_probs() if probs_rule is None else probs_rule
    surface = rule_probs
    model_probs = None
    if "surface" in due:
        _, p = _result(ran, "surface", m.surface, due)
        surface = model_probs = surface_probs_of_model(m.surface.classes, p)
        model_fault |= bool(m.surface.fault) or unknown_class_wins(m.surface.classes, p)
        wr = gait_rule_weight
        if gait is not None and probs_rule is not None and wr > 0:
            surface = (1.0 - wr) * model_probs + wr * rule_probs
    texture = None
    if "texture" in due:
        tid, tp = _result(ran, "texture", m.texture, due)
        texture = (m.texture.classes[tid], float(tp[tid]), tid)
        model_fault |= bool(m.texture.fault)
    measures = m.rule.last if rwin.full else {}
    slip_conf = 0.0
    if "slip" in due:
        ctx = ({"expected_mag_px": expected_mag_px, "expected_motion_px": expected_motion_px}
               if isinstance(m.slip, RuleClassifier) else {})
        sid, sp = _result(ran, "slip", m.slip, due, **ctx)
        slip_conf = (float(sp[list(m.slip.classes).index("slip")]) if "slip" in m.slip.classes
                     else float(sp[sid]))
        model_fault |= bool(m.slip.fault)
    elif probs_rule is not None:
        slip_conf = float(probs_rule[SLIPPERY])
    pressure = None
    if "pressure" in due:
        pressure = _result(ran, "pressure", m.pressure, due)
        model_fault |= pressure is not None and bool(m.pressure.fault)
        if pressure is not None and pressure < 0.0:
            # a normal load cannot pull: the regressor's error around no load (a few
            # hundredths of a newton below 0) is no load, not a value beyond the field
            pressure = 0.0
    class_id = int(np.argmax(surface))
    contact = bool(contact_seen) and class_id != NO_TOUCH
    slip = contact and slip_conf >= SLIP_THRESHOLD
    return Decision(class_id, surface, contact, slip, slip_conf, texture, pressure,
                    model_fault, model_probs, rule_probs, measures)
