"""The marker pipeline's usual frame in one compiled call (``frame.c``'s ``tf_frame``).

:meth:`device.pi.vision.pipeline.MarkerStream.process` is the specification: with a
reference set it detects the pins (``tf_detect``), checks the frame's plausibility
(:mod:`device.pi.vision.plausibility`), tracks (``tf_track``), updates the contact
grid (``tf_grid``) and takes the shear features (``tf_shear``), each a ctypes call with
Python between them. ``tf_frame`` chains the same kernels inside C on their own
contexts (made by :mod:`device.pi.vision.core`, :class:`~device.pi.vision.tracking.Tracker`
and :class:`~device.pi.vision.features.ContactGrid`, so nothing is set up twice), with
the plausibility statistics and check ported to C (the same doubles; the constants
come from :mod:`device.pi.vision.plausibility`, never copied as literals).

Its status names the first stage the stream must take on the existing Python path;
every stage before it has left the state the sequential path would leave:

========  ==================================================================
DONE      everything written: pins, tracking, grid, shear, contact
DETECT    ``tf_detect`` refused its context: the stream detects with OpenCV
IMPLAUS   the frame failed the check (:attr:`FrameCore.reason`)
TRACK     the tracker's numpy path takes the frame (a jump, no pin, ...)
GRID      ``tf_grid`` refused its context: the grid and features in Python
REFUSED   (-1) the fused context was refused: nothing ran
========  ==================================================================
"""
from __future__ import annotations

import numpy as np

from device.pi.vision import plausibility
from device.pi.vision.core import S_GRAY, S_GRAY_STRIDE
from device.pi.vision.features import MAX_VECTOR_PX

__all__ = ["FrameCore", "DONE", "DETECT", "IMPLAUS", "TRACK", "GRID", "REFUSED", "REASONS"]

DONE, DETECT, IMPLAUS, TRACK, GRID, REFUSED = 0, 1, 2, 3, 4, -1
#: FramePlausibility.check's reasons by frame.c's code
REASONS = ("", "blobs", "brightness", "contrast", "dome")

# the context's slots, in frame.c's order (TF_F_*, TF_FD_*)
(F_DETECT, F_TRACK_I, F_TRACK_D, F_TRACK_CAP, F_GRID, F_MAGS, F_MAGS_CAP, F_DBL, F_N_PINS,
 F_HAS_REF, F_REF_BLOBS, F_PINS, F_REASON, F_TRACK_RC, F_GRID_CONTACT, F_N_VALID, F_CONTACT,
 F_SLOTS) = range(18)
(FD_BLOB_FACTOR, FD_MEAN_SHIFT, FD_STD_LOW, FD_STD_HIGH, FD_DOME_KEEP, FD_DOME_MIN,
 FD_REF_MEAN, FD_REF_STD, FD_REF_CORNER, FD_CLIP, FD_CONTACT_PX, FD_MEAN, FD_STD, FD_CORNER,
 FD_SX, FD_SY, FD_MSUM, FD_SLOTS) = range(18)


class FrameCore:
    """One stream's ``tf_frame`` context. :meth:`run` points it at the detection core,
    the tracker's update context, the grid's context and the plausibility reference it
    is given (set again whenever one of them is another object) and runs one frame."""

    def __init__(self, fn, n_pins: int, contact_px: float) -> None:
        self.fn = fn
        self.ctx = np.zeros(F_SLOTS, np.int64)
        self.dbl = np.zeros(FD_SLOTS, np.float64)
        self._ptr = self.ctx.ctypes.data
        c, d = self.ctx, self.dbl
        c[F_DBL] = d.ctypes.data
        c[F_N_PINS] = int(n_pins)
        p = plausibility
        d[FD_BLOB_FACTOR], d[FD_MEAN_SHIFT] = p.BLOB_FACTOR, p.MEAN_SHIFT_GRAY
        d[FD_STD_LOW], d[FD_STD_HIGH] = p.STD_LOW, p.STD_HIGH
        d[FD_DOME_KEEP], d[FD_DOME_MIN] = p.DOME_KEEP, p.DOME_MIN_GRAY
        d[FD_CLIP], d[FD_CONTACT_PX] = MAX_VECTOR_PX, float(contact_px)
        self._bound = (None, None, None, None, None)
        self._mags = np.empty(0, np.float64)

    def __reduce__(self):
        # the context holds addresses of this stream's buffers: a copy starts unbound,
        # with no function (the stream makes a new core for it)
        return (FrameCore, (None, int(self.ctx[F_N_PINS]), float(self.dbl[FD_CONTACT_PX])))

    def _bind(self, dcore, ci, cd, gctx, ref) -> None:
        c, d = self.ctx, self.dbl
        c[F_DETECT], c[F_TRACK_I], c[F_TRACK_D], c[F_GRID] = (
            dcore.ctx.ctypes.data, ci.ctypes.data, cd.ctypes.data, gctx.ctypes.data)
        m = int(ci[4])                               # the reference's pins (TF_T_M)
        if self._mags.shape[0] < m:
            self._mags = np.empty(m, np.float64)
        c[F_MAGS], c[F_MAGS_CAP] = self._mags.ctypes.data, self._mags.shape[0]
        c[F_HAS_REF] = ref is not None
        if ref is not None:
            c[F_REF_BLOBS] = ref.blobs
            d[FD_REF_MEAN], d[FD_REF_STD], d[FD_REF_CORNER] = (
                ref.mean_gray, ref.std_gray, ref.corner_margin_gray)
        # the kernels' contexts are kept alive while the frame context points at them
        self._bound = (dcore, ci, cd, gctx, ref)

    def run(self, dcore, crop: np.ndarray, tracker, ci, cd, grid, check, binary) -> int:
        """One frame: ``dcore`` the detector's :class:`~device.pi.vision.core.DetectCore`,
        ``crop`` its gray dome box, ``ci``/``cd`` the tracker's update contexts as
        :meth:`~device.pi.vision.tracking.Tracker.compiled_args` made them ready,
        ``grid`` a :class:`ContactGrid` with its compiled context, ``check`` the
        :class:`FramePlausibility`, ``binary`` the detector's binary buffer. The
        status (module doc)."""
        b = self._bound
        ref = check.reference
        gctx = grid._ctx
        if b[0] is not dcore or b[1] is not ci or b[2] is not cd or b[3] is not gctx \
                or b[4] is not ref:
            self._bind(dcore, ci, cd, gctx, ref)
        c = self.ctx
        c[F_TRACK_CAP] = tracker._tcap
        gctx[0], gctx[1] = binary.ctypes.data, binary.strides[0]
        d = dcore.ctx
        d[S_GRAY], d[S_GRAY_STRIDE] = crop.ctypes.data, crop.strides[0]
        status = self.fn(self._ptr)
        d[S_GRAY] = 0
        return int(status)

    @property
    def pins(self) -> int:
        return int(self.ctx[F_PINS])

    @property
    def reason(self) -> str:
        """Why the last frame failed the check ('' when it passed)."""
        return REASONS[int(self.ctx[F_REASON])]

    def features(self) -> tuple[float, float, float, bool]:
        """The last DONE frame's (shear x, shear y, magnitude sum, contact)."""
        d = self.dbl
        return float(d[FD_SX]), float(d[FD_SY]), float(d[FD_MSUM]), bool(self.ctx[F_CONTACT])

    def stats(self) -> plausibility.FrameStats:
        """The last checked frame's statistics (what stats_from_sums gives)."""
        d = self.dbl
        return plausibility.FrameStats(self._bound[0].n_blobs, float(d[FD_MEAN]), float(d[FD_STD]), float(d[FD_CORNER]))
