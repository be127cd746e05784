"""Ring description of a pin layout (host/analysis/rings.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from host.analysis.rings import fit_radial_layout
from tests.domes import DOME, PHASE_DEG, RINGS, ring_layout


def _rings(centre=(100.0, 80.0), rings=((15.0, 8, 0.0), (30.0, 16, 5.0)), centre_pin=True):
    pts = [centre] if centre_pin else []
    for r, n, ph in rings:
        for k in range(n):
            a = math.radians(ph) + 2 * math.pi * k / n
            pts.append((centre[0] + r * math.cos(a), centre[1] + r * math.sin(a)))
    return np.array(pts)


def test_recovers_centre_rings_counts_and_phase():
    fit = fit_radial_layout(_rings(), centre_guess=(103.0, 78.0))
    assert abs(fit["centre_x_px"] - 100.0) < 0.05 and abs(fit["centre_y_px"] - 80.0) < 0.05
    assert fit["centre_pin"] and fit["total_pins"] == 1 + 8 + 16
    assert [r["count"] for r in fit["rings"]] == [8, 16]
    assert [round(r["radius_px"]) for r in fit["rings"]] == [15, 30]
    assert abs(fit["rings"][1]["phase_deg"] - 5.0) < 0.1
    assert fit["residual_rms_px"] < 0.01


def test_too_few_points_give_an_empty_finite_answer():
    fit = fit_radial_layout(np.zeros((2, 2)))
    assert fit["rings"] == [] and fit["total_pins"] == 0 and fit["residual_rms_px"] == 0.0


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

