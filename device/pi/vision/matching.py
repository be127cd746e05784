"""One-to-one pin matching and the argument checks the trackers share.

Points are float ``(x, y)`` pixels. An assignment is an int array ``idx`` of
shape ``(m,)``: ``idx[i]`` is the row of the second cloud that point ``i`` of the
first matches, or ``-1``. No point is used twice.

    match_pins     shortest distance with a gate, one to one (greedy by
                   distance, done as rounds of mutual best pairs among the
                   pairs within the gate, found on a cell grid)
    mutual_match   one round: pairs that are each other's nearest within a gate

``match_pins`` runs compiled (:mod:`device.pi.vision.native`, built on the leg)
when the library is built, with the same assignment as the numpy code here.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from device.checks import positive_number
from device.pi.vision import native

__all__ = ["match_pins", "match_pins_unchecked", "mutual_match", "pair_d2", "gated_pairs",
           "MAX_COORD_PX", "as_points", "usable_rows", "all_rows_usable"]


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

def pair_d2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Squared distances (m, n) between the rows of ``a`` (m, 2) and ``b`` (n, 2):
    ``(ax - bx)^2 + (ay - by)^2``, without a (m, n, 2) temporary."""
    dx = np.subtract.outer(a[:, 0], b[:, 0])
    dy = np.subtract.outer(a[:, 1], b[:, 1])
    dx *= dx
    dy *= dy
    dx += dy
    return dx


#: up to this many (reference, current) pairs every pair is scored (one small
#: matrix, the tracker's re-searches for a handful of lost pins); above it only
#: the pairs a cell grid puts within the gate (:func:`gated_pairs`)
_SMALL_PAIRS = 4096
#: cells are this much wider than the gate, so float rounding of the cell
#: coordinates can never put a pair within the gate two cells apart
_CELL_MARGIN = 1.0 + 1e-6
#: up to this many current pins in one range (a column of three cells) the ranges
#: are read as a fixed-width table (fewer numpy calls); beyond, one by one
_FIXED_WIDTH = 4
#: at most this many cells along an axis of the +-MAX_COORD_PX square: the keys
#: (float64) stay exact integers, and cells are never narrower than about 2e6 / 2^21 px
_MAX_CELLS = float(1 << 21)


@functools.lru_cache(maxsize=16)
def _grid(max_d2: float) -> tuple[float, np.ndarray, np.ndarray]:
    """The cell grid's constants for a gate: 1 / cell width, the key fold [ny, 1]
    and the six key offsets of the three cell columns' ranges (start, start, start,
    end, end, end). Cell coordinates run from -1e6 / cell - 1 to 1e6 / cell, so a
    key column of ny cells holds every row with a free cell at each end."""
    cell = max(math.sqrt(max_d2) * _CELL_MARGIN, 2.0 * MAX_COORD_PX / (_MAX_CELLS - 6.0))
    ny = math.floor(2.0 * MAX_COORD_PX / cell) + 5.0
    fold = np.array([ny, 1.0])
    ranges = np.array([-ny - 1.0, -1.0, ny - 1.0, 2.0 - ny, 2.0, ny + 2.0])
    fold.flags.writeable = False
    ranges.flags.writeable = False
    return 1.0 / cell, fold, ranges


#: np.arange(k) for the fixed-width table's widths
_WIDTHS = tuple(np.arange(k) for k in range(_FIXED_WIDTH + 1))


