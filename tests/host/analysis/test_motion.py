"""Pin motion per window and per class (host/analysis/motion.py): known motions give
their figures back, and hard cases stay finite."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from host.analysis.motion import MOTION_FIGURES, motion_by_class, window_motion
from host.data.windows import WindowSet


def windows(step_px, shake_px, lost_pins=0, n=20, M=30, seed=0):
    """n windows of T=3: every pin displaced by 2 px along x, then moved by
    ``step_px`` along y per frame, plus a per-pin shake of ``shake_px``."""
    rng = np.random.default_rng(seed)
    v = np.zeros((n, 3, M, 2), np.float32)
    v[..., 0] = 2.0
    for t in range(3):
        v[:, t, :, 1] = step_px * t
    v += shake_px * rng.standard_normal(v.shape).astype(np.float32)
    lost = np.zeros((n, 3, M), bool)
    lost[:, :, :lost_pins] = True
    v[lost] = 0.0
    return v, lost


def test_common_motion_and_jitter_come_back():
    v, lost = windows(step_px=1.5, shake_px=0.0)
    m = window_motion(v, lost)
    np.testing.assert_allclose(m["common_px"], 1.5, atol=1e-5)
    np.testing.assert_allclose(m["jitter_px"], 0.0, atol=1e-5)
    np.testing.assert_allclose(m["displacement_px"], math.hypot(2.0, 3.0), atol=1e-5)
    v, lost = windows(step_px=0.0, shake_px=0.5, lost_pins=6)
    m = window_motion(v, lost)
    # the difference of two N(0, 0.5^2) shakes has a mean length 0.5 sqrt(pi)
    assert np.median(m["jitter_px"]) == pytest.approx(0.5 * math.sqrt(math.pi), rel=0.15)
    assert np.median(m["common_px"]) < 0.25      # 24 shaking pins average out
    np.testing.assert_allclose(m["lost_share"], 6 / 30)


def test_lost_pins_are_left_out_not_read_as_zero_motion():
    v, lost = windows(step_px=1.0, shake_px=0.0, lost_pins=10)
    np.testing.assert_allclose(window_motion(v, lost)["common_px"], 1.0, atol=1e-5)


def test_motion_by_class_tells_a_shaking_class_from_a_still_one():
    a, la = windows(step_px=0.2, shake_px=0.6, seed=1)
    b, lb = windows(step_px=0.2, shake_px=0.05, seed=2)
    n = len(a)
    ws = WindowSet(task="texture", window=3, vectors=np.concatenate([a, b]),
                   lost=np.concatenate([la, lb]), imu=None, grids=None, frames=None,
                   contact=np.ones(2 * n, bool),
                   labels=np.array(["smooth"] * n + ["concrete"] * n, object), targets=None,
                   groups=np.repeat([0, 1], n), t_index=np.zeros(2 * n, np.int64),
                   trial_len=np.full(2 * n, 3, np.int64))
    res = motion_by_class(ws)
    assert set(res) == {"smooth", "concrete"}
    assert res["smooth"]["jitter_px_p50"] > 5 * res["concrete"]["jitter_px_p50"]
    assert res["smooth"]["windows"] == n and res["smooth"]["few_pins"] == 0
    assert all(f"{k}_p90" in res["concrete"] for k, _ in MOTION_FIGURES)


def test_bad_shapes_are_refused():
    with pytest.raises(ValueError, match="T>=2"):
        window_motion(np.zeros((4, 1, 5, 2)), np.zeros((4, 1, 5), bool))


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 5), st.sampled_from([0.0, 1e30, -1e30, float("nan"), float("inf")]))
def test_hard_cases_stay_finite(n_seen, value):
    v = np.full((3, 2, 5, 2), value, np.float64)
    lost = np.ones((3, 2, 5), bool)
    lost[:, :, :n_seen] = False
    m = window_motion(v, lost)
    assert all(np.isfinite(x).all() for x in m.values())
