"""The marker front end (device/pi/vision/extract.py): synthetic frames with known
answers, property tests on degenerate frames, and checks against the real recordings
when present."""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from device.pi.vision.extract import (
    ROBOSKIN_PARAMS,
    TACTIP_SHEAR_PARAMS,
    PinDetector,
    VisionParams,
    binarise,
    components,
    dome_mask,
    extract_pins,
    find_dome,
    local_contrast,
    offset_scale,
    to_gray,
)
from tests.domes import DOME, SYNTH_PARAMS, degenerate_frames, match, render, ring_layout
from tests.realdata import read_video, real_data_dir


# --------------------------------------------------------------------------
# Parameters and grey conversion
# --------------------------------------------------------------------------


def test_presets_are_valid_params():
    assert VisionParams() == ROBOSKIN_PARAMS
    assert TACTIP_SHEAR_PARAMS.min_area_px > ROBOSKIN_PARAMS.min_area_px


def test_to_gray_accepts_gray_bgr_and_float():
    rng = np.random.default_rng(0)
    bgr = rng.integers(0, 256, (7, 9, 3), dtype=np.uint8)
    np.testing.assert_array_equal(to_gray(bgr), cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))
    g = bgr[:, :, 1].copy()
    np.testing.assert_array_equal(to_gray(g), g)
    np.testing.assert_array_equal(to_gray(g[:, :, None]), g)
    out = np.empty((7, 9), np.uint8)
    assert to_gray(bgr, out=out) is out
    f = np.array([[-5.0, 300.0], [np.nan, 12.4]])
    np.testing.assert_array_equal(to_gray(f), np.array([[0, 255], [0, 12]], np.uint8))
    with pytest.raises(ValueError, match="shape"):
        to_gray(np.zeros((4, 4, 2), np.uint8))


# --------------------------------------------------------------------------
# Dome, threshold, blobs on synthetic frames
# --------------------------------------------------------------------------


@pytest.mark.parametrize("bgr", [False, True])
def test_find_dome_on_synthetic_view(bgr):
    frame = render(ring_layout(), bgr=bgr)
    d = find_dome(frame)
    assert d is not None
    cx, cy, r = d
    assert abs(cx - DOME[0]) < 1.5 and abs(cy - DOME[1]) < 1.5
    assert abs(r - DOME[2]) < 3.0


def test_find_dome_on_binarised_pin_disc():
    # white pins on black filling a disc, like tactip_shear
    g = np.zeros((300, 310), np.uint8)
    c, R = (150.0, 152.0), 120.0
    for y in np.arange(c[1] - R, c[1] + R + 1, 16.0):
        for x in np.arange(c[0] - R, c[0] + R + 1, 16.0):
            if (x - c[0]) ** 2 + (y - c[1]) ** 2 <= (R - 5) ** 2:
                cv2.circle(g, (int(x), int(y)), 5, 255, -1)
    d = find_dome(g)
    assert d is not None
    assert abs(d[0] - c[0]) < 4 and abs(d[1] - c[1]) < 4
    assert R * 0.85 < d[2] < R * 1.1


def test_binarise_respects_mask_and_reuses_buffer():
    frame = render(ring_layout())
    mask = dome_mask(frame.shape, DOME, 0.5)
    out = np.full(frame.shape, 7, np.uint8)
    b = binarise(frame, 11, 14.0, mask, out=out)
    assert b is out
    assert set(np.unique(b)) <= {0, 255}
    assert not b[mask == 0].any()
    assert b[mask > 0].any()
    with pytest.raises(ValueError, match="block"):
        binarise(frame, 10, 14.0, mask)
    with pytest.raises(ValueError, match="roi_mask"):
        binarise(frame, 11, 14.0, mask[:-1])


def test_extract_pins_area_filter_and_centroids():
    b = np.zeros((60, 80), np.uint8)
    b[5, 5] = 255                                 # 1 px noise
    cv2.circle(b, (30, 20), 3, 255, -1)           # pin, 29 px
    cv2.rectangle(b, (50, 30), (75, 55), 255, -1)  # glare, 26*26 px
    xy, areas = extract_pins(b, 6, 100)
    assert xy.shape == (1, 2) and xy.dtype == np.float32
    np.testing.assert_allclose(xy[0], [30.0, 20.0], atol=1e-4)
    assert areas.tolist() == [int(np.count_nonzero(b[14:27, 24:37]))]
    all_xy, all_areas = components(b)
    assert sorted(all_areas.tolist()) == [1, areas[0], 26 * 26]
    with pytest.raises(ValueError, match="max_area"):
        extract_pins(b, 10, 5)