def gated_pairs(r: np.ndarray, c: np.ndarray, max_d2: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every pair of a row of ``r`` (m, 2) and a row of ``c`` (n, 2), both usable
    (finite, within +-MAX_COORD_PX), with squared distance <= ``max_d2``:
    ``rows``, ``cols`` (int64) and ``d2`` (float64), ``rows`` ascending.

    A cell grid with cells about one gate wide: the current pins are sorted by
    cell key, and each reference pin looks up its own and the eight
    neighbouring cells as three key ranges (a column of three cells is
    contiguous in the key order), by binary search. The work is
    O((m + n) log n) plus the number of candidate pairs, not O(m n). ``d2``
    is ``(rx - cx)^2 + (ry - cy)^2``, the same numbers as :func:`pair_d2`.
    """
    m = r.shape[0]
    inv, fold, ranges = _grid(max_d2)
    # cell coordinates of both sets (|k| <= 1e6 / cell + 1), folded into one key
    # kx * ny + ky: exact integers in float64, the rows of a column contiguous
    t = np.concatenate((r, c))
    t *= inv
    np.floor(t, out=t)
    key = t @ fold
    order = np.argsort(key[m:], kind="stable")
    sk = key[m:][order]
    # each reference pin's cell columns kx-1, kx, kx+1, each from ky-1 to ky+1: the
    # keys from q - 1 to q + 1, q = key + dx * ny (start and end of each range)
    q = key[:m, None] + ranges
    ab = np.searchsorted(sk, q)
    cnt = ab[:, 3:] - ab[:, :3]                       # (m, 3) pins in each range
    width = int(cnt.max(initial=0))
    if width == 0:
        e = np.zeros(0, np.int64)
        return e, e, np.zeros(0, np.float64)
    if width <= _FIXED_WIDTH:
        # few pins per range (the usual case): a fixed-width (m, 3, width) table of
        # the ranges' positions, masked by the counts
        j = _WIDTHS[width]
        sel = cnt[:, :, None] > j
        rows = np.nonzero(sel)[0]
        cols = order[(ab[:, :3, None] + j)[sel]]
    else:
        # crowded cells (duplicates, a gate much wider than the spacing): the ranges
        # expanded one by one, so the work stays the number of candidate pairs
        cnt = cnt.ravel()
        a = ab[:, :3].ravel()
        rows = np.repeat(np.arange(m), cnt.reshape(m, 3).sum(axis=1))
        start = np.cumsum(cnt)
        start -= cnt
        a -= start
        cols = order[np.repeat(a, cnt) + np.arange(int(start[-1] + cnt[-1]))]
    d = r[rows] - c[cols]
    d *= d
    d2 = d[:, 0] + d[:, 1]
    keep = d2 <= max_d2
    return rows[keep], cols[keep], d2[keep]


def _greedy_pairs(rows: np.ndarray, cols: np.ndarray, d2: np.ndarray, m: int, n: int,
                  idx: np.ndarray) -> None:
    """Greedy-by-distance one-to-one choice among candidate pairs; writes ``idx``.

    ``rows`` must come grouped (equal values together). Pairs are ranked by
    ``d2``, ties by their order in the arrays (a strict order). Fast paths:
    every pin has at most one candidate and none is shared; or every
    reference pin's best pair goes to a different current pin (that is the
    greedy answer). Otherwise rounds of
    mutual best pairs give the same pairs as taking the best free pair again
    and again: the best free pair is always mutually best, and a mutually
    best pair can never be taken away by a better one. Each round takes at
    least the best remaining pair and drops the pairs of pins taken.
    """
    k = d2.size
    if k == 0:
        return
    # the common case (a gate well under the pin spacing): every pin has at most one
    # candidate (rows come grouped) and no candidate is shared
    if (k == 1 or bool((rows[1:] != rows[:-1]).all())) and np.bincount(cols).max() <= 1:
        idx[rows] = cols
        return
    rank = np.empty(k, np.int64)
    rank[np.argsort(d2, kind="stable")] = np.arange(k)
    best_r = np.full(m, k, np.int64)
    np.minimum.at(best_r, rows, rank)
    first = rank == best_r[rows]                           # each row's best pair
    hits = cols[first]
    if np.bincount(hits, minlength=n).max() <= 1:
        idx[rows[first]] = hits
        return
    free_r = np.ones(m, bool)
    free_c = np.ones(n, bool)
    while True:
        best_c = np.full(n, k, np.int64)
        np.minimum.at(best_c, cols, rank)
        take = first & (rank == best_c[cols])
        tr, tc = rows[take], cols[take]
        idx[tr] = tc
        free_r[tr] = False
        free_c[tc] = False
        keep = free_r[rows] & free_c[cols]
        if not keep.any():
            return
        rows, cols, rank = rows[keep], cols[keep], rank[keep]
        best_r = np.full(m, k, np.int64)
        np.minimum.at(best_r, rows, rank)
        first = rank == best_r[rows]


def _match_finite(r: np.ndarray, c: np.ndarray, max_d2: float, idx: np.ndarray) -> None:
    """Greedy-by-distance one-to-one matching of finite points; writes ``idx`` in place.

    The compiled kernel (:mod:`device.pi.vision.native`) when it is built, with
    the same assignment; otherwise numpy. Few pairs: every pair is scored
    (:func:`pair_d2`); many: only the pairs within the gate, found on a cell grid
    (:func:`gated_pairs`), so the cost grows with the pin count, not with its
    square. Either way the pairs are the exact squared distances, and the choice
    is :func:`_greedy_pairs`.
    """
    if native.match_into(r, c, max_d2, idx):
        return
    m, n = r.shape[0], c.shape[0]
    if m * n <= _SMALL_PAIRS:
        d2 = pair_d2(r, c).ravel()
        near = np.flatnonzero(d2 <= max_d2)
        if near.size == 0:
            return
        rows, cols = np.divmod(near, n)
        d2 = d2[near]
    else:
        rows, cols, d2 = gated_pairs(r, c, max_d2)
    _greedy_pairs(rows, cols, d2, m, n, idx)


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
    ``m = 0`` or ``n = 0`` gives an empty / all -1 result. Distances are exact
    float64; pairs at exactly the same distance are taken in an arbitrary but
    fixed order. The cost grows with m + n (only pairs within the gate are
    scored, see :func:`gated_pairs`), not with m x n.
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
