"""Fixed pin layout: every model sees the same M pins in the same order.

The marker pipeline tracks however many pins its reference frame had; models take
a fixed layout (the sensor profile's pin positions, ring by ring for roboskin).
:class:`LayoutMapper` puts each frame's per-reference-pin vectors onto that layout;
the host's dataset loader and the Pi runtime both use it, so a model sees the same
input on both. :func:`binary_crop` is the CNN's input frame (the thresholded image,
resized).
"""
from __future__ import annotations

import cv2
import numpy as np

from device.checks import positive_number
from device.pi.vision.matching import match_pins
from device.profile import load_layout
from device.errors import TacfootError

__all__ = ["LayoutError", "layout_assignment", "to_layout", "LayoutMapper",
           "layout_for_profile", "binary_crop"]


class LayoutError(TacfootError, ValueError):
    """A profile has no fixed pin layout."""


def layout_assignment(reference_px: np.ndarray, layout_px: np.ndarray, gate_px: float,
                      rounds: int = 3) -> np.ndarray:
    """For each fixed layout pin, the reference pin it stands for, or -1.

    The layout is first shifted onto the reference (the median offset of matched
    pins, ``rounds`` times, starting from a gate of 1.5 x ``gate_px``), then matched
    one to one, nearest first, within ``gate_px``. Returns int64 (M_layout,).
    """
    ref = np.asarray(reference_px, np.float64).reshape(-1, 2)
    lay = np.asarray(layout_px, np.float64).reshape(-1, 2)
    gate_px = positive_number("gate_px", gate_px)
    if len(ref) == 0:
        return np.full(len(lay), -1, np.int64)
    shift = np.zeros(2)
    for r in range(max(0, int(rounds))):
        idx = match_pins(lay + shift, ref, gate_px * (1.5 if r == 0 else 1.0))
        ok = idx >= 0
        if ok.sum() < 3:
            break
        shift = np.median(ref[idx[ok]] - lay[ok], axis=0)
    return match_pins(lay + shift, ref, gate_px)


def to_layout(vectors: np.ndarray, lost: np.ndarray, assignment: np.ndarray,
              out_vectors: np.ndarray | None = None, out_lost: np.ndarray | None = None
              ) -> tuple[np.ndarray, np.ndarray]:
    """Per-reference-pin ``vectors`` (m, 2) / ``lost`` (m,) -> the fixed layout
    (M, 2) float32 / (M,) bool. A layout pin with no reference pin, or whose pin is
    lost, is lost with a zero vector."""
    M = len(assignment)
    v = np.zeros((M, 2), np.float32) if out_vectors is None else out_vectors
    lo = np.ones(M, bool) if out_lost is None else out_lost
    v[:] = 0.0
    lo[:] = True
    m = len(vectors)
    ok = (assignment >= 0) & (assignment < m)
    if m and ok.any():
        src = assignment[ok]
        vv = np.asarray(vectors, np.float32)[src]
        ll = np.asarray(lost, bool)[src] | ~np.isfinite(vv).all(axis=1)
        vv[ll] = 0.0
        v[ok] = vv
        lo[ok] = ll
    return v, lo


class LayoutMapper:
    """Puts a :class:`MarkerStream`'s per-reference-pin vectors on a fixed layout.

    The assignment is worked out once per reference frame (:func:`layout_assignment`).
    This is the one place to swap for the fixed-count localiser, which gives all
    ``M`` pins per frame directly.
    """

    def __init__(self, layout_px: np.ndarray, gate_px: float):
        self.layout_px = np.asarray(layout_px, np.float64).reshape(-1, 2)
        self.gate_px = float(gate_px)
        self._ref_id = None
        self._assignment = np.full(len(self.layout_px), -1, np.int64)

    @property
    def n_pins(self) -> int:
        return len(self.layout_px)

    @property
    def assignment(self) -> np.ndarray:
        return self._assignment

    def __call__(self, stream, ff, out_vectors=None, out_lost=None):
        ref = stream.reference
        if ref is None:
            return to_layout(np.zeros((0, 2), np.float32), np.zeros(0, bool),
                             np.full(self.n_pins, -1, np.int64), out_vectors, out_lost)
        if ref is not self._ref_id:
            self._ref_id = ref
            self._assignment = layout_assignment(ref, self.layout_px, self.gate_px)
        return to_layout(ff.vectors, ff.lost, self._assignment, out_vectors, out_lost)


def layout_for_profile(profile: str) -> np.ndarray:
    """The fixed pin layout (M, 2) px of a sensor profile (ring by ring for roboskin;
    measured rest pins for a profile from ``host calibrate``)."""
    try:
        return np.asarray(load_layout(profile), np.float64)
    except Exception as exc:   # a [vision]-only file has no layout
        raise LayoutError(f"profile {profile!r}: no fixed pin layout ([profile]/[layout]) to "
                        f"map pins onto: {exc}") from None


def binary_crop(stream, size: int) -> np.ndarray:
    det = stream.detector
    b = None if det is None else det.binary
    if b is None or b.size == 0:
        return np.zeros((size, size), np.uint8)
    return cv2.resize(b, (size, size), interpolation=cv2.INTER_AREA)
