"""Tests of the marker front end (device/pi/vision/extract.py) and the realism measures
(host/analysis/realism.py): synthetic frames with known answers, property tests on
degenerate frames, and checks against the real recordings when present."""

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
    to_gray,
)
from host.analysis.drag import measure_drag_displacement
from host.analysis.frames import nearest_neighbour_px
from host.analysis.glare import measure_glare
from host.analysis.realism import measure_static
from host.analysis.rings import fit_radial_layout

try:  # tests/ may or may not become a package
    from tests.realdata import read_video, real_data_dir
except ImportError:  # pragma: no cover
    from tests.realdata import read_video, real_data_dir


# --------------------------------------------------------------------------
# Synthetic TacTip-like frames
# --------------------------------------------------------------------------

DOME = (160.0, 120.0, 100.0)  # cx, cy, r in a 240x320 frame
RINGS = ((14.0, 12), (24.0, 12), (36.0, 24), (48.0, 24), (60.0, 24))
PHASE_DEG = 3.0
SYNTH_PARAMS = VisionParams(block=11, offset=14.0, blur_sigma_px=1.0, min_area_px=6,
                            max_area_px=100, roi_shrink=0.9)


def ring_layout(centre=DOME[:2], rings=RINGS, phase_deg=PHASE_DEG, centre_pin=True) -> np.ndarray:
    pts = [tuple(centre)] if centre_pin else []
    for r, n in rings:
        a = np.radians(phase_deg + np.arange(n) * 360.0 / n)
        pts += list(zip(centre[0] + r * np.cos(a), centre[1] + r * np.sin(a)))
    return np.asarray(pts, np.float64)


def render(pins: np.ndarray, h=240, w=320, dome=DOME, pin_sigma=1.4, pin_amp=120.0,
           inside=70.0, surround=250.0, glare=(), bgr=False) -> np.ndarray:
    """Dark dome in a bright surround, Gaussian pins, optional flat glare discs (x, y, radius)."""
    yy, xx = np.mgrid[:h, :w].astype(np.float64)
    cx, cy, r = dome
    img = np.where((xx - cx) ** 2 + (yy - cy) ** 2 <= r * r, inside, surround)
    for x, y in pins:
        x0, x1 = int(max(0, x - 6)), int(min(w, x + 7))
        y0, y1 = int(max(0, y - 6)), int(min(h, y + 7))
        sub = (xx[y0:y1, x0:x1] - x) ** 2 + (yy[y0:y1, x0:x1] - y) ** 2
        img[y0:y1, x0:x1] += pin_amp * np.exp(-0.5 * sub / pin_sigma**2)
    for gx, gy, gr in glare:
        img[(xx - gx) ** 2 + (yy - gy) ** 2 <= gr * gr] = 255.0
    g = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    return cv2.cvtColor(g, cv2.COLOR_GRAY2BGR) if bgr else g


