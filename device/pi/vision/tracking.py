"""Pin tracking: map reference pins to current pins, one to one, frame by frame.

Runs on the Pi (numpy + OpenCV only). One small state object (:class:`Tracker`)
holds the reference layout and the preallocated per-frame buffers; the matching
itself is :mod:`device.pi.vision.matching` (one-to-one matching with a gate) and
:mod:`device.pi.vision.neighbours` (layout neighbours and large deformations).

Conventions: points are float ``(x, y)`` pixels, ``ref`` is the reference
layout ``(m, 2)`` and ``cur`` the pins of the current frame ``(n, 2)``. An
assignment is an int array ``idx`` of shape ``(m,)``: ``idx[i]`` is the row of
``cur`` that reference pin ``i`` moved to, or ``-1`` when the pin is lost. No
current pin is ever used twice and a lost pin is never invented.

Per frame the :class:`Tracker` predicts each pin from its last displacement,
corrects the prediction from confidently tracked neighbours, matches, and grows
into lost pins; its vectors are always finite and lost pins are flagged.
"""

from __future__ import annotations

import numpy as np

from device.checks import finite_number, positive_number, whole_number

# Tracker fault bits (Tracker.faults), from the one table: FAULT_NO_REFERENCE (update()
# before set_reference(): empty outputs), FAULT_BAD_INPUT (current pins not an (n, 2)
# array, or rows with NaN/inf/huge dropped), FAULT_TOO_FEW_PINS (fewer than
# min_tracked_frac of the reference pins tracked)
from device.pi.faults import FAULT_BAD_INPUT, FAULT_NO_REFERENCE, FAULT_TOO_FEW_PINS
from device.pi.vision import native
from device.pi.vision.matching import all_rows_usable, as_points, usable_rows
from device.pi.vision.neighbours import (_FINAL_ROUNDS, layout_neighbours, layout_pitch_px,
                                         match_and_grow, neighbour_consistency,
                                         track_with_neighbours)

__all__ = [
    "Tracker",
    "FAULT_NO_REFERENCE",
    "FAULT_BAD_INPUT",
    "FAULT_TOO_FEW_PINS",
]

#: Weight of the newest change in the tracker's exponentially averaged velocity.
_VEL_ALPHA = 0.5


# --------------------------------------------------------------------------
# Per-frame state
# --------------------------------------------------------------------------


def _steps(steps) -> int:
    """:meth:`Tracker.update`'s ``steps``: a whole number in 1..1000, else 1."""
    return int(steps) if isinstance(steps, (int, np.integer)) and 1 <= steps <= 1000 else 1


_FILL_MODES = ("predict", "hold", "zero")
_REACQUIRE_MODES = ("inline", "background")


#: the coarse re-acquisition's schedule from scratch: annealing from 3 pitches, 16
#: temperatures, 10 Sinkhorn normalisations each (track_with_neighbours' defaults)
FULL_SEARCH_SCHEDULE = (3.0, 16, 10)


