"""Pin recall and precision: detected pins against true pins within a gate."""

from __future__ import annotations

import numpy as np

__all__ = ["pin_hits", "recall_precision"]


def pin_hits(found, truth, gate_px: float = 2.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which pins have a partner within ``gate_px``.

    ``found`` (m, 2) detected and ``truth`` (n, 2) true pin positions, px.
    Returns ``truth_hit`` (n,) bool (a detection within the gate),
    ``found_hit`` (m,) bool (a true pin within the gate) and ``found_err_px``
    (m,) each detection's distance to its nearest true pin (inf without any).
    """
    f = np.asarray(found, np.float64).reshape(-1, 2)
    t = np.asarray(truth, np.float64).reshape(-1, 2)
    if not len(f) or not len(t):
        return np.zeros(len(t), bool), np.zeros(len(f), bool), np.full(len(f), np.inf)
    d = np.linalg.norm(f[:, None] - t[None], axis=-1)
    err = d.min(axis=1)
    return d.min(axis=0) <= gate_px, err <= gate_px, err


def recall_precision(found, truth, gate_px: float = 2.0) -> tuple[float, float]:
    """Share of true pins with a detection within ``gate_px`` and share of
    detections with a true pin within it; (0.0, 0.0) when either set is empty."""
    truth_hit, found_hit, _ = pin_hits(found, truth, gate_px)
    if not len(truth_hit) or not len(found_hit):
        return 0.0, 0.0
    return float(truth_hit.mean()), float(found_hit.mean())