def test_extract_pins_zero_pins():
    xy, areas = extract_pins(np.zeros((20, 30), np.uint8), 5, 50)
    assert xy.shape == (0, 2) and xy.dtype == np.float32 and areas.shape == (0,)


def test_detector_finds_every_synthetic_pin_and_drops_glare():
    truth = ring_layout()
    glare = [(DOME[0] + 80.0, DOME[1], 7.0)]  # flat saturated disc outside the pin rings
    frame = render(truth, glare=glare)
    det = PinDetector(SYNTH_PARAMS, frame.shape, find_dome(frame))
    xy, areas = det.detect(frame)
    assert len(xy) == len(truth)
    assert match(xy, truth).max() < 0.5
    assert np.all((areas >= SYNTH_PARAMS.min_area_px) & (areas <= SYNTH_PARAMS.max_area_px))
    # the glare disc produced a blob that was dropped for being too big
    gxy, gareas = det.detect_all(frame)
    big = gareas > SYNTH_PARAMS.max_area_px
    assert big.any()
    assert np.hypot(*(gxy[big] - glare[0][:2]).T).min() < 3.0


def test_detector_crop_matches_full_frame_pipeline():
    frame = render(ring_layout(), bgr=True)
    dome = find_dome(frame)
    p = SYNTH_PARAMS
    det = PinDetector(p, frame.shape[:2], dome)
    xy_crop, _ = det.detect(frame)
    g = cv2.GaussianBlur(to_gray(frame), det.blur_ksize, p.blur_sigma_px)
    b = binarise(g, p.block, p.offset, dome_mask(g.shape, dome, p.roi_shrink))
    xy_full, _ = extract_pins(b, p.min_area_px, p.max_area_px)
    assert len(xy_crop) == len(xy_full)
    assert match(xy_crop, xy_full.astype(np.float64)).max() < 1e-3
    with pytest.raises(ValueError, match="frame shape"):
        det.detect(frame[:-1])


@pytest.mark.parametrize("dx, dy", [(0, 0), (1, 0), (0, 1), (1, 1)])
def test_detector_odd_and_even_crops_find_the_same_pins(dx, dy):
    """The dome box's sides are odd or even with the dome's centre; the labelling's
    padded buffer must not change what is found, and ``binary`` stays the box."""
    frame = render(ring_layout())
    dome = find_dome(frame)
    p = SYNTH_PARAMS
    det = PinDetector(p, frame.shape, (dome[0] + 0.5 * dx, dome[1] + 0.5 * dy, dome[2] + 0.5 * dx))
    xy, areas = det.detect(frame)
    x0, y0, x1, y1 = det.box
    assert det.binary.shape == (y1 - y0, x1 - x0)
    ref_xy, ref_areas = extract_pins(np.ascontiguousarray(det.binary), p.min_area_px,
                                     p.max_area_px)
    assert len(xy) == len(ring_layout())
    np.testing.assert_array_equal(xy, ref_xy + np.float32([x0, y0]))
    np.testing.assert_array_equal(areas, ref_areas)


def _reference_detect(frame, p, dome):
    """The detector's answer the long way: gray, blur and cv2.adaptiveThreshold on the
    whole dome box, AND the dome mask, label the whole box."""
    det = PinDetector(p, frame.shape[:2], dome)
    x0, y0, x1, y1 = det.box
    g = np.ascontiguousarray(to_gray(frame)[y0:y1, x0:x1])
    if p.blur_sigma_px > 0:
        g = cv2.GaussianBlur(g, det.blur_ksize, p.blur_sigma_px)
    mask = np.ascontiguousarray(dome_mask(frame.shape[:2], dome, p.roi_shrink)[y0:y1, x0:x1])
    b = cv2.adaptiveThreshold(g, 255, cv2.ADAPTIVE_THRESH_MEAN_C, cv2.THRESH_BINARY, p.block,
                              -p.offset)
    b &= mask
    xy, areas = components(b)
    return b, xy + np.float32([x0, y0]), areas


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**31), block=st.sampled_from([3, 5, 11, 31]),
       offset=st.floats(-6.0, 40.0), sigma=st.sampled_from([0.0, 0.7, 1.0, 2.0]),
       cx=st.floats(-20.0, 340.0), cy=st.floats(-20.0, 260.0), r=st.floats(3.0, 200.0),
       shrink=st.sampled_from([0.5, 0.75, 1.0, 1.3]), colour=st.booleans())
