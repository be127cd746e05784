"""Training windows as a camera of another frame rate would deliver them.

The texture model reads T consecutive frames, so its frame-to-frame changes are per
frame, not per second: a recording taken at 120 fps (or one that drops frames)
shows the same surface as larger changes than one taken at 200 fps, and a model
trained on one rate misreads the other (``python -m host.bench.texture_robust``:
Lego at 3 of 5 frames fell to 0.20). :func:`augment_rates` adds copies of the
training windows re-cut from the same recording with only some frames kept, so
the model sees each surface at several frame intervals:

``3of5``         frames 0, 2, 3 of every 5 (200 fps replayed as 120 fps);
``3of5+drop10``  that, then 10 % of the kept frames dropped at random (seeded).

The frames of a trial are read back from its overlapping windows (each window holds
its T frames; ``t_index`` places its last frame in the trial), so no recording is
read again. A re-cut window ends on a frame of an original window, keeps its label
and contact flag, and is cut only where all its T kept frames are known.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from host.learn.tasks import TrainError

__all__ = ["RATE_KEEPS", "kept_frames", "augment_rates"]

#: the frame-keeping rules of the copies :func:`augment_rates` adds by default
RATE_KEEPS = ("3of5", "3of5+drop10")


def kept_frames(n: int, keep: str, seed: int = 0) -> np.ndarray:
    """The frame indices 0..n-1 a camera of rule ``keep`` delivers (``all``,
    ``3of5``, ``3of5+dropP`` with P percent of those dropped at random with
    ``seed``)."""
    idx = np.arange(int(n), dtype=np.int64)
    if keep == "all":
        return idx
    if keep == "3of5" or keep.startswith("3of5+drop"):
        idx = idx[np.isin(idx % 5, (0, 2, 3))]
        if keep == "3of5":
            return idx
        try:
            p = float(keep[len("3of5+drop"):]) / 100.0
        except ValueError:
            p = -1.0
        if not 0.0 <= p < 1.0:
            raise TrainError(f"keep={keep!r}: the drop share must be 0..99 percent")
        drop = np.random.default_rng(seed).random(len(idx)) < p
        return idx[~drop]
    raise TrainError(f"keep must be 'all', '3of5' or '3of5+dropP', got keep={keep!r}")


#: the per-frame parts of a window that are re-cut (the others are per window)
_PER_FRAME = ("vectors", "lost", "imu")


def _trial_frames(ws, rows: np.ndarray):
    """(first frame, {part: (F, ...) per frame}, known (F,)) of one trial from its
    windows ``rows``."""
    T = ws.window
    ends = ws.t_index[rows]
    lo, hi = int(ends.min()) - T + 1, int(ends.max()) + 1
    F = hi - lo
    per = {k: np.zeros((F,) + getattr(ws, k).shape[2:], getattr(ws, k).dtype)
           for k in _PER_FRAME if getattr(ws, k) is not None}
    known = np.zeros(F, bool)
    for r, e in zip(rows, ends):
        a = int(e) - T + 1 - lo
        for k, buf in per.items():
            buf[a:a + T] = getattr(ws, k)[r]
        known[a:a + T] = True
    return lo, per, known


def augment_rates(ws, keeps=RATE_KEEPS, seed: int = 0):
    """``ws`` plus, for each rule in ``keeps``, its windows re-cut from their trials
    with only the frames that rule keeps (module doc). Windows without a time order
    (``t_index`` < 0) are not re-cut. ``vectors`` layout: grids and frame crops are
    left out of the result, as in :func:`host.learn.inputs.augment_rotations`."""
    T = ws.window
    if ws.vectors is None:
        raise TrainError("augment_rates needs windows with pin vectors")
    keeps = tuple(keeps)
    parts = [replace(ws, grids=None, frames=None)]
    timed = np.asarray(ws.t_index) >= 0
    for k, keep in enumerate(keeps):
        picks, cut = [], {p: [] for p in _PER_FRAME}
        for g in np.unique(ws.groups[timed]):
            rows = np.flatnonzero(timed & (ws.groups == g))
            lo, per, known = _trial_frames(ws, rows)
            kept = kept_frames(lo + len(known), keep, seed + 7919 * k + int(g))
            kept = kept[kept >= lo]
            pos = {int(f): i for i, f in enumerate(kept)}
            for r in rows:
                i = pos.get(int(ws.t_index[r]))
                if i is None or i < T - 1:
                    continue
                frames = kept[i - T + 1:i + 1] - lo
                if not known[frames].all():
                    continue
                picks.append(r)
                for p, buf in per.items():
                    cut[p].append(buf[frames])
        if not picks:
            continue
        sub = ws.subset(np.asarray(picks, np.int64))
        parts.append(replace(sub, grids=None, frames=None,
                             **{p: np.stack(v) for p, v in cut.items() if v}))
    if len(parts) == 1:
        return parts[0]
    cat = {}
    for name in ("vectors", "lost", "imu", "contact", "labels", "targets", "groups", "t_index",
                 "trial_len", "recordings", "frame_index", "session"):
        vals = [getattr(p, name) for p in parts]
        cat[name] = None if any(v is None for v in vals) else np.concatenate(vals)
    return replace(ws, **cat, grids=None, frames=None,
                   source=dict(ws.source, augmented_rates=list(keeps)))
