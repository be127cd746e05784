"""Pin displacement over a drag (host/analysis/drag.py), on synthetic pin frames."""

from __future__ import annotations

import cv2
import numpy as np

from device.pi.vision.extract import VisionParams
from host.analysis.drag import measure_drag_displacement, track_pins

PARAMS = VisionParams(block=11, offset=14.0, blur_sigma_px=1.0, min_area_px=6,
                      max_area_px=100, roi_shrink=0.9)
DOME = (160.0, 120.0, 100.0)


def _grid() -> np.ndarray:
    g = np.arange(-60, 61, 15.0)
    return np.array([(DOME[0] + x, DOME[1] + y) for x in g for y in g
                     if np.hypot(x, y) < 70])


def _frame(pins: np.ndarray) -> np.ndarray:
    f = np.full((240, 320), 30, np.uint8)
    cv2.circle(f, (160, 120), 100, 60, -1)
    for x, y in pins:
        cv2.circle(f, (int(round(x * 4)), int(round(y * 4))), 12, 230, -1, cv2.LINE_AA, 2)
    return f


def test_a_steady_shift_is_tracked_and_measured():
    pins = _grid()
    shifts = [0.0, 1.0, 2.0, 3.0, 4.0, 4.0]
    frames = [_frame(pins + (s, 0.0)) for s in shifts]
    tr = track_pins(frames, PARAMS, dome=DOME)
    n = len(tr["ref_xy"])
    assert n == len(pins) and tr["xy"].shape == (len(frames), n, 2)
    assert tr["matched"][1:].mean() > 0.95
    np.testing.assert_allclose(np.median(tr["xy"][-1] - tr["ref_xy"], axis=0), (4.0, 0.0),
                               atol=0.3)
    m = measure_drag_displacement(frames, PARAMS, dome=DOME)
    assert abs(m["displacement_px_max"] - 4.0) < 0.3
    assert abs(m["displacement_vector_px_at_max"][0] - 4.0) < 0.3
    assert abs(m["displacement_vector_px_at_max"][1]) < 0.3
    assert m["n_pins_ref"] == n and m["faults"] == []


def test_no_pins_gives_zeros_and_a_fault():
    frames = [np.zeros((240, 320), np.uint8)] * 3
    m = measure_drag_displacement(frames, PARAMS, dome=DOME)
    assert m["faults"] == ["no pins in the first frame"]
    assert m["displacement_px_max"] == 0.0 and m["displacement_px_per_frame"] == [0.0] * 3
