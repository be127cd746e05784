"""One-to-one pin matching and the argument checks the trackers share.

Points are float ``(x, y)`` pixels. An assignment is an int array ``idx`` of
shape ``(m,)``: ``idx[i]`` is the row of the second cloud that point ``i`` of the
first matches, or ``-1``. No point is used twice.

    match_pins     shortest distance with a gate, one to one (greedy by
                   distance, done as rounds of mutual nearest neighbours on
                   one matrix product)
    mutual_match   one round: pairs that are each other's nearest within a gate
"""

from __future__ import annotations

import threading

import numpy as np

from device.checks import positive_number

__all__ = ["match_pins", "match_pins_unchecked", "mutual_match", "pair_d2", "MAX_COORD_PX", "as_points", "usable_rows",
           "all_rows_usable"]


# --------------------------------------------------------------------------
# Argument checks
# --------------------------------------------------------------------------


def as_points(name: str, value) -> np.ndarray:
    """``value`` as a float64 (k, 2) array; raises ValueError naming ``name``."""
    a = np.asarray(value, dtype=np.float64)
    if a.ndim == 1 and a.size == 0:
        return np.zeros((0, 2), np.float64)
    if a.ndim != 2 or a.shape[1] != 2:
        raise ValueError(f"{name} must be an (n, 2) array of x, y px, got {name}.shape={a.shape!r}")
    return a


#: Coordinates beyond this (px) are treated like NaN: no camera is that large,
#: and squaring them would overflow.
MAX_COORD_PX = 1.0e6


def usable_rows(a: np.ndarray) -> np.ndarray:
    """Rows of an (k, 2) array that are finite and within +-MAX_COORD_PX."""
    with np.errstate(invalid="ignore"):
        return (np.abs(a) <= MAX_COORD_PX).all(axis=1)


def all_rows_usable(a: np.ndarray) -> bool:
    if a.size == 0:
        return True
    with np.errstate(invalid="ignore"):
        return bool(a.max() <= MAX_COORD_PX and a.min() >= -MAX_COORD_PX)


# --------------------------------------------------------------------------
# One-to-one matching
# --------------------------------------------------------------------------

#: Above this coordinate spread (px) the score matrices are float64, below it
#: float32 (half the memory traffic; score rounding ~0.015 px^2 at 500 px).
_F32_SPREAD_PX = 1024.0


class _Scratch(threading.local):
    """Per-thread score buffers for :func:`match_pins`, grown on demand.

    Fresh (m, n) matrices of a few hundred kB cost more in page faults than
    the arithmetic, so they are reused from call to call.
    """

    def __init__(self) -> None:
        self.bufs: dict = {}

    def get(self, key: str, size: int, dtype) -> np.ndarray:
        b = self.bufs.get((key, dtype))
        if b is None or b.size < size:
            b = np.empty(max(size, 64), dtype)
            self.bufs[(key, dtype)] = b
        return b[:size]


_SCRATCH = _Scratch()