def test_detector_is_bit_identical_to_adaptive_threshold_on_the_whole_box(
        seed, block, offset, sigma, cx, cy, r, shrink, colour):
    """The detector thresholds and labels only the dome's pixels (box filter, saturating
    subtraction under the mask, one threshold; labels on the even-aligned core): the
    binary box, the pins, their order, their float32 centroids and areas are exactly
    cv2.adaptiveThreshold's on the whole box, for any offset (fractional, negative),
    block, blur and any dome, on or off the frame's edge."""
    rng = np.random.default_rng(seed)
    frame = render(ring_layout(), bgr=colour).astype(np.int16)
    frame = np.clip(frame + rng.integers(-25, 26, frame.shape), 0, 255).astype(np.uint8)
    p = VisionParams(block=block, offset=offset, blur_sigma_px=sigma, min_area_px=1,
                     max_area_px=10_000, roi_shrink=shrink)
    dome = (cx, cy, r)
    det = PinDetector(p, frame.shape[:2], dome)
    ref_b, ref_xy, ref_areas = _reference_detect(frame, p, dome)
    xy, areas = det.detect(frame)
    np.testing.assert_array_equal(det.binary, ref_b)
    pin = (ref_areas >= p.min_area_px) & (ref_areas <= p.max_area_px)
    np.testing.assert_array_equal(xy, ref_xy[pin])
    np.testing.assert_array_equal(areas, ref_areas[pin])
    assert det.n_blobs == len(ref_areas)
    all_xy, all_areas = det.detect_all(frame)
    np.testing.assert_array_equal(all_xy, ref_xy)
    np.testing.assert_array_equal(all_areas, ref_areas)


def test_detector_gray_and_bgr_frames_give_the_same_pins():
    """A gray frame (a camera's luma plane, a file source read with gray=True) gives
    exactly the pins its colour original gives, and its dome box is read in place."""
    frame = render(ring_layout(), bgr=True)
    frame[:, :, 0] //= 2                                  # a real colour frame
    gray = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
    dome = find_dome(frame)
    det = PinDetector(SYNTH_PARAMS, frame.shape[:2], dome)
    xy_bgr, a_bgr = det.detect(frame)
    b_bgr = det.binary.copy()
    crop = det.gray_crop(gray)
    assert np.shares_memory(crop, gray)                   # no copy, no conversion
    xy_g, a_g = det.detect_gray(crop)
    assert len(xy_g) == len(ring_layout())
    np.testing.assert_array_equal(xy_g, xy_bgr)
    np.testing.assert_array_equal(a_g, a_bgr)
    np.testing.assert_array_equal(det.binary, b_bgr)
    with pytest.raises(ValueError, match="frame shape"):
        det.gray_crop(gray[:-1])


# --------------------------------------------------------------------------
# Property tests: degenerate frames never break the front end
# --------------------------------------------------------------------------

_SETTINGS = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@_SETTINGS
@given(degenerate_frames())
def test_find_dome_none_or_finite(case):
    kind, frame = case
    d = find_dome(frame)
    if kind != "noise":
        assert d is None  # a constant frame holds no dome
    if d is not None:
        assert len(d) == 3 and all(math.isfinite(v) for v in d)
        assert d[2] > 0


@_SETTINGS
@given(degenerate_frames(), st.sampled_from([3, 11, 31]), st.floats(0.0, 40.0))
def test_binarise_and_extract_never_raise(case, block, offset):
    kind, frame = case
    gray = to_gray(frame)
    h, w = gray.shape
    mask = dome_mask(gray.shape, (w / 2.0, h / 2.0, max(h, w) / 2.0), 1.0)
    b = binarise(gray, block, offset, mask)
    assert b.shape == gray.shape and b.dtype == np.uint8
    assert set(np.unique(b)) <= {0, 255}
    xy, areas = extract_pins(b, 3, 200)
    assert xy.ndim == 2 and xy.shape[1] == 2 and xy.dtype == np.float32
    assert np.isfinite(xy).all() and len(areas) == len(xy)
    assert np.all((areas >= 3) & (areas <= 200))
    if kind != "noise" and not (kind == "saturated" and frame.ndim == 3):
        assert len(xy) == 0 and not b.any()  # uniform gray: nothing above its own mean


@_SETTINGS
@given(degenerate_frames())
def test_detector_finite_on_degenerate_frames(case):
    _, frame = case
    dome = find_dome(frame)
    det = PinDetector(ROBOSKIN_PARAMS, frame.shape[:2], dome)
    xy, areas = det.detect(frame)
    assert np.isfinite(xy).all() and xy.shape == (len(areas), 2)


# --------------------------------------------------------------------------
# Real recordings (skipped when absent)
# --------------------------------------------------------------------------


@pytest.mark.real
@pytest.mark.parametrize(
    "name, centre, radius",
    [("smooth.avi", (325.8, 218.8), 144.8), ("concrete.avi", (325.7, 219.4), 141.6)],
)
def test_real_roboskin_dome(name, centre, radius):
    root = real_data_dir(f"roboskin/{name}")
    frame = read_video(root / "roboskin" / name, count=1)[0]
    d = find_dome(frame)
    assert d is not None
    assert abs(d[0] - centre[0]) < 3 and abs(d[1] - centre[1]) < 3
    assert abs(d[2] - radius) < 4


