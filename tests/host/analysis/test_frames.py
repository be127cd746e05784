"""Shared measures of the realism checks (host/analysis/frames.py)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from host.analysis.frames import finite, frame_list, locate_dome, nearest_neighbour_px, stat


def test_finite_and_stat_never_give_nan():
    assert finite(math.nan) == 0.0 and finite(math.inf, 7.0) == 7.0 and finite(2.5) == 2.5
    assert stat([], np.median) == 0.0
    assert stat([1.0, 3.0], np.mean) == 2.0
    assert stat([1.0, math.nan], np.mean, default=-1.0) == -1.0


def test_frame_list_names_the_bad_frame():
    with pytest.raises(ValueError, match="0 frames"):
        frame_list([])
    with pytest.raises(ValueError, match=r"frames\[1\]\.shape"):
        frame_list([np.zeros((4, 4)), np.zeros((5, 4))])
    assert len(frame_list(iter([np.zeros((4, 4))] * 3))) == 3


def test_nearest_neighbour_px():
    xy = np.array([[0.0, 0.0], [3.0, 0.0], [3.0, 4.0]])
    np.testing.assert_allclose(nearest_neighbour_px(xy), [3.0, 3.0, 4.0])
    assert nearest_neighbour_px(np.zeros((1, 2))).shape == (0,)


def test_locate_dome_finds_a_dark_disc_and_none_on_black():
    f = np.full((240, 320), 230, np.uint8)          # bright surround, dark dome
    cv2.circle(f, (160, 120), 90, 60, -1)
    d = locate_dome([f, f])
    assert d is not None
    assert abs(d[0] - 160) < 5 and abs(d[1] - 120) < 5 and abs(d[2] - 90) < 10
    assert locate_dome([np.zeros((240, 320), np.uint8)]) is None


def test_nearest_neighbour_px_known_grid():
    xy = np.array([[0, 0], [3, 0], [0, 4], [10, 10]], np.float32)
    np.testing.assert_allclose(nearest_neighbour_px(xy), [3.0, 3.0, 4.0, math.hypot(10, 6)], rtol=1e-6)
    assert nearest_neighbour_px(np.zeros((1, 2))).shape == (0,)