class Tracker:
    """Reference pins plus per-frame tracking to displacement vectors.

    >>> tr = Tracker()                      # doctest: +SKIP
    >>> tr.set_reference(ref_pins)          # doctest: +SKIP
    >>> vectors, lost = tr.update(pins)     # doctest: +SKIP

    Each frame the reference pins are predicted at their last displacement
    plus their recent change per frame (an exponentially averaged velocity)
    and matched one to one (:func:`match_pins`), first with half the gate
    ``max_dist_px``; lost pins are then searched for again at the
    displacement predicted from their tracked layout neighbours (growing
    outward), and last with the full gate. When fewer than
    ``reacquire_frac`` of the pins are within half the gate of their
    prediction, and either frames were dropped before this one, or the
    growth found fewer than ``reacquire_frac`` of the pins, or it found them
    a median of more than 0.8 gate from their prediction (a jump: a snap
    back, a deformation larger than a pitch), the frame is tracked again with
    the coarse annealed matching of :func:`track_with_neighbours`, and of the
    two answers the one whose pins move more like their layout neighbours is
    kept. Glare that hides pins and fast shear leave many pins away from
    their prediction but within reach of the growth; on the real smooth.avi
    the coarse search (about 3 ms) runs on 8 of 540 frames. The
    prediction goes ``steps`` frames ahead when frames were dropped, with the
    velocity kept per frame. Its annealing
    schedule is ``reacquire_schedule`` = (start in pitches, temperatures,
    Sinkhorn normalisations per temperature), by default the search from
    scratch, ``FULL_SEARCH_SCHEDULE``. A cheaper one trades accuracy on large
    jumps for time: (1.5, 6, 5) costs less than half as much (1.3 against
    3.0 ms per re-acquisition on the real clips, one thread) and keeps every
    identity on the simulated scenes with frames skipped in threes and fives
    (:func:`host.analysis.pipeline_eval.evaluate_scene` with ``stride``), but
    after a jump of more than a pitch from rest it places 94 % of the pins
    right, against 97 %.

    ``reacquire`` says where that coarse search runs. ``"inline"`` (default): in
    the update, which then takes it (3-9 ms on the real clips). ``"background"``
    (the leg's runtime): on a worker thread, so the jump frame returns at once,
    with every pin reported lost at its prediction and ``FAULT_TOO_FEW_PINS`` (a pin
    found near its prediction after a jump can be its neighbour); the next update
    first takes the search's answer (waiting for it if needed) and, when it wins,
    puts the state where the inline search would have left it, so every later
    frame's output is the inline one. ``reacquire_errors`` counts searches that
    raised (the frame's fast answer is then kept).

    Lost pins are flagged in ``lost`` and never invented: their vector is
    filled according to ``fill``:

    * ``"predict"`` (default): their predicted vector - the last value
      (plus velocity) corrected by the median prediction error of their
      tracked layout neighbours, or those neighbours' median vector when the
      two disagree by more than the gate; without tracked neighbours, the
      last value (plus velocity) corrected by the median error of all
      tracked pins (uncorrected when fewer than 3 are tracked);
    * ``"hold"``: their last value;
    * ``"zero"``: 0.

    All outputs are finite. ``faults`` holds the fault bits of the last
    update: ``FAULT_NO_REFERENCE`` (no reference set: empty outputs),
    ``FAULT_BAD_INPUT`` (pins not an (n, 2) array: treated as no pins; or
    rows with NaN, inf or beyond ``MAX_COORD_PX``: dropped, and ``idx``
    still indexes the caller's array) and ``FAULT_TOO_FEW_PINS`` (fewer than
    ``min_tracked_frac`` of the reference tracked; such a frame does not
    update the prediction). ``update`` never raises. After each update
    ``idx`` (m,) holds the row of the current pins each reference pin was
    matched to (-1 lost), ``n_tracked`` their number, and ``reacquired``
    1 when the coarse re-acquisition ran (else 0).

    Parameters: ``max_dist_px`` the matching gate (default ``gate_frac`` x
    the layout pitch); ``pitch_px`` the pin spacing (default: measured from
    the reference; give it, or ``max_dist_px``, for a one-pin reference);
    ``velocity_gain`` how much of each pin's last change per frame is added
    to its prediction (constant-velocity model; 0 predicts the last value);
    ``k`` neighbours per pin for the predictions; ``grow_rounds`` how many
    rings of lost pins the neighbour prediction may grow into per frame.

    Cost per frame in steady state is one :func:`match_pins` call plus a few
    small array operations, growing linearly with the pin count (the matching
    scores only the pairs a cell grid puts within the gate); buffers are
    allocated in :meth:`set_reference` only. The coarse re-acquisition costs
    several times more, grows with pins x detections (its soft matching is
    dense), and only runs after a jump.
    """

    def __init__(
        self,
        max_dist_px: float | None = None,
        pitch_px: float | None = None,
        gate_frac: float = 0.4,
        fill: str = "predict",
        reacquire_frac: float = 0.7,
        min_tracked_frac: float = 0.5,
        k: int = 6,
        grow_rounds: int = 4,
        velocity_gain: float = 1.0,
        reacquire_schedule: tuple[float, int, int] = FULL_SEARCH_SCHEDULE,
        reacquire: str = "inline",
    ) -> None:
        self.max_dist_px = None if max_dist_px is None else positive_number("max_dist_px", max_dist_px)
        self.pitch_px = None if pitch_px is None else positive_number("pitch_px", pitch_px)
        self.gate_frac = positive_number("gate_frac", gate_frac)
        if fill not in _FILL_MODES:
            raise ValueError(f"fill must be one of {_FILL_MODES}, got fill={fill!r}")
        self.fill = fill
        self.reacquire_frac = finite_number("reacquire_frac", reacquire_frac, 0, 1)
        self.min_tracked_frac = finite_number("min_tracked_frac", min_tracked_frac, 0, 1)
        self.k = whole_number("k", k, 1)
        self.grow_rounds = whole_number("grow_rounds", grow_rounds, 0)
        self.velocity_gain = finite_number("velocity_gain", velocity_gain, 0, 2)
        if not isinstance(reacquire_schedule, (tuple, list)) or len(reacquire_schedule) != 3:
            raise ValueError("reacquire_schedule must be (start_pitches, steps, sinkhorn_iters), "
                             f"got reacquire_schedule={reacquire_schedule!r}")
        self.reacquire_schedule = (positive_number("reacquire_schedule[0]", reacquire_schedule[0]),
                                   whole_number("reacquire_schedule[1]", reacquire_schedule[1], 1),
                                   whole_number("reacquire_schedule[2]", reacquire_schedule[2], 1))
        if reacquire not in _REACQUIRE_MODES:
            raise ValueError(f"reacquire must be one of {_REACQUIRE_MODES}, got reacquire={reacquire!r}")
        self.reacquire = reacquire
        self._job = None               # a background re-acquisition: (future, frame's state)
        self._pool = None
        self.reacquire_errors = 0      # background searches that raised (their frame kept)
        self.reacquisitions = 0        # frames the coarse search ran on, in all
        self.faults = FAULT_NO_REFERENCE
        self.n_tracked = 0
        self.reacquired = 0            # 1 when the last update ran the coarse re-acquisition
        self.idx = np.zeros(0, np.int64)
        self._ref: np.ndarray | None = None
        self._alloc(0)

    # -- reference -------------------------------------------------------------
    def _alloc(self, m: int) -> None:
        self._disp = np.zeros((m, 2), np.float64)     # last vectors
        self._vel = np.zeros((m, 2), np.float64)      # last change per frame
        self._pred = np.zeros((m, 2), np.float64)     # this frame's prediction
        self._work = np.zeros((m, 2), np.float64)
        self._vec = np.zeros((m, 2), np.float32)      # output buffer
        self._lost = np.ones(m, bool)
        self.idx = np.full(m, -1, np.int64)
        self._tctx = None              # the compiled update's context, built when first used
        self._tcap, self._tcur = 0, None   # its scratch copy of a frame's pins

    def __getstate__(self) -> dict:
        # tf_track's context holds the addresses of this object's own buffers, and a
        # worker thread's future cannot be copied: a copy takes any pending search's
        # answer first (as the next update would) and builds its own context
        self._settle()
        state = dict(self.__dict__)
        state.update(_tctx=None, _tkeep=None, _tcap=0, _tcur=None, _pool=None, _job=None)
        return state

    @property
    def has_reference(self) -> bool:
        return self._ref is not None

    @property
    def reference(self) -> np.ndarray | None:
        """A copy of the reference pins (m, 2) float32, or None."""
        return None if self._ref is None else self._ref.astype(np.float32)

    def set_reference(self, pins) -> None:
        """Make ``pins`` (m, 2) px the reference layout (rows with NaN/inf are dropped)."""
        r = as_points("pins", pins)
        r = r[usable_rows(r)]
        self._job = None                # a search for the old layout is dropped
        self._ref = np.ascontiguousarray(r)
        m = r.shape[0]
        pitch = self.pitch_px if self.pitch_px is not None else layout_pitch_px(r)
        self._pitch = pitch if pitch > 0 else (self.max_dist_px or 1.0) / self.gate_frac
        self._gate = self.max_dist_px if self.max_dist_px is not None else self.gate_frac * self._pitch
        self._nb, self._valid = layout_neighbours(r, self.k)
        self._fin = np.ones(m, bool)
        self._alloc(m)
        self._lost[:] = False
        self.n_tracked = m
        self.faults = 0

    def rezero(self, pins=None) -> None:
        """Re-zero: with ``pins``, same as :meth:`set_reference`; without, the
        current tracked positions become the reference, keeping the pin count
        and order (so feature vectors keep their layout)."""
        if pins is not None:
            self.set_reference(pins)
            return
        if self._ref is None:
            return
        self._settle()
        self._ref = self._ref + self._disp
        self._nb, self._valid = layout_neighbours(self._ref, self.k)
        self._tctx = None
        self._disp[:] = 0.0
        self._vel[:] = 0.0
        self._vec[:] = 0.0

    def _moved_from_prediction(self, ok: np.ndarray) -> float:
        """Median distance, px, between the tracked pins and their prediction."""
        if not ok.any():
            return 0.0
        d = self._work[ok] - self._pred[ok]
        return float(np.median(np.hypot(d[:, 0], d[:, 1])))

    # -- re-acquisition ----------------------------------------------------------
    def _advance(self, work: np.ndarray, lost: np.ndarray, n_ok: int, steps: int) -> None:
        """Move the prediction's state (last vectors, velocity) to this frame's ``work``.
        A frame with too few pins tracked (garbage, a gap) does not move it."""
        m = work.shape[0]
        if n_ok >= self.min_tracked_frac * m:
            adv = native.advance_fn()
            if adv is not None and work.dtype == np.float64 and work.flags.c_contiguous \
                    and lost.dtype == np.bool_ and lost.flags.c_contiguous:
                # the same steps, compiled (match.c's tf_advance)
                adv(work.ctypes.data, self._disp.ctypes.data, self._vel.ctypes.data,
                    lost.ctypes.data, m, 1.0 - _VEL_ALPHA, _VEL_ALPHA / steps, n_ok < m,
                    0.5 * self._pitch)
                return
            # exponential average of the change, so centroid noise is not
            # doubled into the prediction
            vel = self._vel
            vel *= 1.0 - _VEL_ALPHA
            np.subtract(work, self._disp, out=self._disp)              # the change, in place
            self._disp *= _VEL_ALPHA / steps                           # per frame
            vel += self._disp
            if n_ok < m:
                vel[lost] *= 0.8
            cap = 0.5 * self._pitch
            np.minimum(vel, cap, out=vel)
            np.maximum(vel, -cap, out=vel)
            np.copyto(self._disp, work)

    def _coarse_kwargs(self, pred: np.ndarray) -> dict:
        """The coarse annealed search's arguments besides the two point sets, bound
        now (a search on the worker thread never reads the tracker)."""
        a_start, a_steps, a_iters = self.reacquire_schedule
        return dict(init_disp_px=pred, neighbours=(self._nb, self._valid),
                    gate_frac=self._gate / self._pitch, coarse=True, grow_rounds=self.grow_rounds,
                    anneal_start=a_start, anneal_steps=a_steps, sinkhorn_iters=a_iters)

    def _coarse(self, r: np.ndarray, c: np.ndarray, pred: np.ndarray):
        """The coarse annealed search of one frame: (idx, displacements)."""
        return track_with_neighbours(r, c, self._pitch, **self._coarse_kwargs(pred))

    def _coarse_wins(self, work, idx, work2, idx2) -> bool:
        """Keep the answer whose pins move more like their neighbours (wrong
        assignments do not); the fast one on a tie."""
        q1 = neighbour_consistency(work, idx >= 0, self._nb, self._valid, self._gate)
        q2 = neighbour_consistency(work2, idx2 >= 0, self._nb, self._valid, self._gate)
        return q2 > q1

    def _start_coarse(self, r, c, idx, steps) -> None:
        """Start the coarse search of this frame on the worker thread, keeping what
        :meth:`_settle` needs to replay the frame with its answer."""
        if self._pool is None:
            from concurrent.futures import ThreadPoolExecutor
            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="tacfoot-reacquire")
        pred = self._pred.copy()
        fut = self._pool.submit(track_with_neighbours, r, c.copy(), self._pitch,
                                **self._coarse_kwargs(pred))
        self._job = (fut, self._work.copy(), idx.copy(), self._disp.copy(), self._vel.copy(), steps)

    def _settle(self) -> None:
        """Take a background search's answer (waiting for it if it is still running):
        when it wins, the state becomes what the inline search would have left."""
        job, self._job = self._job, None
        if job is None:
            return
        fut, work, idx, disp0, vel0, steps = job
        try:
            idx2, work2 = fut.result()
        except Exception:             # the frame keeps the fast answer
            self.reacquire_errors += 1
            return
        if self._coarse_wins(work, idx, work2, idx2):
            np.copyto(self._disp, disp0)
            np.copyto(self._vel, vel0)
            self._advance(work2, idx2 < 0, int(np.count_nonzero(idx2 >= 0)), steps)

    # -- the compiled update (match.c's tf_track) ---------------------------------
    _FILL_CODE = {"predict": 0, "hold": 1, "zero": 2}

    def _track_context(self, fn):
        """The integer and double contexts of tf_track for this reference, or None
        (a reference pin not finite: the numpy path)."""
        r = self._ref
        if not np.isfinite(r).all() or r.shape[0] == 0:
            return None
        nb = np.ascontiguousarray(self._nb, np.int64)
        valid = np.ascontiguousarray(self._valid, np.bool_)
        m = r.shape[0]
        self._tkeep = (r, nb, valid, np.empty(m, np.float64))
        ci = np.zeros(native.TRACK_SLOTS[0], np.int64)
        ci[3], ci[4] = r.ctypes.data, m
        ci[5], ci[6], ci[7], ci[8] = (self._pred.ctypes.data, self._vel.ctypes.data,
                                      self._disp.ctypes.data, self._work.ctypes.data)
        ci[9], ci[10], ci[11] = nb.ctypes.data, valid.ctypes.data, nb.shape[1]
        ci[12], ci[13] = self.grow_rounds, _FINAL_ROUNDS
        ci[15] = self._FILL_CODE[self.fill]
        ci[17], ci[18] = self._lost.ctypes.data, self._vec.ctypes.data
        ci[21] = self._tkeep[3].ctypes.data
        cd = np.array([self._gate, 0.0, self.reacquire_frac, self.min_tracked_frac,
                       self._pitch, 1.0 - _VEL_ALPHA, 0.0], np.float64)
        return ci, cd

    def compiled_args(self, steps: int):
        """tf_track's contexts made ready for a frame ``steps`` after the last one
        (``steps`` as :meth:`update` takes it), all but the current pins: ``(ci, cd,
        idx)``, ``idx`` the fresh (m,) buffer the kernel writes; None when the frame
        must take the numpy path (no library, no reference, a background search to
        take first, a reference pin not finite). Changes nothing the outputs read;
        :meth:`compiled_done` takes the kernel's answer (also the fused frame's,
        device.pi.vision.frame)."""
        fn = native.track_fn()
        if fn is None or self._job is not None or self._ref is None:
            return None
        if self._tctx is None:
            self._tctx = self._track_context(fn) or False
            self._tcap = 0             # a new context points at no scratch yet
        if self._tctx is False:
            return None
        steps = _steps(steps)
        ci, cd = self._tctx
        # the settings a caller may have changed since the context was made
        ci[12], ci[15] = self.grow_rounds, self._FILL_CODE[self.fill]
        cd[0], cd[2], cd[3] = self._gate, self.reacquire_frac, self.min_tracked_frac
        idx = np.empty(self._ref.shape[0], np.int64)
        ci[14], ci[16] = steps, idx.ctypes.data
        cd[1] = self.velocity_gain * steps
        cd[6] = _VEL_ALPHA / steps
        return ci, cd, idx

    def compiled_done(self, idx: np.ndarray):
        """After tf_track returned 0 on :meth:`compiled_args`' contexts: the update's
        counts and faults, and its (vectors, lost) as :meth:`update` returns them."""
        n_ok = int(self._tctx[0][19])
        self.reacquired = 0
        self.idx = idx
        self.n_tracked = n_ok
        self.faults = FAULT_TOO_FEW_PINS if n_ok < self.min_tracked_frac * self._ref.shape[0] else 0
        return self._vec.copy(), self._lost.copy()

    def _update_compiled(self, cur, steps: int):
        """The usual frame through tf_track: (vectors, lost), or None when the
        numpy path must take it (a jump, unusual input, no library)."""
        if not isinstance(cur, np.ndarray) or cur.dtype != np.float32 or cur.ndim != 2 \
                or cur.shape[1] != 2 or not cur.flags.c_contiguous:
            return None
        args = self.compiled_args(steps)
        if args is None:
            return None
        ci, cd, idx = args
        n = cur.shape[0]
        if n > self._tcap:             # the kernel's copy of the pins, grown as needed
            self._tcap = max(2 * n, 256)
            self._tcur = np.empty((self._tcap, 2), np.float64)
            ci[2] = self._tcur.ctypes.data
        ci[0], ci[1] = cur.ctypes.data, n
        if native.track_fn()(ci.ctypes.data, cd.ctypes.data) != 0:
            return None
        return self.compiled_done(idx)

    # -- per frame ---------------------------------------------------------------
    def update(self, cur, steps: int = 1, compiled: bool = True
               ) -> tuple[np.ndarray, np.ndarray]:
        """Track one frame's pins ``cur`` (n, 2) px, ``steps`` frames after the last
        one tracked (more than 1 when frames were dropped in between: the prediction
        goes that many frames ahead). ``compiled`` False goes straight to the numpy
        path (the fused frame, whose tf_track already handed this frame back).

        Returns ``vectors`` float32 (m, 2) (current minus reference position,
        px) and ``lost`` bool (m,). Both are fresh arrays (copies of the
        preallocated buffers), safe to keep.
        """
        if self._ref is None:
            self.faults = FAULT_NO_REFERENCE
            self.n_tracked = 0
            return np.zeros((0, 2), np.float32), np.zeros(0, bool)
        self._settle()
        self.reacquired = 0
        steps = _steps(steps)
        done = self._update_compiled(cur, steps) if compiled else None
        if done is not None:
            return done
        faults = 0
        cols = None
        searching = False              # a background search holds this frame's answer
        try:
            c = np.asarray(cur, dtype=np.float64)
            if c.ndim != 2 or c.shape[1] != 2:
                if c.size:
                    faults |= FAULT_BAD_INPUT
                c = np.zeros((0, 2))
        except (TypeError, ValueError):
            faults |= FAULT_BAD_INPUT
            c = np.zeros((0, 2))
        if not all_rows_usable(c):
            keep = usable_rows(c)
            cols = np.flatnonzero(keep)
            c = c[keep]
            faults |= FAULT_BAD_INPUT
        r = self._ref
        m = r.shape[0]
        # constant-velocity prediction: last vectors plus their last change
        np.multiply(self._vel, self.velocity_gain * steps, out=self._pred)
        self._pred += self._disp
        if m and c.shape[0]:
            idx, n_conf = match_and_grow(r, self._fin, c, self._pred, self._nb, self._valid,
                                          self._gate, self.grow_rounds, 2, self._work)
            n_ok = int(np.count_nonzero(idx >= 0))
            if (n_conf < self.reacquire_frac * m and c.shape[0] >= self.reacquire_frac * m
                    and (steps > 1 or n_ok < self.reacquire_frac * m
                         or self._moved_from_prediction(idx >= 0) > 0.8 * self._gate)):
                # Most pins are far from their prediction (a jump) and, unless frames
                # were dropped before this one, the neighbour growth either did not
                # find them or found them far from where they were predicted: track
                # the frame again with the coarse matching.
                self.reacquired = 1
                self.reacquisitions += 1
                if self.reacquire == "inline":
                    idx2, work2 = self._coarse(r, c, self._pred)
                    if self._coarse_wins(self._work, idx, work2, idx2):
                        idx, n_ok = idx2, int(np.count_nonzero(idx2 >= 0))
                        self._work[:] = work2
                else:
                    # beside the loop: this frame keeps the fast answer for the state
                    # (what the inline search keeps when it loses) and reports every
                    # pin lost at its prediction (too few pins: a fault); the next
                    # update takes the search's answer for this frame if it wins, as
                    # inline would, so every later frame is the inline one
                    self._start_coarse(r, c, idx, steps)
                    searching = True
        else:
            idx = np.full(m, -1, np.int64)
            self._work[:] = self._disp
            n_ok = 0
        lost = idx < 0
        # _work: measured vectors of tracked pins, the neighbour prediction (or
        # the last value) for lost ones. It is also the basis of next frame's
        # prediction, whatever ``fill`` reports. Velocity: the change since the last
        # frame (for lost pins the change of their prediction, damped so a
        # pin lost for long stops drifting), at most half a pitch per frame.
        # A frame with too few pins tracked (garbage, a gap) does not move
        # the prediction.
        self._advance(self._work, lost, n_ok, steps)
        if searching:
            # after a jump a pin found near its prediction can still be its neighbour
            # (a deformation beyond the pitch): no vector is trusted before the search
            # answers, so every pin is reported lost at its prediction
            lost = np.ones(m, bool)
            idx = np.full(m, -1, np.int64)
            n_ok = 0
            np.copyto(self._work, self._pred)
        if self.fill == "hold":
            np.copyto(self._vec, self._work, casting="unsafe", where=~lost[:, None])
        else:
            np.copyto(self._vec, self._work, casting="unsafe")
            if self.fill == "zero":
                self._vec[lost] = 0.0
        np.copyto(self._lost, lost)
        if cols is not None:
            idx = idx.copy()
            idx[~lost] = cols[idx[~lost]]
        self.idx = idx
        self.n_tracked = n_ok
        if n_ok < self.min_tracked_frac * m:
            faults |= FAULT_TOO_FEW_PINS
        self.faults = faults
        return self._vec.copy(), self._lost.copy()
