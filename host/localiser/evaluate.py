"""Held-out pin errors of a fitted localiser, in px, also per displacement bin."""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from device.pi.models.localiser import effective_dome
from host.localiser.samples import Sample, augment_rows

__all__ = ["DISP_BINS_PX", "pin_errors_px", "error_stats", "evaluate", "evaluate_perturbed"]


def pin_errors_px(pred_norm: np.ndarray, true_norm: np.ndarray, r_px: np.ndarray,
                  mask: np.ndarray | None = None) -> np.ndarray:
    """Per-pin Euclidean error in px (flattened over the rows and selected pins)."""
    if len(pred_norm) == 0:
        return np.zeros(0)
    p = pred_norm.reshape(len(pred_norm), -1, 2)
    t = true_norm.reshape(len(true_norm), -1, 2)
    e = np.hypot(*(p - t).transpose(2, 0, 1)) * np.asarray(r_px, np.float64)[:, None]
    return e[mask] if mask is not None else e.reshape(-1)


def error_stats(e: np.ndarray) -> dict:
    """Count, median, p90 and mean of pin errors ``e`` (px); all 0 when empty."""
    if e.size == 0:
        return {"n_pins": 0, "median_px": 0.0, "p90_px": 0.0, "mean_px": 0.0}
    return {"n_pins": int(e.size), "median_px": round(float(np.median(e)), 3),
            "p90_px": round(float(np.percentile(e, 90)), 3), "mean_px": round(float(e.mean()), 3)}


#: displacement bins (median pin displacement from rest, px) of the held-out metrics
DISP_BINS_PX = (0.0, 6.0, 12.0, math.inf)


def evaluate(model, samples: Sequence[Sample], size: int, crop_factor: float,
             measured_only: bool) -> dict:
    """Pin error stats, plus the same per displacement bin (``by_displacement``)."""
    if not samples:
        return error_stats(np.zeros(0))
    X, Y = augment_rows(samples, size, crop_factor, 1, 0.0, 0.0, np.random.default_rng(0))
    pred = model.predict(X)
    r = np.array([effective_dome(s.dome, crop_factor)[2] for s in samples])
    mask = np.stack([s.measured for s in samples]) if measured_only else \
        np.ones((len(samples), len(samples[0].pins_px)), bool)
    out = error_stats(pin_errors_px(pred, Y, r, mask))
    disp = np.array([s.disp_px for s in samples])
    bins = {}
    for lo, hi in zip(DISP_BINS_PX[:-1], DISP_BINS_PX[1:]):
        sel = (disp >= lo) & (disp < hi)
        name = f"{lo:g}-{hi:g}px" if math.isfinite(hi) else f">={lo:g}px"
        bins[name] = {"frames": int(sel.sum()),
                      **error_stats(pin_errors_px(pred[sel], Y[sel], r[sel], mask[sel]))}
    out["by_displacement"] = bins
    return out


def evaluate_perturbed(model, samples: Sequence[Sample], size: int, crop_factor: float,
                       shift_px: float, zoom: float, seed: int) -> dict:
    """Pin error stats on crops cut around a perturbed dome (shift and zoom sigmas)."""
    if not samples:
        return error_stats(np.zeros(0))
    rng = np.random.default_rng(seed)
    X, Y = augment_rows(samples, size, crop_factor, 2, shift_px, zoom, rng)
    X, Y = X[1::2], Y[1::2]
    pred = model.predict(X)
    # the error in px is measured in the (perturbed) crop's own scale; close enough
    r = np.array([effective_dome(s.dome, crop_factor)[2] for s in samples])
    mask = np.stack([s.measured for s in samples])
    return error_stats(pin_errors_px(pred, Y, r, mask))
