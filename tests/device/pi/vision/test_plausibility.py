"""The per-frame plausibility check (device/pi/vision/plausibility.py), from simulated
frames with a reference set: garbage frames (black, white, salt, random, NaN/inf
floats, uint16 beyond 255, bool) get the frame fault, no contact and no tracked pin;
mild noise, glare and a few lost pins do not, and their numbers stay finite."""
from __future__ import annotations

import cv2
import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from device.pi.faults import FAULT_FRAME
from device.pi.vision.pipeline import MarkerStream
from device.pi.vision.plausibility import FramePlausibility, FrameStats
from tests.simframes import N_FRAMES, finite_features, garbage, referenced, sim_stream

GARBAGE = ("black", "white", "salt", "random", "nan", "inf", "uint16", "bool")


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(kind=st.sampled_from(GARBAGE), i=st.integers(8, N_FRAMES - 1), seed=st.integers(0, 2**31))
def test_garbage_after_the_reference_is_a_frame_fault_with_no_contact(kind, i, seed):
    s, frames = referenced()
    ff = s.process(garbage(kind, frames[i], np.random.default_rng(seed)))
    finite_features(ff)
    assert ff.faults & FAULT_FRAME, (kind, s.implausible)
    assert not ff.contact and s.implausible
    assert ff.lost.all() and not ff.vectors.any() and ff.magnitude_sum == 0.0
    # the next genuine frame is judged as if the garbage had not been there
    s2, _ = referenced()
    for k in range(8, i):
        s2.process(frames[k])
    s2.process(garbage(kind, frames[i], np.random.default_rng(seed)))
    nxt = s2.process(frames[i])
    assert not nxt.faults & FAULT_FRAME and s2.implausible == ""
    assert np.array_equal(s2.reference, sim_stream()[1].reference)      # the reference is kept
    assert nxt.lost.mean() < 0.5                                   # and tracking goes on


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(i=st.integers(4, N_FRAMES - 1), sigma=st.floats(0.0, 4.0),
       glare=st.integers(0, 2), lost=st.integers(0, 5), seed=st.integers(0, 2**31))
def test_mild_noise_glare_and_lost_pins_are_no_frame_fault(i, sigma, glare, lost, seed):
    s, frames = referenced()
    rng = np.random.default_rng(seed)
    f = frames[i].astype(np.float32)
    f += rng.normal(0.0, sigma, f.shape).astype(np.float32)
    cx, cy, r = s.dome
    for _ in range(glare):                          # an LED reflection on the dome
        a, d = rng.uniform(0, 2 * np.pi), rng.uniform(0, 0.6 * r)
        cv2.circle(f, (int(cx + d * np.cos(a)), int(cy + d * np.sin(a))), 8, (255, 255, 255), -1)
    for p in s.reference[rng.choice(len(s.reference), lost, replace=False)]:
        cv2.circle(f, (int(p[0]), int(p[1])), 6, (60, 60, 60), -1)     # a pin painted out
    frame = np.clip(f, 0, 255).astype(np.uint8)
    ff = s.process(frame)
    finite_features(ff)
    assert not ff.faults & FAULT_FRAME, s.implausible
    assert s.implausible == ""
    assert ff.lost.mean() < 0.5                     # the pins are still tracked
    assert np.abs(ff.vectors).max() <= 4 * s.profile.pitch_px


def test_the_checks_fail_for_the_reason_they_name():
    ref = FrameStats(blobs=140, mean_gray=130.0, std_gray=44.0, corner_margin_gray=120.0)
    p = FramePlausibility(133)
    assert p.check(FrameStats(300, 0.0, 0.0, 0.0)) == ""          # no reference: blobs only
    assert p.check(FrameStats(333, 0.0, 0.0, 0.0)) == "blobs"     # > 2.5 x 133
    p.set_reference(ref)
    assert p.check(ref) == ""
    assert p.check(FrameStats(351, 130.0, 44.0, 120.0)) == "blobs"  # > 2.5 x 140
    assert p.check(FrameStats(350, 130.0, 44.0, 120.0)) == ""
    assert p.check(FrameStats(140, 181.0, 44.0, 120.0)) == "brightness"
    assert p.check(FrameStats(140, 79.0, 44.0, 120.0)) == "brightness"
    assert p.check(FrameStats(140, 180.0, 44.0, 120.0)) == ""
    assert p.check(FrameStats(140, 130.0, 21.0, 120.0)) == "contrast"
    assert p.check(FrameStats(140, 130.0, 89.0, 120.0)) == "contrast"
    assert p.check(FrameStats(140, 130.0, 22.0, 120.0)) == ""
    assert p.check(FrameStats(140, 130.0, 44.0, 41.0)) == "dome"    # < 0.35 x 120
    assert p.check(FrameStats(140, 130.0, 44.0, 43.0)) == ""
    p.set_reference(FrameStats(140, 130.0, 44.0, 39.0))             # corners not bright
    assert p.check(FrameStats(140, 130.0, 44.0, 0.0)) == ""
    p.clear()
    assert p.reference is None and p.check(FrameStats(140, 0.0, 0.0, 0.0)) == ""


def test_a_garbage_run_never_becomes_the_reference():
    frames, _ = sim_stream()
    s = MarkerStream("roboskin", warmup=3)
    rng = np.random.default_rng(0)
    salt = [garbage("salt", frames[0], rng) for _ in range(6)]
    for f in salt:
        ff = s.process(f)
        assert ff.faults & FAULT_FRAME and s.reference is None and not ff.contact
    for f in frames[:6]:
        s.process(f)
    assert s.reference is not None and 100 <= len(s.reference) <= 140
