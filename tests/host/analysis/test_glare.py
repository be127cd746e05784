"""Glare blobs and the dome's radial profile (host/analysis/glare.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from host.analysis.glare import glare_blobs, measure_glare, radial_profile
from tests.domes import DOME, render, ring_layout


def _frame(with_blob: bool = True) -> np.ndarray:
    yy, xx = np.mgrid[:240, :320]
    f = np.full((240, 320), 40.0)
    if with_blob:
        f += 120.0 * np.exp(-((xx - 190) ** 2 + (yy - 110) ** 2) / (2 * 8.0 ** 2))
    return f.clip(0, 255).astype(np.uint8)


def test_one_soft_blob_is_found_where_it_is():
    blobs = glare_blobs(_frame(), DOME, pin_diameter_px=4.0)
    assert len(blobs) == 1
    b = blobs[0]
    assert abs(b["x_px"] - 190) <= 1 and abs(b["y_px"] - 110) <= 1
    assert 80 <= b["amplitude_gray"] <= 125
    assert 5.0 <= b["sigma_px"] <= 11.0
    assert abs(b["radius_frac"] - np.hypot(30, 10) / 100.0) < 0.02


def test_measure_glare_counts_and_faults():
    res = measure_glare([_frame(), _frame()], dome=DOME, pin_diameter_px=4.0)
    assert res["n_frames"] == 2 and res["glare_blob_count_median"] == 1.0
    assert len(res["blobs_first_frame"]) == 1 and res["faults"] == []
    none = measure_glare([np.zeros((60, 80), np.uint8)])
    assert none["faults"] == ["no dome found"] and none["glare_blob_count_median"] == 0.0
    assert measure_glare([_frame(False)], dome=DOME)["glare_blob_count_median"] == 0.0


def test_radial_profile_of_a_ring():
    f = np.zeros((50, 50), np.uint8)
    yy, xx = np.mgrid[:50, :50]
    r = np.hypot(xx - 25, yy - 25).astype(int)
    f[r == 10] = 200
    prof = radial_profile(f, (25.0, 25.0), 30)
    assert prof.shape == (30,) and prof[10] == 200.0 and prof[5] == 0.0
    assert np.isfinite(prof).all()


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

