"""Is this frame one the sensor can make? The per-frame plausibility check.

A frame that passes the earlier stages can still be garbage: a black or white frame,
salt noise, random pixels, a camera that moved. Those give pin counts and vectors
that look like a press. :class:`FramePlausibility` compares cheap statistics of each
frame with the sensor's profile and with the reference (rest) frame's own, recorded
when the reference is set:

* blobs: every thresholded blob in the dome's box, of any size. Noise makes hundreds;
  more than ``BLOB_FACTOR`` x max(the profile's pins, the reference's blobs) fails,
  with or without a reference;
* brightness: the mean gray of the smoothed dome box more than
  ``MEAN_SHIFT_GRAY`` levels from the reference's;
* contrast: its standard deviation below ``STD_LOW`` or above ``STD_HIGH`` x the
  reference's (a flat frame has none, blurred random pixels too little);
* the dome: the box's corners lie outside the dome, brighter than its mean. Their
  margin below ``DOME_KEEP`` x the reference's (when that was at least
  ``DOME_MIN_GRAY``) fails: the dome is not where it was.

On the seven roboskin clips no genuine frame fails (docs/pipeline.md, "Faults"): a
press moves pins, it does not add hundreds of blobs, shift the mean gray by 50 or
flatten the image. Costs a few µs per frame (one ``cv2.meanStdDev`` and 16 pixels).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

#: more blobs than this x max(profile pins, reference blobs) is noise (genuine: <= 1.3)
BLOB_FACTOR = 2.5
#: the dome box's mean gray may move this far from the reference's (genuine: <= 16)
MEAN_SHIFT_GRAY = 50.0
#: its contrast (std) must stay within these factors of the reference's (genuine: 0.85-1.15)
STD_LOW = 0.5
STD_HIGH = 2.0
#: the corners' margin over the mean must keep this share of the reference's (genuine: >= 0.6)
DOME_KEEP = 0.35
#: the dome check runs when the reference's corners were at least this much brighter
DOME_MIN_GRAY = 40.0
#: a corner patch is CORNER_PX x CORNER_PX pixels, inset by CORNER_INSET_PX
CORNER_PX = 2
CORNER_INSET_PX = 1
#: the mean and std read every ROW_STEP-th row of the box
ROW_STEP = 4


@dataclass(frozen=True)
class FrameStats:
    """What the check reads from one frame's smoothed dome box and its blobs."""
    blobs: int
    mean_gray: float
    std_gray: float
    corner_margin_gray: float      # corners' mean minus the box's mean


def _corner_index(shape: tuple[int, int]) -> list[tuple[int, int]]:
    h, w = shape
    k, e = CORNER_PX, CORNER_INSET_PX
    rows = [min(max(r, 0), h - 1) for r0 in (e, h - e - k) for r in range(r0, r0 + k)]
    cols = [min(max(c, 0), w - 1) for c0 in (e, w - e - k) for c in range(c0, c0 + k)]
    return [(r, c) for r in rows for c in cols]


def frame_stats(smooth: np.ndarray, blobs: int, index=None) -> FrameStats:
    """The statistics of a smoothed uint8 dome box (``PinDetector``'s) with ``blobs``
    blobs; ``index`` is :func:`_corner_index` of its shape (worked out when None).
    Mean and std are taken over every ``ROW_STEP``-th row (the same numbers within a
    gray level or two, at half the cost)."""
    m, s = cv2.meanStdDev(smooth[::ROW_STEP])
    mean = float(m[0, 0])
    idx = _corner_index(smooth.shape) if index is None else index
    item = smooth.item
    corners = sum([item(r, c) for r, c in idx]) / len(idx)
    return FrameStats(int(blobs), mean, float(s[0, 0]), corners - mean)


def stats_from_sums(total: int, squares: int, n: int, corner_sum: int, n_corners: int,
                    blobs: int) -> FrameStats:
    """:func:`frame_stats` from the integer sums the compiled detection takes
    (:meth:`device.pi.vision.core.DetectCore.sums`): the mean and standard deviation
    as ``cv2.meanStdDev`` forms them from its sums (the mean is the sum times 1/n; the
    deviation the root of the mean square less the squared mean), the same doubles."""
    if n <= 0 or n_corners <= 0:
        return FrameStats(int(blobs), 0.0, 0.0, 0.0)
    scale = 1.0 / n
    mean = total * scale
    std = math.sqrt(max(squares * scale - mean * mean, 0.0))
    return FrameStats(int(blobs), mean, std, corner_sum / n_corners - mean)


class FramePlausibility:
    """The check, against the profile's ``n_pins`` and the reference's statistics.

    :meth:`check` gives '' for a plausible frame, else the first reason it failed
    (the pipeline then raises ``FAULT_FRAME`` and reports no contact)."""

    def __init__(self, n_pins: int):
        self.n_pins = int(n_pins)
        self.reference: FrameStats | None = None
        self._index = None
        self._shape = None

    def stats(self, smooth: np.ndarray, blobs: int) -> FrameStats:
        if smooth.shape != self._shape:
            self._shape = smooth.shape
            self._index = _corner_index(smooth.shape)
        return frame_stats(smooth, blobs, self._index)

    def set_reference(self, stats: FrameStats) -> None:
        self.reference = stats

    def clear(self) -> None:
        self.reference = None

    def check(self, s: FrameStats) -> str:
        ref = self.reference
        ref_blobs = ref.blobs if ref is not None else 0
        if s.blobs > BLOB_FACTOR * max(self.n_pins, ref_blobs):
            return "blobs"
        if ref is None:
            return ""
        if abs(s.mean_gray - ref.mean_gray) > MEAN_SHIFT_GRAY:
            return "brightness"
        if not STD_LOW * ref.std_gray <= s.std_gray <= STD_HIGH * max(ref.std_gray, 1.0):
            return "contrast"
        if (ref.corner_margin_gray >= DOME_MIN_GRAY
                and s.corner_margin_gray < DOME_KEEP * ref.corner_margin_gray):
            return "dome"
        return ""
