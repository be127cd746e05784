"""Decisions (device/pi/runtime/decisions.py): the gait context from GAIT, the
expected load and motion it gives, learned-model probabilities as SURFACE class ids,
and one decision from rule windows."""
from __future__ import annotations

import math

import numpy as np
import pytest

from device.pi.models.window import RollingWindow
from device.pi import protocol as P
from device.pi.runtime.config import DecisionConfig, LegConfig
from device.pi.runtime.decisions import (SLIP_THRESHOLD, GaitContext, decide, expected_context,
                                         finite_float, gait_from_message, no_touch_probs,
                                         surface_probs_of_model)
from device.pi.runtime.load import load_models

N_PINS = 133


def test_gait_message_gives_stance_load_and_horizontal_speed():
    g = gait_from_message(P.Gait(P.PHASE_STANCE, 12.5, (3.0, 4.0, 99.0)), t=7.0)
    assert (g.stance, g.load_n, g.vel_mm_s, g.t) == (True, 12.5, 5.0, 7.0)
    swing = gait_from_message(P.Gait(P.PHASE_SWING, 1.0, (0.0, 0.0, 0.0)), t=0.0)
    assert swing.stance is False


def test_bad_gait_numbers_become_finite():
    msg = P.Gait(P.PHASE_STANCE, 0.0, (0.0, 0.0, 0.0))
    msg.load_n, msg.vel_mm_s = float("nan"), (float("inf"), -2.0)
    g = gait_from_message(msg, 0.0)
    assert g.load_n == 0.0 and g.vel_mm_s == 2.0
    assert finite_float("x", 3.0) == 3.0 and finite_float(float("-inf")) == 0.0


def test_expected_context_from_fresh_gait_and_none_when_stale():
    dc = DecisionConfig()
    g = GaitContext(stance=True, load_n=10.0, vel_mm_s=20.0, t=1.0)
    mag, motion, info = expected_context(g, 1.1, dc, fps=100.0)
    assert mag == pytest.approx(10.0 * dc.mag_px_per_n)
    assert motion == pytest.approx(20.0 * dc.motion_px_per_mm / 100.0)
    assert info == {"stance": True, "load_n": 10.0, "vel_mm_s": 20.0}
    assert expected_context(g, 1.0 + dc.gait_timeout_ms / 1e3 + 0.01, dc, 100.0) == \
        (None, None, None)
    assert expected_context(None, 0.0, dc, 100.0) == (None, None, None)
    swing = GaitContext(stance=False, load_n=10.0, vel_mm_s=20.0, t=1.0)
    assert expected_context(swing, 1.0, dc, 100.0)[:2] == (0.0, 0.0)


def test_model_probabilities_land_on_the_surface_class_ids():
    p = surface_probs_of_model(["hard", "no-touch", "slippery", "soft"], [0.1, 0.2, 0.3, 0.4])
    assert p.tolist() == pytest.approx([0.2, 0.1, 0.4, 0.3])      # no-touch, hard, soft, slippery
    only = surface_probs_of_model(["soft", "lego"], [0.5, 0.5])
    assert only.tolist() == pytest.approx([0.0, 0.0, 1.0, 0.0])
    assert surface_probs_of_model(["lego"], [1.0]).tolist() == pytest.approx([0.25] * 4)
    assert no_touch_probs().tolist() == [1.0, 0.0, 0.0, 0.0]


def _windows(models, vectors_px):
    Ts = {models.rule.T}
    ws = {T: RollingWindow(T, N_PINS) for T in Ts}
    for v in vectors_px:
        for w in ws.values():
            w.push(vectors=v, imu=np.zeros(6, np.float32))
    return ws


def test_decide_before_the_window_is_full_is_no_touch(tmp_path):
    m = load_models(tmp_path, "int8", N_PINS, LegConfig())
    d = decide(m, _windows(m, []), contact_seen=True, referenced=True, expected_mag_px=None,
               expected_motion_px=None, gait=None, gait_rule_weight=0.5)
    assert d.class_id == P.SURFACE_CLASSES.index("no-touch") and not d.contact
    assert d.slip_conf == 0.0 and d.pressure is None and d.measures == {}


def test_decide_with_the_rule_hard_soft_and_slippery(tmp_path):
    m = load_models(tmp_path, "int8", N_PINS, LegConfig())
    press = np.full((N_PINS, 2), 2.0, np.float32)                # |v| = 2.83 px, no motion
    ws = _windows(m, [press] * m.rule.T)
    kw = dict(contact_seen=True, referenced=True, gait=None, gait_rule_weight=0.5)
    hard = decide(m, ws, expected_mag_px=1.0, expected_motion_px=0.0, **kw)
    soft = decide(m, ws, expected_mag_px=100.0, expected_motion_px=0.0, **kw)
    wet = decide(m, ws, expected_mag_px=1.0, expected_motion_px=5.0, **kw)
    names = P.SURFACE_CLASSES
    assert (names[hard.class_id], names[soft.class_id], names[wet.class_id]) == \
        ("hard", "soft", "slippery")
    assert hard.contact and not hard.slip
    assert wet.slip and wet.slip_conf >= SLIP_THRESHOLD
    assert math.isclose(float(hard.probs.sum()), 1.0)
    assert hard.measures["magnitude_px"] == pytest.approx(math.hypot(2.0, 2.0), rel=1e-5)
    airborne = decide(m, ws, expected_mag_px=1.0, expected_motion_px=5.0,
                      **{**kw, "contact_seen": False})
    assert not airborne.contact and not airborne.slip
