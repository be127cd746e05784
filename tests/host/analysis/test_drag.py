"""Pin displacement over a drag (host/analysis/drag.py), on synthetic pin frames and
the real north.avi push."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from device.pi.vision.extract import ROBOSKIN_PARAMS
from host.analysis.drag import measure_drag_displacement, track_pins
from tests.domes import DOME, SYNTH_PARAMS, render, ring_layout
from tests.realdata import read_video, real_data_dir



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
    tr = track_pins(frames, SYNTH_PARAMS, dome=DOME)
    n = len(tr["ref_xy"])
    assert n == len(pins) and tr["xy"].shape == (len(frames), n, 2)
    assert tr["matched"][1:].mean() > 0.95
    np.testing.assert_allclose(np.median(tr["xy"][-1] - tr["ref_xy"], axis=0), (4.0, 0.0),
                               atol=0.3)
    m = measure_drag_displacement(frames, SYNTH_PARAMS, dome=DOME)
    assert abs(m["displacement_px_max"] - 4.0) < 0.3
    assert abs(m["displacement_vector_px_at_max"][0] - 4.0) < 0.3
    assert abs(m["displacement_vector_px_at_max"][1]) < 0.3
    assert m["n_pins_ref"] == n and m["faults"] == []


def test_no_pins_gives_zeros_and_a_fault():
    frames = [np.zeros((240, 320), np.uint8)] * 3
    m = measure_drag_displacement(frames, SYNTH_PARAMS, dome=DOME)
    assert m["faults"] == ["no pins in the first frame"]
    assert m["displacement_px_max"] == 0.0 and m["displacement_px_per_frame"] == [0.0] * 3


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

