"""The fixed-count pin localiser on the Pi (device/pi/models/localiser.py), run with the
shipped roboskin artefact: always N finite pins, the fault flag where it belongs and
no exception on hard inputs; its model input (an area resize of the zero-padded dome
square) and coordinates. Training it is tested in tests/host/localiser/."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from device.pi.models.localiser import (Localiser, crop_square, effective_dome,
                                        from_normalised, localiser_input, to_normalised)
from device.pi.runtime.load import default_models_dir
from device.pi.vision.extract import ROBOSKIN_PARAMS, PinDetector, find_dome
from device.sim import Simulator, load_scene

N_PINS = 133
SHIPPED = default_models_dir() / "localiser-roboskin"


@pytest.fixture(scope="module")
def loc() -> Localiser:
    if not (SHIPPED / "manifest.json").is_file():
        pytest.skip("no shipped localiser-roboskin model")
    return Localiser.load(SHIPPED)


# -- hard cases: always N finite pins, the fault flag where it belongs, no exception --


_DOME = (325.8, 218.8, 145.0)


_absurd_domes = st.sampled_from([
    None, (math.nan, 200.0, 140.0), (300.0, math.inf, 140.0), (300.0, 200.0, -5.0),
    (300.0, 200.0, 0.0), (300.0, 200.0, 1.0), (300.0, 200.0, 1e9), (1e12, -1e12, 140.0),
    (-5000.0, 200.0, 140.0), "dome", (1.0, 2.0), ("a", "b", "c"),
])


def _image(kind: str, h: int, w: int, p: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    if kind == "black":
        return np.zeros((h, w), np.uint8)
    if kind == "white":
        return np.full((h, w), 255, np.uint8)
    if kind == "noise":
        return ((rng.random((h, w)) < p) * 255).astype(np.uint8)
    if kind == "float_nan":
        a = rng.random((h, w)).astype(np.float32)
        a[a < 0.5] = np.nan
        return a
    return rng.integers(0, 256, (h, w), dtype=np.uint8)  # grey garbage


@settings(max_examples=60, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(kind=st.sampled_from(["black", "white", "noise", "grey", "float_nan"]),
       h=st.integers(1, 500), w=st.integers(1, 700), p=st.floats(0.3, 1.0),
       seed=st.integers(0, 10_000), use_box=st.booleans(),
       dome=st.one_of(_absurd_domes, st.tuples(st.floats(-1e4, 1e4), st.floats(-1e4, 1e4),
                                               st.floats(-10, 1e4))))
def test_hard_cases_give_n_finite_pins(loc, kind, h, w, p, seed, use_box, dome):
    img = _image(kind, h, w, p, seed)
    box = (100, 50, 100 + w, 50 + h) if use_box else None
    pins, fault = loc.locate(img, dome, box=box)
    assert pins.shape == (N_PINS, 2) and pins.dtype == np.float32
    assert np.isfinite(pins).all()
    # nothing here looks like a dome of pins: black has no pins, the others are
    # far denser than any training frame (or leave parts of the crop empty)
    assert fault, (kind, dome, loc.fault_reason)
    assert loc.fault_reason


@settings(max_examples=30, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(dome=_absurd_domes)
def test_no_dome_or_absurd_dome_sets_fault(loc, dome):
    sim = Simulator(load_scene("press-hard"), seed=3)
    det = PinDetector(ROBOSKIN_PARAMS, (sim.height, sim.width), _DOME)
    det.threshold(sim.render(5))
    pins, fault = loc.locate(det.binary, dome, box=det.box)
    assert fault and np.isfinite(pins).all() and pins.shape == (N_PINS, 2)
    # the fallback layout lies in the image region
    x0, y0, x1, y1 = det.box
    assert (pins[:, 0] >= x0).all() and (pins[:, 0] < x1).all()
    assert (pins[:, 1] >= y0).all() and (pins[:, 1] < y1).all()


@pytest.mark.parametrize("p", [0.3, 0.5, 0.9])
def test_dense_noise_over_the_dome_sets_fault(loc, p):
    """Noise where the dome should be: every crop cell is far too full."""
    rng = np.random.default_rng(int(p * 10))
    img = ((rng.random((480, 640)) < p) * 255).astype(np.uint8)
    pins, fault = loc.locate(img, _DOME)
    assert fault and "foreground fraction" in loc.fault_reason
    assert np.isfinite(pins).all()
    # the fallback is the mean layout in the dome
    assert np.hypot(*(pins.mean(0) - _DOME[:2])) < 10.0


@pytest.mark.parametrize("binary", [None, np.zeros((0, 5), np.uint8), np.zeros((4, 4, 3)),
                                    "frame", 3.0])
def test_unusable_binary_sets_fault(loc, binary):
    pins, fault = loc.locate(binary, _DOME)
    assert fault and pins.shape == (N_PINS, 2) and np.isfinite(pins).all()


def test_normal_frame_no_fault_and_dome_shift_equivariance(loc):
    """A frame and the same frame shifted by whole pixels (dome shifted too)
    give the same pins, shifted: the model does not care where the dome sits."""
    sim = Simulator(load_scene("press-hard"), seed=11)
    dome = find_dome(sim.render(0))
    det = PinDetector(ROBOSKIN_PARAMS, (sim.height, sim.width), dome)
    det.threshold(sim.render(sim.n_frames // 2))
    full = np.zeros((sim.height, sim.width), np.uint8)
    x0, y0, x1, y1 = det.box
    full[y0:y1, x0:x1] = det.binary
    a, fa = loc.locate(det.binary, dome, box=det.box)
    b, fb = loc.locate(full, dome)                      # whole-frame binary, same result
    dx, dy = 37, -21
    big = np.zeros((sim.height + 100, sim.width + 100), np.uint8)
    big[50 + dy:50 + dy + sim.height, 50 + dx:50 + dx + sim.width] = full
    c, fc = loc.locate(big, (dome[0] + 50 + dx, dome[1] + 50 + dy, dome[2]))
    assert not (fa or fb or fc)
    np.testing.assert_allclose(a, b, atol=1e-4)
    np.testing.assert_allclose(c - (50 + dx, 50 + dy), a, atol=1e-3)


def test_locate_writes_into_out(loc):
    out = np.empty((N_PINS, 2), np.float32)
    pins, _ = loc.locate(np.zeros((100, 100), np.uint8), (50.0, 50.0, 40.0), out=out)
    assert pins is out


# -- the model input and coordinates ------------------------------------------------

@settings(max_examples=80, deadline=None)
@given(h=st.integers(1, 200), w=st.integers(1, 200), size=st.integers(4, 40),
       cx=st.floats(-80, 280), cy=st.floats(-80, 280), r=st.floats(4, 200),
       factor=st.floats(0.3, 1.5), bx=st.integers(-30, 60), by=st.integers(-30, 60),
       use_box=st.booleans(), seed=st.integers(0, 1000))
def test_input_is_area_resize_of_zero_padded_square(h, w, size, cx, cy, r, factor, bx, by,
                                                    use_box, seed):
    rng = np.random.default_rng(seed)
    img = ((rng.random((h, w)) < rng.random()) * 255).astype(np.uint8)
    box = (bx, by, bx + w, by + h) if use_box else None
    x = localiser_input(img, box, (cx, cy, r), size, factor)
    assert x.shape == (1, size * size) and x.dtype == np.float32
    assert np.isfinite(x).all() and x.min() >= 0.0 and x.max() <= 1.0
    x0, y0, side = crop_square((cx, cy, r), factor)
    ox, oy = (bx, by) if use_box else (0, 0)
    pad = np.zeros((side, side), np.float32)
    sx, sy = x0 - ox, y0 - oy
    ys0, ys1, xs0, xs1 = max(sy, 0), min(sy + side, h), max(sx, 0), min(sx + side, w)
    if ys1 > ys0 and xs1 > xs0:
        pad[ys0 - sy:ys1 - sy, xs0 - sx:xs1 - sx] = img[ys0:ys1, xs0:xs1] / 255.0
    if side >= size:  # shrinking: exactly cv2's INTER_AREA
        ref = cv2.resize(pad, (size, size), interpolation=cv2.INTER_AREA).reshape(1, -1)
        np.testing.assert_allclose(x, ref, atol=1e-5)
    else:  # growing (absurdly small domes): still the area average, the mean is kept
        assert abs(float(x.mean()) - float(pad.mean())) <= 1e-5


def test_input_reuses_buffers_and_handles_other_dtypes():
    img = np.zeros((240, 320), np.uint8)
    cv2.circle(img, (160, 120), 30, 255, -1)
    out = np.empty((1, 24 * 24), np.float32)
    scratch: dict = {}
    x = localiser_input(img, None, (160.0, 120.0, 60.0), 24, out=out, scratch=scratch)
    assert x is out
    geo = scratch["geo"]
    localiser_input(img, None, (160.0, 120.0, 60.0), 24, out=out, scratch=scratch)
    assert scratch["geo"] is geo  # same dome: no new buffers
    xb = localiser_input(img > 0, None, (160.0, 120.0, 60.0), 24)
    x01 = localiser_input((img > 0).astype(np.uint8), None, (160.0, 120.0, 60.0), 24)
    np.testing.assert_allclose(xb, out)
    np.testing.assert_allclose(x01, out)


def test_normalised_coordinates_round_trip():
    rng = np.random.default_rng(0)
    dome = (325.77, 218.83, 144.77)
    pts = rng.uniform(100, 500, (50, 2))
    uv = to_normalised(pts, dome, 0.75)
    back = from_normalised(uv, dome, 0.75)
    np.testing.assert_allclose(back, pts, atol=1e-3)
    cx, cy, r = effective_dome(dome, 0.75)
    assert abs(cx - dome[0]) <= 0.5 and abs(cy - dome[1]) <= 0.5 and abs(r - dome[2]) < 1.0
    # the effective dome is a fixed point: cutting it again gives the same square
    assert crop_square((cx, cy, r), 0.75) == crop_square(dome, 0.75)


@pytest.mark.parametrize("kwargs, field", [
    ({"size": 0}, "size"), ({"size": 3.5}, "size"), ({"crop_factor": 0.0}, "crop_factor"),
    ({"dome": (1.0, math.nan, 3.0)}, "dome"), ({"dome": None}, "dome"),
    ({"binary": np.zeros((4, 4, 3), np.uint8)}, "binary"), ({"box": "x"}, "box"),
    ({"out": np.empty((1, 5), np.float32)}, "out"),
])
def test_input_bad_arguments_name_the_field(kwargs, field):
    args = {"binary": np.zeros((50, 50), np.uint8), "box": None, "dome": (25.0, 25.0, 20.0),
            "size": 16, "crop_factor": 0.75}
    args.update(kwargs)
    with pytest.raises(ValueError, match=field):
        localiser_input(**args)

