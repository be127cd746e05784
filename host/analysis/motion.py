"""Pin motion of windows, per class: how far the pins are displaced, how far they
move together from frame to frame, how much they shake on their own, and how many
are lost. Real and simulated windows are measured alike, so the figures are the
targets a simulated texture is calibrated to.

Per window, from its last two frames over the pins seen in both:

* ``displacement_px``: the mean pin displacement |v| from the reference frame;
* ``common_px``: the length of the mean frame-to-frame change (the patch's motion);
* ``jitter_px``: the mean length of each pin's change minus that mean (pins that
  shake, stretch or twist apart from the patch's motion);
* ``lost_share``: the share of layout pins lost in the last frame.

Each is summarised by its median and 90th percentile over the windows. A window with
fewer than 3 pins seen gives 0 and is counted in ``few_pins``; nothing is NaN.
"""
from __future__ import annotations

import numpy as np

__all__ = ["MOTION_FIGURES", "window_motion", "motion_by_class"]

#: (key, label) of each figure, in report order
MOTION_FIGURES = (("displacement_px", "pin displacement [px]"),
                  ("common_px", "patch motion per frame [px]"),
                  ("jitter_px", "pin jitter per frame [px]"),
                  ("lost_share", "lost pins [share]"))


def window_motion(vectors: np.ndarray, lost: np.ndarray) -> dict:
    """Per-window figures (arrays of N) of windows ``vectors`` (N, T, M, 2) with
    ``lost`` (N, T, M); T >= 2."""
    v = np.asarray(vectors, np.float64)
    lo = np.asarray(lost, bool)
    if v.ndim != 4 or v.shape[1] < 2 or lo.shape != v.shape[:3]:
        raise ValueError(f"window_motion needs vectors (N, T>=2, M, 2) and lost (N, T, M), "
                         f"got {v.shape} and {lo.shape}")
    seen = ~lo[:, -1] & ~lo[:, -2]                                   # (N, M)
    n = seen.sum(axis=1)
    ok = n >= 3
    w = seen / np.maximum(n, 1)[:, None]
    # inf/NaN/huge vectors (the hard cases) give inf or NaN on the way; the answer
    # maps them to 0 below, so numpy's warnings about them are expected here
    with np.errstate(invalid="ignore", over="ignore"):
        step = v[:, -1] - v[:, -2]
        d = np.where(np.isfinite(step), step, 0.0)
        mag = np.linalg.norm(np.nan_to_num(v[:, -1]), axis=-1)
        common = np.einsum("nm,nmk->nk", w, d)
        resid = np.linalg.norm(d - common[:, None, :], axis=-1)
        out = {"displacement_px": np.where(ok, (w * mag).sum(axis=1), 0.0),
               "common_px": np.where(ok, np.linalg.norm(common, axis=-1), 0.0),
               "jitter_px": np.where(ok, (w * resid).sum(axis=1), 0.0),
               "lost_share": lo[:, -1].mean(axis=1) if lo.shape[2] else np.zeros(len(v))}
    return {k: np.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0) for k, x in out.items()}


def motion_by_class(ws) -> dict:
    """{class: {figure_p50, figure_p90 for each of :data:`MOTION_FIGURES`, windows,
    few_pins}} of a :class:`host.data.windows.WindowSet` (T >= 2) with labels."""
    out = {}
    if ws.labels is None or len(ws) == 0:
        return out
    per = window_motion(ws.vectors, ws.lost)
    seen = (~ws.lost[:, -1] & ~ws.lost[:, -2]).sum(axis=1)
    for label in sorted({str(x) for x in ws.labels}):
        k = np.asarray([str(x) == label for x in ws.labels])
        row = {"windows": int(k.sum()), "few_pins": int((seen[k] < 3).sum())}
        for key, _ in MOTION_FIGURES:
            row[f"{key}_p50"] = round(float(np.percentile(per[key][k], 50)), 4)
            row[f"{key}_p90"] = round(float(np.percentile(per[key][k], 90)), 4)
        out[label] = row
    return out