@pytest.mark.real
def test_real_flat_skin_has_no_dome():
    root = real_data_dir("roboskin/flatSkin.avi")
    frame = read_video(root / "roboskin" / "flatSkin.avi", count=1)[0]
    assert find_dome(frame) is None


@pytest.mark.real
def test_real_tactip_shear_image_1():
    root = real_data_dir("tactip_shear/images/image_1.png")
    g = cv2.imread(str(root / "tactip_shear" / "images" / "image_1.png"), cv2.IMREAD_GRAYSCALE)
    d = find_dome(g)
    assert d is not None
    assert 195 <= d[2] <= 225
    assert abs(d[0] - g.shape[1] / 2) < 15 and abs(d[1] - g.shape[0] / 2) < 15


# --------------------------------------------------------------------------
# Exposure: the dome's local contrast and the offset's scale
# --------------------------------------------------------------------------


def test_local_contrast_follows_the_exposure_gain():
    """The pins' height above their surround: a gain of 0.6 on the frame gives 0.6
    of the contrast (within a few %), and the mask chooses the pixels measured."""
    f = render(ring_layout(), pin_amp=60.0).astype(np.float64)
    mask = dome_mask(f.shape, DOME, 0.9)
    c1 = local_contrast(np.clip(np.rint(f), 0, 255).astype(np.uint8), mask, 11)
    c06 = local_contrast(np.clip(np.rint(0.6 * f), 0, 255).astype(np.uint8), mask, 11)
    assert 10.0 < c1 < 40.0
    assert c06 / c1 == pytest.approx(0.6, abs=0.03)
    assert local_contrast(np.zeros((40, 50), np.uint8), None, 11) == 0.0
    assert local_contrast(np.full((40, 50), 255, np.uint8), None, 11) == 0.0
    assert local_contrast(f.astype(np.uint8), np.zeros(f.shape, np.uint8), 11) == 0.0
    with pytest.raises(ValueError, match="mask"):
        local_contrast(f.astype(np.uint8), np.zeros((3, 3), np.uint8), 11)


@pytest.mark.parametrize("contrast, ref, want", [
    (24.0, 30.0, 0.8),           # darker: scaled
    (29.0, 30.0, 1.0),           # within 5 %: the same exposure, not scaled
    (36.0, 30.0, 1.0),           # brighter: never above 1
    (6.0, 30.0, 0.5),            # very dark: clamped
    (0.0, 30.0, 1.0),            # black / blank dome: no measure, not scaled
    (0.5, 30.0, 1.0),
    (float("nan"), 30.0, 1.0), (float("inf"), 30.0, 1.0),
    (24.0, None, 1.0),           # no contrast_ref: not scaled
    (None, 30.0, 1.0),
])
def test_offset_scale(contrast, ref, want):
    assert offset_scale(contrast, ref) == pytest.approx(want)


@given(st.one_of(st.none(), st.floats(allow_nan=True, allow_infinity=True)),
       st.one_of(st.none(), st.floats(allow_nan=True, allow_infinity=True)))
def test_offset_scale_is_always_a_finite_factor_between_half_and_one(contrast, ref):
    k = offset_scale(contrast, ref)
    assert math.isfinite(k) and 0.5 <= k <= 1.0


def test_set_offset_thresholds_as_a_detector_built_with_that_offset():
    """A detector whose offset is set later gives the pins (and binary) of one built
    with it, on the fast path (offset >= 0) and on cv2's (offset < 0)."""
    f = render(ring_layout(), pin_amp=60.0)
    for offset in (8.4, 14.0, -2.0):
        a = PinDetector(SYNTH_PARAMS, f.shape, DOME)
        a.set_offset(offset)
        b = PinDetector(dataclasses.replace(SYNTH_PARAMS, offset=offset), f.shape, DOME)
        xa, _ = a.detect(f)
        xb, _ = b.detect(f)
        assert np.array_equal(xa, xb) and np.array_equal(a.binary, b.binary)
        assert a.offset == offset
    fewer, _ = PinDetector(SYNTH_PARAMS, f.shape, DOME).detect(
        np.clip(0.6 * f, 0, 255).astype(np.uint8))
    det = PinDetector(SYNTH_PARAMS, f.shape, DOME)
    det.set_offset(0.6 * SYNTH_PARAMS.offset)
    more, _ = det.detect(np.clip(0.6 * f, 0, 255).astype(np.uint8))
    assert len(more) > len(fewer)
    with pytest.raises(ValueError, match="offset"):
        det.set_offset(float("nan"))
