"""The compiled pin detection (``detect.c``'s ``tf_detect``) behind :class:`PinDetector`.

:meth:`device.pi.vision.extract.PinDetector.detect_gray` is the specification: OpenCV's
blur, box-mean threshold and connected components. :class:`DetectCore` holds one
context (an int64 array of sizes, parameters and buffer addresses, the ``S_*`` slots
below, which ``detect.c`` names the same) and the buffers it points at, so a frame
is one call with one argument into preallocated memory.

A core is made only after it has shown, on a random frame of the detector's own
geometry, that it gives OpenCV's smoothed box, binary image, pins and areas to the
byte (:func:`self_check`); otherwise the detector keeps the numpy path and
:attr:`DetectCore.why_not` says why. That check also guards against an OpenCV whose
arithmetic differs from the one ``detect.c`` reproduces.
"""
from __future__ import annotations

import math

import cv2
import numpy as np

__all__ = ["S_SLOTS", "gaussian_taps", "DetectCore"]

# the context's slots, in detect.c's order
(S_GRAY, S_GRAY_STRIDE, S_BH, S_BW, S_KN, S_KERNEL, S_ROWS, S_SMOOTH, S_BLOCK,
 S_FLOOR_OFFSET, S_PAD, S_GY0, S_GX0, S_GY1, S_GX1, S_CY0, S_CX0,
 S_CY1, S_CX1, S_MASK, S_COLSUM, S_BINARY, S_BIN_STRIDE, S_LABELS, S_CAP, S_PARENT,
 S_ACC, S_ORDER, S_MIN_AREA, S_MAX_AREA, S_OX, S_OY, S_XY, S_AREAS, S_OUT_CAP,
 S_N_BLOBS, S_STAT_STEP, S_STAT_SUM, S_STAT_SQSUM, S_STAT_N, S_CORNERS, S_N_CORNERS,
 S_CORNER_SUM, S_SLOTS) = range(44)

#: the largest blur kernel and mean block the compiled path takes (OpenCV sums a box
#: of at most 256 pixels in 16 bits; larger blocks take another path, which stays
#: on numpy)
MAX_TAPS = 15
MAX_BLOCK = 15


def gaussian_taps(ksize: int, sigma: float) -> np.ndarray:
    """OpenCV's fixed-point Gaussian kernel for 8-bit images: ``ksize`` taps in
    1/256ths that sum to 256 (the normalised Gaussian rounded with its error carried
    from the tails inwards, the centre taking the rest)."""
    n = int(ksize)
    if n < 1 or n % 2 == 0:
        raise ValueError(f"ksize must be odd and >= 1, got ksize={ksize!r}")
    if not (math.isfinite(sigma) and sigma > 0):
        raise ValueError(f"sigma must be finite and > 0, got sigma={sigma!r}")
    if n == 1:
        return np.array([256], np.uint16)
    half = n // 2
    scale2 = -0.125 / (sigma * sigma)
    vals = [math.exp(float((x * x)) * scale2) for x in range(1 - n, 0, 2)][:half]
    total = 2.0 * sum(vals) + 1.0
    inv = 1.0 / total
    taps = [0] * n
    err, acc = 0.0, 0
    for i in range(half):
        v = vals[i] * inv * 256.0 + err
        r = int(round(v))            # cvRound: half to even, as Python's round
        err = v - r
        taps[i] = taps[n - 1 - i] = r
        acc += r
    taps[half] = 256 - 2 * acc
    return np.array(taps, np.uint16)


def _addr(a: np.ndarray) -> int:
    return a.ctypes.data