def _homogeneous(r: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Columns ``ut = [x, y, 1]`` and ``vt = [2x, 2y, -|p|^2]`` of both sets (3, m+n).

    ``ut[:, a] . vt[:, b] = 2 p_a.p_b - |p_b|^2 = |p_a|^2 - |p_a - p_b|^2``, so a
    row argmax of ``ut[:, :m].T @ vt[:, m:]`` is each reference pin's nearest
    current pin. Both sets are first shifted to the first reference pin, for
    precision. Coordinates are kept as rows (x row, y row) so every numpy
    loop runs along the long axis.
    """
    m, n = r.shape[0], c.shape[0]
    k = m + n
    qt = _SCRATCH.get("qt", 2 * k, np.float64).reshape(2, k)
    sq = _SCRATCH.get("sq", k, np.float64)
    np.subtract(r.T, r[0, :, None], out=qt[:, :m])
    np.subtract(c.T, r[0, :, None], out=qt[:, m:])
    dt = np.float32 if max(qt.max(), -qt.min()) < _F32_SPREAD_PX else np.float64
    ut = _SCRATCH.get("ut", 3 * k, dt).reshape(3, k)
    vt = _SCRATCH.get("vt", 3 * k, dt).reshape(3, k)
    ut[:2] = qt
    ut[2] = 1.0
    np.multiply(qt, 2.0, out=vt[:2], casting="unsafe")
    np.multiply(qt[0], qt[0], out=sq)
    sq += qt[1] * qt[1]
    np.negative(sq, out=vt[2], casting="unsafe")
    return ut, vt


def pair_d2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Squared distances (m, n) between the rows of ``a`` (m, 2) and ``b`` (n, 2):
    ``(ax - bx)^2 + (ay - by)^2``, without a (m, n, 2) temporary."""
    dx = np.subtract.outer(a[:, 0], b[:, 0])
    dy = np.subtract.outer(a[:, 1], b[:, 1])
    dx *= dx
    dy *= dy
    dx += dy
    return dx


#: up to this many (reference, current) pairs the scores are exact squared
#: distances by broadcasting; above it, one matrix product (:func:`_homogeneous`)
_SMALL_PAIRS = 4096


def _match_finite(r: np.ndarray, c: np.ndarray, max_d2: float, idx: np.ndarray) -> None:
    """Greedy-by-distance one-to-one matching of finite points; writes ``idx`` in place.

    Fast path: when every reference pin's nearest current pin is different,
    each gets its first choice and that is the greedy answer. Otherwise rounds
    of mutual nearest neighbours give the same pairs as taking the globally
    closest free pair again and again: the closest free pair is always a
    mutual nearest pair, and a mutual nearest pair can never be taken away by
    a closer pair. Later rounds work on the still-free pins only, on
    sub-matrices of the same scores (a pin's score does not depend on the
    others).
    """
    m, n = r.shape[0], c.shape[0]
    small = m * n <= _SMALL_PAIRS
    if small:
        # few pairs (the tracker's re-searches for a handful of lost pins): the
        # exact negative squared distances, without the product's set-up
        s_rc = pair_d2(r, c)
        np.negative(s_rc, out=s_rc)
    else:
        ut, vt = _homogeneous(r, c)
        s_rc = _SCRATCH.get("s_rc", m * n, ut.dtype).reshape(m, n)
        np.matmul(ut[:, :m].T, vt[:, m:], out=s_rc)
    nn_r = s_rc.argmax(axis=1)
    if small:
        d2 = -s_rc.max(axis=1)             # the exact distances already
    else:
        d = r - c[nn_r]
        d *= d
        d2 = d[:, 0] + d[:, 1]
    reach = d2 <= max_d2
    hits = nn_r[reach]
    if np.bincount(hits, minlength=n).max(initial=0) <= 1:
        idx[reach] = hits
        return
    if small:
        s_cr = s_rc.T
    else:
        s_cr = _SCRATCH.get("s_cr", m * n, ut.dtype).reshape(n, m)
        np.matmul(ut[:, m:].T, vt[:, :m], out=s_cr)
    nn_c = s_cr.argmax(axis=1)
    rows = np.arange(m)
    cols = np.arange(n)
    while True:
        take = (nn_c[nn_r] == np.arange(rows.size)) & reach
        if not take.any():
            # Only (near-)exact ties get here, when rounding breaks the
            # symmetry of the two argmax passes: take the closest pair alone.
            take[int(np.argmin(np.where(reach, d2, np.inf)))] = True
        idx[rows[take]] = cols[nn_r[take]]
        # A reference pin whose nearest free pin is out of reach never matches.
        keep_r = reach & ~take
        if not keep_r.any():
            return
        keep_c = np.ones(cols.size, bool)
        keep_c[nn_r[take]] = False
        if not keep_c.any():
            return
        rows, cols = rows[keep_r], cols[keep_c]
        nn_r = s_rc[np.ix_(rows, cols)].argmax(axis=1)
        nn_c = s_cr[np.ix_(cols, rows)].argmax(axis=1)
        d = r[rows] - c[cols[nn_r]]
        d *= d
        d2 = d[:, 0] + d[:, 1]
        reach = d2 <= max_d2
        if not reach.any():
            return


def mutual_match(pred: np.ndarray, det: np.ndarray, gate_px: float) -> np.ndarray:
    """Index into ``det`` for each row of ``pred``, or -1: a pair is kept only when
    each is the other's nearest and they are within ``gate_px``. Stricter than
    :func:`match_pins` (no second choices), for labelling and measurement where a
    doubtful pair is better dropped. One to one by construction."""
    idx = np.full(len(pred), -1, np.int64)
    if len(pred) == 0 or len(det) == 0:
        return idx
    d2 = pair_d2(np.asarray(pred), np.asarray(det))
    fwd = d2.argmin(axis=1)
    back = d2.argmin(axis=0)
    rows = np.arange(len(pred))
    ok = (back[fwd] == rows) & (d2[rows, fwd] <= gate_px * gate_px)
    idx[ok] = fwd[ok]
    return idx


def match_pins_unchecked(ref: np.ndarray, cur: np.ndarray, max_dist_px: float) -> np.ndarray:
    """:func:`match_pins` for callers that already hold float64 (m, 2) and (n, 2)
    arrays of usable rows (finite, within ``MAX_COORD_PX``) and a positive gate:
    the same answer without the argument checks (the tracker's inner loop)."""
    idx = np.full(ref.shape[0], -1, np.int64)
    if ref.shape[0] and cur.shape[0]:
        _match_finite(ref, cur, max_dist_px * max_dist_px, idx)
    return idx


def match_pins(ref, cur, max_dist_px: float) -> np.ndarray:
    """One-to-one nearest matching of reference pins to current pins.

    ``ref`` (m, 2) and ``cur`` (n, 2) are pin centres in px; ``max_dist_px`` is
    the distance gate. Returns ``idx`` int64 (m,): for each reference pin the
    row of ``cur`` it is matched to, or -1 when no free current pin is within
    the gate (lost). Pairs are taken shortest first (greedy by distance), so
    no current pin is used twice and a pin is not swapped with a neighbour
    that is closer to someone else. Rows with NaN, inf or a coordinate beyond
    ``MAX_COORD_PX`` never match.
    ``m = 0`` or ``n = 0`` gives an empty / all -1 result. Distances that tie
    to within float32 rounding (below 0.1 px^2 for point sets up to 1024 px
    across; float64 beyond) are broken arbitrarily.
    """
    gate = positive_number("max_dist_px", max_dist_px)
    r = as_points("ref", ref)
    c = as_points("cur", cur)
    m = r.shape[0]
    idx = np.full(m, -1, np.int64)
    if m == 0 or c.shape[0] == 0:
        return idx
    if all_rows_usable(r) and all_rows_usable(c):
        _match_finite(r, c, gate * gate, idx)
        return idx
    ok_r = usable_rows(r)
    ok_c = usable_rows(c)
    if not ok_r.any() or not ok_c.any():
        return idx
    sub = np.full(int(ok_r.sum()), -1, np.int64)
    _match_finite(r[ok_r], c[ok_c], gate * gate, sub)
    hit = sub >= 0
    sub[hit] = np.flatnonzero(ok_c)[sub[hit]]
    idx[ok_r] = sub
    return idx
