"""The marker pipeline stream (device/pi/vision/pipeline.py): a steady pin count on the
real clips at rest, and hard cases that must stay finite with the right fault bits.
Its accuracy on simulated scenes and the real clips is measured in
tests/host/analysis/test_pipeline_eval.py."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from device.pi.faults import (FAULT_BAD_FRAME, FAULT_FRAME, FAULT_FRAME_SIZE_CHANGED,
                              FAULT_LOCALISER, FAULT_NO_DOME, FAULT_NO_REFERENCE, FAULT_TOO_FEW_PINS, fault_names)
from device.pi.vision.pipeline import MarkerStream
from tests.realdata import read_video, real_data_dir
from tests.simframes import referenced

# -- the real clips ------------------------------------------------------------------

@pytest.mark.parametrize("name,rest", [("smooth.avi", 16), ("concrete.avi", 14)])
def test_real_rest_pin_count_is_steady(name, rest):
    frames = read_video(real_data_dir(f"roboskin/{name}") / "roboskin" / name, count=rest)
    stream = MarkerStream("roboskin")
    counts = [len(stream.process(f).pins) for f in frames]
    c = np.array(counts, float)
    assert np.all(np.abs(c - c.mean()) <= 0.03 * c.mean()), counts


def _same_features(a, b):
    for k in ("pins", "vectors", "lost", "grid"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
    assert (a.faults, a.contact, a.shear_x, a.shear_y, a.magnitude_sum) == \
        (b.faults, b.contact, b.shear_x, b.shear_y, b.magnitude_sum)


@pytest.mark.real
def test_real_gray_and_bgr_frames_give_identical_features():
    """A gray source (a camera's luma plane, a file read with gray=True) gives the
    pipeline exactly what the colour frames give: the same pins, vectors, grid and
    faults on every frame of a real clip; its gray stage reads the frame in place."""
    frames = read_video(real_data_dir("roboskin/smooth.avi") / "roboskin" / "smooth.avi",
                        count=40)
    s_bgr, s_gray = MarkerStream("roboskin"), MarkerStream("roboskin")
    for i, f in enumerate(frames):
        a = s_bgr.process(f, i / 120.0)
        b = s_gray.process(cv2.cvtColor(f, cv2.COLOR_BGR2GRAY), i / 120.0)
        _same_features(a, b)
        # detection's timer, or the fused call's (device.pi.vision.frame)
        assert "gray" in b.timings_ms and ("detect" in b.timings_ms or "core" in b.timings_ms)
    assert s_gray.reference is not None and len(b.pins) > 100


def test_sim_gray_and_bgr_frames_give_identical_features():
    s_gray, frames = referenced()
    s_bgr, _ = referenced()
    for i, g in enumerate(frames[-6:]):
        a = s_gray.process(g, float(i))
        b = s_bgr.process(cv2.cvtColor(g, cv2.COLOR_GRAY2BGR), float(i))
        _same_features(a, b)
    assert len(a.pins) > 0 and len(a.vectors) > 0


# -- hard cases -------------------------------------------------------------------------

def _check_finite(out):
    for v in (out.shear_x, out.shear_y, out.magnitude, out.magnitude_sum):
        assert math.isfinite(v)
    assert np.isfinite(out.pins).all() and np.isfinite(out.vectors).all()
    assert np.isfinite(out.grid).all()
    line = out.summary()
    assert all(math.isfinite(v) for v in line.values() if isinstance(v, float))


@pytest.mark.parametrize("kind", ["black", "white", "saturated", "noise"])
def test_featureless_frames_raise_no_dome(kind):
    rng = np.random.default_rng(0)
    frame = {"black": np.zeros((480, 640), np.uint8),
             "white": np.full((480, 640), 255, np.uint8),
             "saturated": np.full((480, 640, 3), 255, np.uint8),
             "noise": rng.integers(0, 256, (480, 640), dtype=np.uint8)}[kind]
    s = MarkerStream("roboskin")
    for _ in range(3):
        out = s.process(frame)
        _check_finite(out)
        assert out.faults & FAULT_NO_DOME and not out.contact


def test_reference_not_set_then_set_then_rezero():
    from device.sim import Simulator, load_scene
    sim = Simulator(load_scene("no-touch"))
    s = MarkerStream("roboskin", warmup=5)
    faults = [s.process(sim.render(i)).faults for i in range(8)]
    assert all(f & FAULT_NO_REFERENCE for f in faults[:4])
    assert not faults[-1] & FAULT_NO_REFERENCE
    s.rezero()
    assert s.process(sim.render(9)).faults & FAULT_NO_REFERENCE


def test_frame_size_change_mid_stream():
    from dataclasses import replace

    from device.sim import Simulator, load_scene
    big = Simulator(load_scene("no-touch"))
    small = Simulator(replace(load_scene("no-touch"), width=320, height=240))
    s = MarkerStream("roboskin")
    for i in range(6):
        s.process(big.render(i))
    out = s.process(small.render(0))
    _check_finite(out)
    assert out.faults & FAULT_FRAME_SIZE_CHANGED and out.faults & FAULT_NO_REFERENCE
    out = s.process(small.render(1))
    assert not out.faults & FAULT_FRAME_SIZE_CHANGED


def test_one_pin_and_merged_pins_give_too_few_pins():
    frame = np.full((480, 640), 240, np.uint8)
    cv2.circle(frame, (320, 240), 140, 90, -1)             # a dark dome
    s = MarkerStream("roboskin")
    one = frame.copy()
    cv2.circle(one, (320, 240), 3, 220, -1)                 # a single pin
    merged = frame.copy()
    cv2.circle(merged, (320, 240), 30, 220, -1)             # pins merged into one blob
    for f in (one, merged, one):
        out = s.process(f)
        _check_finite(out)
        assert out.faults & FAULT_TOO_FEW_PINS
    assert "too_few_pins" in fault_names(out.faults)


@pytest.mark.parametrize("bad", [None, np.zeros((0, 0)), np.zeros((3, 3)), "frame",
                                 np.full((10, 10), np.nan), np.zeros((5, 5, 5, 5))])
def test_bad_frames_are_flagged_not_raised(bad):
    out = MarkerStream("roboskin").process(bad)
    _check_finite(out)
    assert out.faults & FAULT_BAD_FRAME or out.faults & FAULT_NO_DOME


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(h=st.integers(8, 200), w=st.integers(8, 200), seed=st.integers(0, 2**31),
       level=st.integers(0, 255), mode=st.sampled_from(["noise", "flat", "dome", "stripes"]),
       with_reference=st.booleans())
def test_any_frame_sequence_stays_finite(h, w, seed, level, mode, with_reference):
    """From a fresh stream, or one whose reference was set on simulated frames: any
    frames give finite numbers, and a frame fault never comes with contact."""
    rng = np.random.default_rng(seed)
    if with_reference:
        s, sim_frames = referenced()
        assert s.reference is not None
        h, w = (sim_frames[0].shape[:2] if mode != "dome" else (h, w))
    else:
        s = MarkerStream("roboskin", warmup=2)
    for k in range(4):
        if mode == "noise":
            f = rng.integers(0, 256, (h, w), dtype=np.uint8)
        elif mode == "flat":
            f = np.full((h, w), level, np.uint8)
        elif mode == "stripes":
            f = np.zeros((h, w), np.uint8)
            f[:, ::4] = 255
        else:
            f = np.full((h, w), 240, np.uint8)
            cv2.circle(f, (w // 2, h // 2), min(h, w) // 3, 80, -1)
            for _ in range(20):
                cv2.circle(f, (int(rng.integers(0, w)), int(rng.integers(0, h))), 2, 220, -1)
        out = s.process(f, t_s=float(k) if k != 2 else float("nan"))
        _check_finite(out)
        assert not (out.faults & FAULT_FRAME and out.contact)
        if with_reference and mode in ("noise", "flat", "stripes") and k == 0:
            assert out.faults & FAULT_FRAME and not out.contact      # garbage on the sensor


class SpyLocaliser:
    """A fixed-count localiser stand-in: counts its calls, reports a bad fit on
    every other one."""

    def __init__(self, n_pins=5):
        self.calls = 0
        self.n_pins = n_pins

    def locate(self, binary, dome, box=None):
        self.calls += 1
        return np.zeros((self.n_pins, 2), np.float32), self.calls % 2 == 0


def test_localiser_runs_on_every_frame_when_given_and_raises_its_fault():
    from device.sim import Simulator, load_scene
    sim = Simulator(load_scene("no-touch"))
    loc = SpyLocaliser()
    s = MarkerStream("roboskin", localiser=loc)
    outs = [s.process(sim.render(i)) for i in range(4)]
    assert loc.calls == 4
    assert all(o.localised is not None and o.localised.shape == (5, 2) for o in outs)
    assert [bool(o.faults & FAULT_LOCALISER) for o in outs] == [False, True, False, True]
    plain = MarkerStream("roboskin").process(sim.render(0))
    assert plain.localised is None and not plain.faults & FAULT_LOCALISER


# -- exposure: the offset scaled by the dome's contrast ([vision] contrast_ref) --------

def _synth_profile(contrast_ref=None):
    from device.profile import parse_pipeline_profile
    from tests.domes import DOME, ring_layout
    v = {"block": 11, "offset": 14.0, "min_area_px": 6, "max_area_px": 100,
         "roi_shrink": 0.9, "pitch_px": 10.0, "n_pins": len(ring_layout()),
         "dome_px": list(DOME)}
    if contrast_ref is not None:
        v["contrast_ref"] = contrast_ref
    return parse_pipeline_profile({"vision": v}, source="synth.toml")


def _synth_frames(gain):
    """A still synthetic dome (faint pins) at exposure ``gain``, and the calibration
    contrast of the same dome at gain 1."""
    from tests.domes import render, ring_layout
    f = render(ring_layout(), pin_amp=60.0).astype(np.float64)
    s = MarkerStream(_synth_profile())
    s.process(f.astype(np.uint8))
    return np.clip(np.rint(gain * f), 0, 255).astype(np.uint8), s.detector.local_contrast()


def test_a_darker_exposure_keeps_its_pins_with_contrast_ref():
    """At 0.6 of the calibration's exposure the fixed offset finds under half of the
    pins (too few to take a reference); scaled by the contrast it finds them all,
    takes its reference, and the still frames after it read as rest."""
    dim, c_ref = _synth_frames(0.6)
    fixed, scaled = MarkerStream(_synth_profile()), MarkerStream(_synth_profile(c_ref))
    for i in range(8):
        a, b = fixed.process(dim, float(i)), scaled.process(dim, float(i))
    n = len(scaled.reference)
    assert len(a.pins) < 0.5 * n <= n and a.faults & FAULT_TOO_FEW_PINS
    assert fixed.reference is None
    assert len(b.pins) == n == _synth_profile().n_pins and not b.faults
    assert scaled.offset_scale == pytest.approx(0.6, abs=0.03)
    assert scaled.detector.offset == pytest.approx(14.0 * scaled.offset_scale)
    assert not b.contact and not b.lost.any() and np.abs(b.vectors).max() < 0.05
    # the calibration's own exposure is not scaled: the fixed offset's pins exactly
    same, _ = _synth_frames(1.0)
    s1, s0 = MarkerStream(_synth_profile(c_ref)), MarkerStream(_synth_profile())
    for i in range(6):
        x, y = s1.process(same, float(i)), s0.process(same, float(i))
    assert s1.offset_scale == 1.0 and np.array_equal(x.pins, y.pins)


def test_the_contrast_is_measured_once_per_reference_search_not_per_frame(monkeypatch):
    """One measurement when the reference search begins, none on the frames after the
    reference (their cost is unchanged), one more after rezero; and none at all without
    contrast_ref."""
    dim, c_ref = _synth_frames(0.7)
    for ref, want in ((c_ref, [1, 2]), (None, [0, 0])):
        s = MarkerStream(_synth_profile(ref))
        s.process(dim)
        calls = []
        real = s.detector.local_contrast
        monkeypatch.setattr(s.detector, "local_contrast", lambda: calls.append(1) or real())
        s.rezero()
        for i in range(20):
            s.process(dim, float(i))
        got = [len(calls)]
        s.rezero()
        for i in range(20):
            s.process(dim, float(i))
        got.append(len(calls))
        assert got == want and s.reference is not None


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 255), st.integers(0, 3))
def test_a_flat_black_or_white_reference_frame_leaves_the_offset_unscaled(level, n_flat):
    """A flat frame (black, white or any gray) has no contrast to compare: whether or
    not it passes as a frame, the offset is not scaled from it, every number is
    finite, and a real (dim) dome after it still gets its scale."""
    dim, c_ref = _synth_frames(0.6)
    s = MarkerStream(_synth_profile(c_ref))
    flat = np.full(dim.shape, level, np.uint8)
    for i in range(n_flat + 1):
        out = s.process(flat, float(i))
        _check_finite(out)
        assert s.offset_scale == 1.0 and s.detector.offset == 14.0
        assert not out.contact
    for i in range(8):
        out = s.process(dim, float(i))
        _check_finite(out)
    assert s.offset_scale == pytest.approx(0.6, abs=0.03) and s.reference is not None


def test_fuse_off_times_every_stage_and_changes_nothing():
    """``fuse = False`` (host.bench.scaling) runs the stages apart: the same
    features as the fused call, with a timer for each stage instead of 'core'."""
    from device.pi.vision import native
    fused, frames = referenced()
    apart, _ = referenced()
    apart.fuse = False
    for i, g in enumerate(frames[-6:]):
        a, b = fused.process(g, float(i)), apart.process(g, float(i))
        _same_features(a, b)
        assert "core" not in b.timings_ms and {"detect", "track", "grid"} <= set(b.timings_ms)
        if native.frame_fn() is not None:
            assert "core" in a.timings_ms