def match(found: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Distance from each true point to the nearest found point."""
    if len(found) == 0:
        return np.full(len(truth), np.inf)
    d = np.sqrt(((truth[:, None, :] - found[None, :, :]) ** 2).sum(-1))
    return d.min(axis=1)


# --------------------------------------------------------------------------
# Parameters and small helpers
# --------------------------------------------------------------------------


@pytest.mark.parametrize(
    "field, value",
    [
        ("block", 10), ("block", 1), ("block", 11.0), ("block", True),
        ("offset", float("nan")), ("offset", 1e6),
        ("blur_sigma_px", -1.0),
        ("min_area_px", 0), ("max_area_px", 5),  # max < default min 10
        ("roi_shrink", 0.0), ("roi_shrink", float("inf")),
    ],
)
def test_params_reject_bad_value_and_name_it(field, value):
    with pytest.raises(ValueError) as err:
        VisionParams(**{field: value})
    msg = str(err.value)
    assert field in msg
    assert repr(value) in msg or str(value) in msg


def test_params_frozen_and_presets_valid():
    p = VisionParams()
    assert p == ROBOSKIN_PARAMS
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.block = 13  # type: ignore[misc]
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


def test_nearest_neighbour_px_known_grid():
    xy = np.array([[0, 0], [3, 0], [0, 4], [10, 10]], np.float32)
    np.testing.assert_allclose(nearest_neighbour_px(xy), [3.0, 3.0, 4.0, math.hypot(10, 6)], rtol=1e-6)
    assert nearest_neighbour_px(np.zeros((1, 2))).shape == (0,)


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


# --------------------------------------------------------------------------
# Realism measures on synthetic frames with known answers
# --------------------------------------------------------------------------


def test_measure_static_synthetic_counts_spacing_and_brightness():
    truth = ring_layout()
    frames = [render(truth) for _ in range(3)]
    m = measure_static(frames, SYNTH_PARAMS)
    assert m["faults"] == []
    assert m["pin_count_median"] == len(truth) and m["pin_count_iqr"] == 0
    expected_spacing = float(np.median(nearest_neighbour_px(truth)))
    assert m["pin_spacing_px_median"] == pytest.approx(expected_spacing, abs=0.3)
    assert m["pin_sigma_px"] == pytest.approx(1.4, abs=0.35)
    assert m["pin_background_gray_median"] == pytest.approx(70, abs=6)
    assert m["pin_peak_gray_median"] == pytest.approx(190, abs=10)
    assert m["glare_count_median"] == 0 and m["glare_area_px2_median"] == 0
    assert m["dome_r_px"] == pytest.approx(DOME[2], abs=3)


def test_measure_static_no_dome_gives_finite_and_fault():
    m = measure_static([np.zeros((40, 50), np.uint8)] * 2, SYNTH_PARAMS)
    assert m["pin_count_median"] == 0
    assert any("dome" in f for f in m["faults"]) and any("pins" in f for f in m["faults"])
    assert all(math.isfinite(v) for v in m.values() if isinstance(v, float))


def test_measure_drag_displacement_known_shift():
    truth = ring_layout()
    # pins slide 0..9 px along +x (1.5 px per frame), hold, then spring back at once
    shifts = [0.0, 1.5, 3.0, 4.5, 6.0, 7.5, 9.0, 9.0, 9.0, 0.0, 0.0]
    frames = [render(truth + [s, 0.0]) for s in shifts]
    m = measure_drag_displacement(frames, SYNTH_PARAMS, dome=DOME)
    per = np.asarray(m["displacement_px_per_frame"])
    np.testing.assert_allclose(per, shifts, atol=0.3)
    assert m["displacement_px_max"] == pytest.approx(9.0, abs=0.3)
    assert m["displacement_vector_px_at_max"][0] == pytest.approx(9.0, abs=0.3)
    assert abs(m["displacement_vector_px_at_max"][1]) < 0.3
    assert m["tracked_fraction_median"] > 0.9


def test_measure_glare_finds_soft_blob():
    truth = ring_layout(rings=((14.0, 12), (24.0, 12)))
    g = render(truth).astype(np.float64)
    yy, xx = np.mgrid[: g.shape[0], : g.shape[1]]
    gx, gy, sig = DOME[0] + 55.0, DOME[1] - 20.0, 10.0
    g += 120.0 * np.exp(-0.5 * ((xx - gx) ** 2 + (yy - gy) ** 2) / sig**2)
    frame = np.clip(g, 0, 255).astype(np.uint8)
    res = measure_glare([frame], dome=DOME, pin_diameter_px=4.0)
    blobs = res["blobs_first_frame"]
    assert len(blobs) == 1
    b = blobs[0]
    assert abs(b["x_px"] - gx) <= 2 and abs(b["y_px"] - gy) <= 2
    assert b["amplitude_gray"] == pytest.approx(120, abs=20)
    # half-amplitude area of a Gaussian: 2 pi ln2 sigma^2
    assert b["half_amplitude_area_px2"] == pytest.approx(2 * math.pi * math.log(2) * sig**2, rel=0.25)
    assert b["sigma_px"] == pytest.approx(sig, rel=0.3)


def test_fit_radial_layout_recovers_rings():
    truth = ring_layout()
    rng = np.random.default_rng(1)
    noisy = truth + rng.normal(0, 0.3, truth.shape)
    fit = fit_radial_layout(noisy, centre_guess=(DOME[0] + 4, DOME[1] - 3))
    assert fit["centre_x_px"] == pytest.approx(DOME[0], abs=0.3)
    assert fit["centre_y_px"] == pytest.approx(DOME[1], abs=0.3)
    assert fit["centre_pin"] is True
    assert [r["count"] for r in fit["rings"]] == [n for _, n in RINGS]
    np.testing.assert_allclose([r["radius_px"] for r in fit["rings"]], [r for r, _ in RINGS], atol=0.3)
    for ring in fit["rings"]:
        assert ring["phase_deg"] == pytest.approx(PHASE_DEG, abs=1.0)
    assert fit["total_pins"] == len(truth)


# --------------------------------------------------------------------------
# Property tests: degenerate frames never break the front end
# --------------------------------------------------------------------------

_KINDS = ("black", "white", "saturated", "noise")


@st.composite
def degenerate_frames(draw):
    h = draw(st.integers(1, 96))
    w = draw(st.integers(1, 128))
    kind = draw(st.sampled_from(_KINDS))
    colour = draw(st.booleans())
    shape = (h, w, 3) if colour else (h, w)
    if kind == "black":
        f = np.zeros(shape, np.uint8)
    elif kind == "white":
        f = np.full(shape, 255, np.uint8)
    elif kind == "saturated":
        level = draw(st.integers(0, 255))
        f = np.full(shape, level, np.uint8)
        if colour:
            f[:, :, draw(st.integers(0, 2))] = 255  # one clipped channel
    else:
        seed = draw(st.integers(0, 2**32 - 1))
        f = np.random.default_rng(seed).integers(0, 256, shape, dtype=np.uint8)
    return kind, f


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
def test_detector_and_measures_finite_on_degenerate_frames(case):
    _, frame = case
    dome = find_dome(frame)
    det = PinDetector(ROBOSKIN_PARAMS, frame.shape[:2], dome)
    xy, areas = det.detect(frame)
    assert np.isfinite(xy).all() and xy.shape == (len(areas), 2)
    m = measure_static([frame], ROBOSKIN_PARAMS, dome=dome)
    assert all(math.isfinite(v) for v in m.values() if isinstance(v, float))


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
def test_real_roboskin_rest_pins_and_layout():
    root = real_data_dir("roboskin/smooth.avi")
    frames = read_video(root / "roboskin" / "smooth.avi", count=12)  # at rest
    m = measure_static(frames, ROBOSKIN_PARAMS)
    assert m["faults"] == []
    assert 120 <= m["pin_count_median"] <= 145
    assert 10.5 <= m["pin_spacing_px_median"] <= 13.0
    assert 5.5 <= m["pin_diameter_px_median"] <= 7.5
    assert m["pin_contrast_gray_median"] > 40
    gray = np.mean([to_gray(f).astype(np.float32) for f in frames], axis=0).astype(np.uint8)
    dome = (m["dome_cx_px"], m["dome_cy_px"], m["dome_r_px"])
    xy, _ = PinDetector(ROBOSKIN_PARAMS, gray.shape, dome).detect(gray)
    fit = fit_radial_layout(xy, centre_guess=dome[:2])
    assert fit["total_pins"] == 133  # the sensor's 133 pins
    assert fit["centre_pin"] is True
    assert [r["count"] for r in fit["rings"]] == [12, 12, 12, 24, 24, 24, 24]
    np.testing.assert_allclose([r["radius_px"] for r in fit["rings"]],
                               [20.9, 30.7, 44.1, 57.0, 70.0, 82.6, 93.8], atol=1.5)


@pytest.mark.real
def test_real_north_push_displacement():
    root = real_data_dir("roboskin/north.avi")
    frames = read_video(root / "roboskin" / "north.avi", count=150)
    m = measure_drag_displacement(frames, ROBOSKIN_PARAMS)
    per = np.asarray(m["displacement_px_per_frame"])
    assert per[:30].max() < 1.0          # at rest before the push
    assert m["displacement_px_p90"] > 6  # the push moves pins by about a pin spacing
    assert m["displacement_px_max"] < 25
    assert m["tracked_fraction_median"] > 0.6


@pytest.mark.real
def test_real_tactip_shear_image_1():
    root = real_data_dir("tactip_shear/images/image_1.png")
    g = cv2.imread(str(root / "tactip_shear" / "images" / "image_1.png"), cv2.IMREAD_GRAYSCALE)
    d = find_dome(g)
    assert d is not None
    assert 195 <= d[2] <= 225
    assert abs(d[0] - g.shape[1] / 2) < 15 and abs(d[1] - g.shape[0] / 2) < 15
    m = measure_static([g], TACTIP_SHEAR_PARAMS, dome=d)
    assert abs(m["pin_count_median"] - 331) <= 3
    assert 11.0 <= m["pin_diameter_px_median"] <= 14.5
    assert 17.0 <= m["pin_spacing_px_median"] <= 21.0