class DetectCore:
    """One detector geometry's context and buffers for ``tf_detect``.

    ``det`` is the :class:`~device.pi.vision.extract.PinDetector` whose geometry and
    buffers (its smoothed box, binary buffer and mask) the core writes into, so the
    rest of the pipeline reads them as it reads the numpy path's."""

    def __init__(self, fn, det) -> None:
        p = det.params
        self._fn = fn
        bh, bw = det._smooth.shape
        k = det.blur_ksize[0] if p.blur_sigma_px > 0 else 0
        self.kernel = (gaussian_taps(k, p.blur_sigma_px) if k else np.zeros(1, np.uint16))
        gy, gx = det._grown
        cx0, cy0, _, _ = det.core
        ty1 = cy0 + det._core_mask.shape[0]
        tx1 = cx0 + det._core_mask.shape[1]
        ch, cw = ty1 - cy0, tx1 - cx0
        self._rows = np.empty((bh, bw), np.uint16)
        self._pad = np.empty(bw + 2 * (MAX_TAPS // 2), np.uint8)
        self._colsum = np.empty(bw + bw + 16, np.uint16)
        # two rows of runs (start, end, label), at most cw / 2 + 1 runs a row
        self._labels = np.empty(6 * (cw // 2 + 2), np.int32)
        cap = ch * (cw // 2 + 1) + 2        # a run a provisional label
        self._parent = np.empty(cap, np.int32)
        self._acc = np.empty((cap, 4), np.int64)
        self._order = np.empty(cap, np.int32)
        self.xy = np.empty((cap, 2), np.float32)
        self.areas = np.empty(cap, np.int32)
        # the detector's buffers this context writes into, kept alive with it; not the
        # detector itself, which holds this core (a cycle would wait for the cyclic
        # collector, and a calibration's many short-lived detectors piled up)
        self._buffers = (det._smooth, det._binary_even, det._core_mask)
        c = np.zeros(S_SLOTS, np.int64)
        c[S_BH], c[S_BW], c[S_KN] = bh, bw, k
        c[S_KERNEL] = _addr(self.kernel)
        c[S_ROWS] = _addr(self._rows)
        c[S_SMOOTH] = _addr(det._smooth)
        c[S_BLOCK] = p.block
        c[S_PAD] = _addr(self._pad)
        c[S_GY0], c[S_GY1], c[S_GX0], c[S_GX1] = gy.start, gy.stop, gx.start, gx.stop
        c[S_CY0], c[S_CX0], c[S_CY1], c[S_CX1] = cy0, cx0, ty1, tx1
        c[S_MASK] = _addr(det._core_mask)
        c[S_COLSUM] = _addr(self._colsum)
        c[S_BINARY] = _addr(det._binary_even)
        c[S_BIN_STRIDE] = det._binary_even.strides[0]
        c[S_LABELS] = _addr(self._labels)
        c[S_CAP] = cap
        c[S_PARENT], c[S_ACC], c[S_ORDER] = (_addr(self._parent), _addr(self._acc),
                                             _addr(self._order))
        c[S_MIN_AREA], c[S_MAX_AREA] = p.min_area_px, p.max_area_px
        x0, y0 = det.box[0], det.box[1]
        c[S_OX], c[S_OY] = x0, y0
        c[S_XY], c[S_AREAS], c[S_OUT_CAP] = _addr(self.xy), _addr(self.areas), cap
        from device.pi.vision.plausibility import ROW_STEP, _corner_index
        self._corners = np.array(_corner_index((bh, bw)), np.int64).reshape(-1, 2)
        c[S_STAT_STEP] = ROW_STEP
        c[S_CORNERS], c[S_N_CORNERS] = _addr(self._corners), len(self._corners)
        self.ctx = c
        self._ptr = c.ctypes.data
        self.set_offset(det.offset)

    def set_offset(self, offset: float) -> None:
        self.ctx[S_FLOOR_OFFSET] = math.floor(offset)

    def detect(self, crop: np.ndarray) -> int:
        """Run on the gray dome box ``crop`` (uint8, rows contiguous): the number of
        pins kept (in :attr:`xy`, :attr:`areas`), or -1 (nothing trusted: use numpy)."""
        c = self.ctx
        c[S_GRAY] = crop.ctypes.data
        c[S_GRAY_STRIDE] = crop.strides[0]
        n = self._fn(self._ptr)
        c[S_GRAY] = 0
        return n

    @property
    def n_blobs(self) -> int:
        return int(self.ctx[S_N_BLOBS])

    def sums(self) -> tuple[int, int, int, int, int]:
        """The last frame's plausibility sums: (pixel sum, sum of squares, pixels) over
        every ``ROW_STEP``-th row of the smoothed box, (corner sum, corners)."""
        c = self.ctx
        return (int(c[S_STAT_SUM]), int(c[S_STAT_SQSUM]), int(c[S_STAT_N]),
                int(c[S_CORNER_SUM]), int(c[S_N_CORNERS]))


def self_check(det, c: DetectCore, seed: int = 0) -> str:
    """'' when ``c`` gives ``det``'s numpy path to the byte (smoothed box, binary
    image, pins, areas, blob count) on a test frame of ``det``'s geometry: smooth
    noise with bright dots, as a dome looks. Else what differed."""
    bh, bw = det._smooth.shape
    rng = np.random.default_rng(seed)
    crop = rng.integers(40, 90, (bh, bw), dtype=np.uint8)
    n = max(8, bh * bw // 150)
    for cx, cy, r, v in zip(rng.integers(0, bw, n).tolist(), rng.integers(0, bh, n).tolist(),
                            rng.integers(1, 6, n).tolist(), rng.integers(120, 256, n).tolist()):
        cv2.circle(crop, (cx, cy), r, v, -1)
    xy, areas = det.detect_numpy(crop)
    smooth, binary, n_blobs = det._smooth.copy(), det._binary_even.copy(), det.n_blobs
    n = c.detect(crop)
    if n < 0:
        return "the compiled detection refused its context"
    for name, ok in (("pins", n == len(xy) and np.array_equal(c.xy[:n], xy)),
                     ("areas", np.array_equal(c.areas[:n], areas)),
                     ("smoothed box", np.array_equal(det._smooth, smooth)),
                     ("binary image", np.array_equal(det._binary_even, binary)),
                     ("blob count", c.n_blobs == n_blobs)):
        if not ok:
            return f"the compiled detection's {name} differ from OpenCV's on a test frame"
    return ""


def supported(params, offset: float) -> str:
    """'' when ``tf_detect`` can reproduce the numpy path for these parameters, else
    why not."""
    if math.floor(offset) < 0:
        return f"a negative threshold offset ({offset})"
    if not 3 <= params.block <= MAX_BLOCK:
        return f"block {params.block} is over {MAX_BLOCK}"
    if params.blur_sigma_px > 0 and 2 * math.ceil(2.0 * params.blur_sigma_px) + 1 > MAX_TAPS:
        return f"blur sigma {params.blur_sigma_px} px needs more than {MAX_TAPS} taps"
    return ""

