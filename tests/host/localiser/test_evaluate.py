"""Held-out pin errors of the localiser (host/localiser/evaluate.py)."""

from __future__ import annotations

import numpy as np

from host.localiser.evaluate import error_stats, pin_errors_px


def test_pin_errors_are_scaled_by_each_rows_radius():
    true = np.zeros((2, 4))                       # 2 rows, 2 pins
    pred = np.array([[0.03, 0.04, 0.0, 0.0], [0.0, 0.0, 0.06, 0.08]])
    e = pin_errors_px(pred, true, np.array([100.0, 10.0]))
    np.testing.assert_allclose(e, [5.0, 0.0, 0.0, 1.0])
    mask = np.array([[True, False], [False, True]])
    np.testing.assert_allclose(pin_errors_px(pred, true, np.array([100.0, 10.0]), mask), [5.0, 1.0])
    assert pin_errors_px(np.zeros((0, 4)), np.zeros((0, 4)), np.zeros(0)).size == 0


def test_error_stats_are_finite_also_when_empty():
    assert error_stats(np.zeros(0)) == {"n_pins": 0, "median_px": 0.0, "p90_px": 0.0,
                                        "mean_px": 0.0}
    s = error_stats(np.arange(11, dtype=float))
    assert s == {"n_pins": 11, "median_px": 5.0, "p90_px": 9.0, "mean_px": 5.0}
