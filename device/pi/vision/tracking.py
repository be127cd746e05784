"""Pin tracking: map reference pins to current pins, one to one.

Runs on the Pi (numpy + OpenCV only). Plain functions over arrays plus one small
state object (:class:`Tracker`) that holds the reference layout and the
preallocated per-frame buffers.

Conventions: points are float ``(x, y)`` pixels, ``ref`` is the reference
layout ``(m, 2)`` and ``cur`` the pins of the current frame ``(n, 2)``. An
assignment is an int array ``idx`` of shape ``(m,)``: ``idx[i]`` is the row of
``cur`` that reference pin ``i`` moved to, or ``-1`` when the pin is lost. No
current pin is ever used twice and a lost pin is never invented.

Stages::

    match_pins            shortest distance with a gate, one to one
                          (greedy by distance, done as rounds of mutual
                          nearest neighbours on one matrix product)
    track_with_neighbours for deformations larger than the pin pitch (deep
                          presses): an annealed soft one-to-one matching of
                          the two clouds (softassign) predicts every pin's
                          displacement; pins are matched at the predicted
                          positions, and lost pins are predicted again from
                          their tracked layout neighbours and matched again,
                          growing outward from confident matches
    Tracker               holds the reference; per frame predicts each pin
                          from its last displacement, corrects the prediction
                          from confidently tracked neighbours, matches, grows
                          into lost pins; finite vectors and lost flags always
"""

from __future__ import annotations

import math
import threading

import numpy as np

__all__ = [
    "match_pins",
    "mutual_match",
    "layout_neighbours",
    "layout_pitch_px",
    "track_with_neighbours",
    "Tracker",
    "FAULT_NO_REFERENCE",
    "FAULT_BAD_INPUT",
    "FAULT_TOO_FEW_PINS",
    "MAX_COORD_PX",
]

#: Tracker fault bits (``Tracker.faults``), from the one table in device.pi.faults:
#: FAULT_NO_REFERENCE (update() before set_reference(): empty outputs), FAULT_BAD_INPUT
#: (current pins not an (n, 2) array, or rows with NaN/inf/huge dropped),
#: FAULT_TOO_FEW_PINS (fewer than ``min_tracked_frac`` of the reference pins tracked)
from device.pi.faults import FAULT_BAD_INPUT, FAULT_NO_REFERENCE, FAULT_TOO_FEW_PINS  # noqa: E402


# --------------------------------------------------------------------------
# Argument checks
# --------------------------------------------------------------------------


def _points(name: str, value) -> np.ndarray:
    """``value`` as a float64 (k, 2) array; raises ValueError naming ``name``."""
    a = np.asarray(value, dtype=np.float64)
    if a.ndim == 1 and a.size == 0:
        return np.zeros((0, 2), np.float64)
    if a.ndim != 2 or a.shape[1] != 2:
        raise ValueError(f"{name} must be an (n, 2) array of x, y px, got {name}.shape={a.shape!r}")
    return a


def _positive(name: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{name} must be a number, got {name}={value!r}")
    v = float(value)
    if not math.isfinite(v) or v <= 0.0:
        raise ValueError(f"{name} must be a finite number > 0, got {name}={value!r}")
    return v


def _count(name: str, value, lo: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < lo:
        raise ValueError(f"{name} must be an integer >= {lo}, got {name}={value!r}")
    return int(value)


#: Coordinates beyond this (px) are treated like NaN: no camera is that large,
#: and squaring them would overflow.
MAX_COORD_PX = 1.0e6


def _usable(a: np.ndarray) -> np.ndarray:
    """Rows of an (k, 2) array that are finite and within +-MAX_COORD_PX."""
    with np.errstate(invalid="ignore"):
        return (np.abs(a) <= MAX_COORD_PX).all(axis=1)


def _all_usable(a: np.ndarray) -> bool:
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
    ut, vt = _homogeneous(r, c)
    s_rc = _SCRATCH.get("s_rc", m * n, ut.dtype).reshape(m, n)
    np.matmul(ut[:, :m].T, vt[:, m:], out=s_rc)
    nn_r = s_rc.argmax(axis=1)
    d = r - c[nn_r]
    d *= d
    d2 = d[:, 0] + d[:, 1]
    reach = d2 <= max_d2
    hits = nn_r[reach]
    if np.bincount(hits, minlength=n).max(initial=0) <= 1:
        idx[reach] = hits
        return
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
    d2 = ((pred[:, None, :] - det[None, :, :]) ** 2).sum(-1)
    fwd = d2.argmin(axis=1)
    back = d2.argmin(axis=0)
    rows = np.arange(len(pred))
    ok = (back[fwd] == rows) & (d2[rows, fwd] <= gate_px * gate_px)
    idx[ok] = fwd[ok]
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
    gate = _positive("max_dist_px", max_dist_px)
    r = _points("ref", ref)
    c = _points("cur", cur)
    m = r.shape[0]
    idx = np.full(m, -1, np.int64)
    if m == 0 or c.shape[0] == 0:
        return idx
    if _all_usable(r) and _all_usable(c):
        _match_finite(r, c, gate * gate, idx)
        return idx
    ok_r = _usable(r)
    ok_c = _usable(c)
    if not ok_r.any() or not ok_c.any():
        return idx
    sub = np.full(int(ok_r.sum()), -1, np.int64)
    _match_finite(r[ok_r], c[ok_c], gate * gate, sub)
    hit = sub >= 0
    sub[hit] = np.flatnonzero(ok_c)[sub[hit]]
    idx[ok_r] = sub
    return idx


# --------------------------------------------------------------------------
# Layout helpers
# --------------------------------------------------------------------------


def layout_pitch_px(ref) -> float:
    """Typical pin spacing of a layout: the median nearest-neighbour distance, px.

    Returns 0.0 for fewer than two finite pins.
    """
    r = _points("ref", ref)
    r = r[_usable(r)]
    if r.shape[0] < 2:
        return 0.0
    d2 = ((r[:, None, :] - r[None, :, :]) ** 2).sum(axis=2)
    np.fill_diagonal(d2, np.inf)
    return float(np.sqrt(np.median(d2.min(axis=1))))


def layout_neighbours(ref, k: int = 6, max_dist_px: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` nearest layout neighbours of every reference pin.

    Returns ``nb`` int64 (m, k) (indices into ``ref``; padded with the pin
    itself when the layout has fewer than k+1 pins) and ``valid`` bool (m, k):
    False for padding, for non-finite pins, and for neighbours further than
    twice the pin's own nearest-neighbour distance (so a rim pin does not
    borrow from across a gap, while the sparse outer rings of a radial layout
    still have neighbours) or than ``max_dist_px`` when given. Computed once
    per reference.
    """
    k = _count("k", k, 1)
    r = _points("ref", ref)
    m = r.shape[0]
    nb = np.tile(np.arange(m)[:, None], (1, k))
    valid = np.zeros((m, k), bool)
    if m < 2:
        return nb, valid
    cap2 = np.inf if max_dist_px is None else _positive("max_dist_px", max_dist_px) ** 2
    finite = _usable(r)
    rr = np.where(finite[:, None], r, 0.0)
    d2 = ((rr[:, None, :] - rr[None, :, :]) ** 2).sum(axis=2)
    d2[~finite, :] = np.inf
    d2[:, ~finite] = np.inf
    np.fill_diagonal(d2, np.inf)
    kk = min(k, m - 1)
    order = np.argsort(d2, axis=1, kind="stable")[:, :kk]
    dist2 = np.take_along_axis(d2, order, axis=1)
    nb[:, :kk] = order
    valid[:, :kk] = (dist2 <= 4.0 * dist2[:, :1]) & (dist2 <= cap2)
    return nb, valid


def _consistency(disp: np.ndarray, ok: np.ndarray, nb: np.ndarray, valid: np.ndarray, tol: float) -> int:
    """How many tracked pins move like their tracked neighbours (within ``tol`` px
    of their median displacement). Wrong assignments break this."""
    rows = np.flatnonzero(ok)
    if rows.size == 0:
        return 0
    med, count = _neighbour_median(disp, ok, nb, valid, rows)
    dev = disp[rows] - med
    good = (count > 0) & (dev[:, 0] * dev[:, 0] + dev[:, 1] * dev[:, 1] <= tol * tol)
    return int(np.count_nonzero(good))


def _neighbour_median(obs: np.ndarray, ok: np.ndarray, nb: np.ndarray, valid: np.ndarray,
                      rows: np.ndarray | None = None):
    """Per pin, the median of ``obs`` over its valid, tracked neighbours.

    ``obs`` (m, d) per-pin values (e.g. displacements), ``ok`` (m,) tracked
    flags; ``rows`` (r,) restricts the answer to those pins. Returns ``med``
    (r, d) (0 where no neighbour is tracked) and ``count`` (r,).
    """
    if rows is not None:
        nb = nb[rows]
        valid = valid[rows]
    use = valid & ok[nb]                                  # (r, k)
    count = use.sum(axis=1)
    med = np.zeros((nb.shape[0], obs.shape[1]), np.float64)
    has = np.flatnonzero(count)
    if has.size:
        vals = obs[nb[has]]                                # (h, k, d)
        vals[~use[has]] = np.inf                           # inf sorts last
        vals.sort(axis=1)
        c = count[has]
        ar = np.arange(has.size)
        med[has] = 0.5 * (vals[ar, (c - 1) // 2] + vals[ar, c // 2])
    return med, count


# --------------------------------------------------------------------------
# Large deformations
# --------------------------------------------------------------------------

#: Annealing schedule of the coarse soft matching, in units of the pin pitch.
_ANNEAL_START = 3.0
_ANNEAL_END = 0.1
#: Passes with the full gate over the pins the half-gate growth left lost.
_FINAL_ROUNDS = 4
#: Weight of the newest change in the tracker's exponentially averaged velocity.
_VEL_ALPHA = 0.5


def _anneal(ref: np.ndarray, use: np.ndarray, cur: np.ndarray, pitch: float, disp: np.ndarray,
            nb: np.ndarray, valid: np.ndarray, steps: int, sinkhorn_iters: int,
            outlier_sigmas: float, smooth: float, smooth_iters: int = 10) -> np.ndarray:
    """Coarse displacement field by annealed, smoothed soft one-to-one matching.

    Softassign with a smooth field (after Gold & Rangarajan's robust point
    matching): at temperature sigma every reference pin spreads a unit of
    mass over the current pins with weights exp(-d^2 / 2 sigma^2) around its
    predicted position; Sinkhorn row/column normalisation makes the weights
    nearly one-to-one (each current pin receives at most about one unit), with
    a slack that lets a pin further than ``outlier_sigmas`` sigma from
    everything stay unmatched. Each pin's target is the weighted mean of its
    current pins, with confidence w (its matched mass). The new field
    minimises  sum_i w_i |v_i - target_i|^2 + lam sum_edges |v_i - v_j|^2
    over the layout-neighbour graph, approximately: ``smooth_iters`` Jacobi
    sweeps started from the targets (so the smoothing reaches a few pins
    far), with lam = smooth * sigma / pitch: strong at first, small at the
    end.

    sigma falls geometrically from 3 pitches, where the whole cloud is matched
    to the whole cloud (a radial expansion or a shift by more than a pitch is
    found as such, which nearest-neighbour matching cannot do), to 0.1 pitch,
    where the weights are nearly hard. Without the smoothing the soft matching
    tends to the optimal-transport map, which has no curl: a twist, or a
    shear that fades towards the rim, is then partly absorbed by assigning
    rows of pins one place along. Pins with no mass (outliers) follow their
    neighbours. Rows not in ``use`` take no part (``valid`` must already
    exclude them). Returns the displacement field (m, 2) float64.
    """
    m, n = ref.shape[0], cur.shape[0]
    v = disp.copy()
    if m == 0 or n == 0:
        return v
    kappa = np.float32(math.exp(-0.5 * outlier_sigmas * outlier_sigmas))
    origin = cur.mean(axis=0)
    cur32 = (cur - origin).astype(np.float32)
    # squared distances by one product: [x, y, 1, |p|^2] . [-2cx, -2cy, |c|^2, 1]
    hp = np.ones((m, 4), np.float32)
    hc = np.ones((4, n), np.float32)
    hc[:2] = -2.0 * cur32.T
    hc[2] = (cur32 * cur32).sum(axis=1)
    col = np.ones(n, np.float32)
    k = np.empty((m, n), np.float32)
    # the neighbour graph as a dense (m, m) matrix: one product sums neighbours
    adj = np.zeros((m, m), np.float64)
    rows = np.repeat(np.arange(m), nb.shape[1])
    np.add.at(adj, (rows[valid.ravel()], nb.ravel()[valid.ravel()]), 1.0)
    deg = adj.sum(axis=1)
    for sigma in np.geomspace(_ANNEAL_START, _ANNEAL_END, steps) * pitch:
        pos = ref + v - origin
        hp[:, :2] = pos
        hp[:, 3] = (pos * pos).sum(axis=1)
        np.matmul(hp, hc, out=k)
        np.maximum(k, 0.0, out=k)              # rounding can dip below 0
        k *= np.float32(-0.5 / (sigma * sigma))
        np.exp(k, out=k)
        k[~use] = 0.0
        for _ in range(sinkhorn_iters):          # warm-started column scaling
            row = 1.0 / (k @ col + kappa)
            col = 1.0 / (k.T @ row + kappa)
        k *= row[:, None]
        k *= col[None, :]
        w = k.sum(axis=1, dtype=np.float64)    # matched mass of each pin, <= ~1
        wt = (k @ cur32).astype(np.float64) + w[:, None] * (origin - ref)   # w * (target - ref)
        has = w > 1e-12
        v[has] = wt[has] / w[has, None]        # the data term's own answer
        lam = smooth * sigma / pitch
        if lam <= 0.0:
            continue
        den = (w + lam * deg + 1e-12)[:, None]
        for _ in range(smooth_iters):           # Jacobi sweeps from the data
            v = (wt + lam * (adj @ v) + 1e-12 * v) / den
    return v


def track_with_neighbours(
    ref,
    cur,
    pitch_px: float,
    init_disp_px=None,
    neighbours: tuple[np.ndarray, np.ndarray] | None = None,
    gate_frac: float = 0.4,
    coarse: bool = True,
    anneal_steps: int = 16,
    sinkhorn_iters: int = 10,
    outlier_sigmas: float = 3.0,
    smooth: float = 1.0,
    grow_rounds: int = 12,
    min_support: int = 2,
) -> tuple[np.ndarray, np.ndarray]:
    """Track pins that may have moved further than their spacing.

    ``ref`` (m, 2) reference layout, ``cur`` (n, 2) current pins, px;
    ``pitch_px`` the layout's pin spacing (see :func:`layout_pitch_px`).
    ``init_disp_px`` (m, 2) is a prior displacement (e.g. the last frame's);
    ``neighbours`` the output of :func:`layout_neighbours` for ``ref`` (pass
    it to avoid recomputing it every frame).

    1. Coarse (``coarse=True``): annealed soft one-to-one matching of the two
       clouds, with a smooth displacement field over the layout-neighbour
       graph (weight ``smooth``; 0 turns the smoothing off), gives a
       predicted displacement for every pin, starting from ``init_disp_px``
       (see ``_anneal``). Without it the prediction is ``init_disp_px`` (or
       zero).
    2. Match the predicted positions with :func:`match_pins`, first with
       half the gate ``gate_frac * pitch_px`` (confident matches).
    3. Grow: each lost pin is predicted again from its tracked layout
       neighbours (needs ``min_support`` of them: its own prediction
       corrected by their median prediction error, or their median
       displacement when its own prediction disagrees with them by more
       than the gate) and the lost pins are matched one to one against the
       free current pins at those positions; repeated (up to
       ``grow_rounds``), so tracking grows outward from the confident
       matches. A few last passes use the full gate.

    Returns ``idx`` int64 (m,) (row of ``cur`` or -1 when lost) and
    ``disp_px`` float64 (m, 2): measured for tracked pins; for lost pins the
    neighbour prediction (or the coarse / prior prediction when no neighbour
    is tracked), so every value is finite. Rows with NaN, inf or a
    coordinate beyond ``MAX_COORD_PX`` are treated as absent; ``idx`` indexes
    the caller's ``cur``. Bad arguments raise ValueError naming the field.
    """
    pitch = _positive("pitch_px", pitch_px)
    gate_frac = _positive("gate_frac", gate_frac)
    anneal_steps = _count("anneal_steps", anneal_steps, 1)
    sinkhorn_iters = _count("sinkhorn_iters", sinkhorn_iters, 1)
    outlier_sigmas = _positive("outlier_sigmas", outlier_sigmas)
    if isinstance(smooth, bool) or not isinstance(smooth, (int, float, np.integer, np.floating)) or not (
            math.isfinite(float(smooth)) and float(smooth) >= 0.0):
        raise ValueError(f"smooth must be a finite number >= 0, got smooth={smooth!r}")
    grow_rounds = _count("grow_rounds", grow_rounds, 0)
    min_support = _count("min_support", min_support, 1)
    r = _points("ref", ref)
    c = _points("cur", cur)
    m = r.shape[0]
    fin_r = _usable(r)
    r = np.where(fin_r[:, None], r, 0.0)
    cols = None
    if not _all_usable(c):
        keep = _usable(c)
        cols = np.flatnonzero(keep)
        c = c[keep]
    if init_disp_px is None:
        pred = np.zeros((m, 2))
    else:
        pred = _points("init_disp_px", init_disp_px)
        if pred.shape[0] != m:
            raise ValueError(
                f"init_disp_px must have one row per reference pin ({m}), got init_disp_px.shape={pred.shape!r}"
            )
        pred = np.where(_usable(pred)[:, None], pred, 0.0)
    if neighbours is None:
        nb, valid = layout_neighbours(r)
    else:
        nb, valid = neighbours
        if nb.shape[0] != m or valid.shape != nb.shape:
            raise ValueError(f"neighbours must be layout_neighbours(ref), got shapes {nb.shape!r}, {valid.shape!r}")
    valid = valid & fin_r[nb] & fin_r[:, None]
    idx = np.full(m, -1, np.int64)
    if m == 0 or c.shape[0] == 0:
        return idx, pred
    if coarse:
        pred = _anneal(r, fin_r, c, pitch, pred, nb, valid, anneal_steps, sinkhorn_iters,
                       outlier_sigmas, float(smooth))
        pred[~fin_r] = 0.0
    idx[:] = _match_and_grow(r, fin_r, c, pred, nb, valid, gate_frac * pitch, grow_rounds, min_support,
                             pred)[0]
    if cols is not None:
        hit = idx >= 0
        idx[hit] = cols[idx[hit]]
    return idx, pred


def _match_and_grow(r, fin_r, c, pred, nb, valid, gate, grow_rounds, min_support, disp):
    """Match predicted positions, then grow into lost pins from tracked neighbours.

    1. Confident matches: :func:`match_pins` with half the gate (a wrong pin
       is that close only when a pin moved by about half its spacing more
       than predicted). When that catches fewer than half of the pins, the
       predictions shifted by the median offset of wide-gate matches are
       tried as well (a sudden common jump: a lift, a slip).
    2. Grow: every lost pin with ``min_support`` tracked layout neighbours is
       predicted again from them - its own prediction corrected by their
       median prediction error, or, when that is more than the gate away
       from their median displacement (its own prediction was bad), that
       median displacement - and matched one to one against the free current
       pins with half the gate. Repeated, so tracking grows outward from the
       confident matches (about one ring of pins per round), up to
       ``grow_rounds`` times, while it finds pins.
    3. Every pin still lost is matched once more with the full gate: at its
       neighbour prediction, or, when the growth never reached it, at its own
       prediction corrected by the median error of all tracked pins.

    ``disp`` (m, 2) float64 is written in place (it may be ``pred``): the
    measured displacement of tracked pins and the best prediction of lost
    ones. Returns ``idx`` and the number of confident matches of step 1.
    """
    prior = np.array(pred, dtype=np.float64)            # the caller's prediction, kept
    prior[~fin_r] = 0.0
    pos = r + prior
    pos[~fin_r] = np.nan
    disp[:] = prior
    idx = match_pins(pos, c, 0.5 * gate)
    ok = idx >= 0
    n_ok = int(np.count_nonzero(ok))
    if n_ok < 0.5 * np.count_nonzero(fin_r):
        # A common jump (a lift, a slip): shift every prediction by the median
        # offset of one-to-one matches with a wide gate (robust to pins
        # entering or leaving the view, unlike the shift of the centroids).
        # Kept when it catches more pins confidently and keeps most of the
        # pins already caught (a prior that is right for part of the layout
        # is not overruled by the rest).
        wide = match_pins(pos, c, 1.25 * gate)
        hit = wide >= 0
        if hit.any():
            shift = np.median(c[wide[hit]] - pos[hit], axis=0)
            idx2 = match_pins(pos + shift, c, 0.5 * gate)
            ok2 = idx2 >= 0
            n2 = int(np.count_nonzero(ok2))
            kept = int(np.count_nonzero(idx2[ok] == idx[ok]))
            if n2 > n_ok and 2 * kept >= n_ok:
                prior += shift
                pos += shift
                idx, ok, n_ok = idx2, ok2, n2
    n_confident = n_ok
    disp[:] = prior
    disp[ok] = c[idx[ok]] - r[ok]
    err = disp - prior                                   # prediction error (0 for lost pins)
    free = np.ones(c.shape[0], bool)
    free[idx[ok]] = False

    def predict(rows):
        """Neighbour predictions of lost ``rows``: written to disp; returns support mask."""
        med, count = _neighbour_median(np.hstack([err, disp]), ok, nb, valid, rows)
        sup = count >= min_support
        if sup.any():
            s_rows = rows[sup]
            own = prior[s_rows] + med[sup, :2]
            med_disp = med[sup, 2:]
            dev = own - med_disp
            agree = dev[:, 0] * dev[:, 0] + dev[:, 1] * dev[:, 1] <= gate * gate
            disp[s_rows] = np.where(agree[:, None], own, med_disp)
        return sup

    def take(rows, g):
        """Match ``rows`` at disp against the free pins (gate g); returns the rows caught."""
        fc = np.flatnonzero(free)
        sub = match_pins(r[rows] + disp[rows], c[fc], g)
        hit = sub >= 0
        got = rows[hit]
        idx[got] = fc[sub[hit]]
        ok[got] = True
        free[idx[got]] = False
        disp[got] = c[idx[got]] - r[got]
        err[got] = disp[got] - prior[got]
        return got

    n_pred = -1                       # tracked count when the lost pins were last predicted
    sup = None
    for _ in range(grow_rounds):
        lost = np.flatnonzero(~ok & fin_r)
        if lost.size == 0 or not ok.any():
            break
        sup = predict(lost)
        n_pred = int(np.count_nonzero(ok))
        if not sup.any() or not free.any() or take(lost[sup], 0.5 * gate).size == 0:
            break
    for _ in range(_FINAL_ROUNDS):
        # last passes over every pin still lost: the neighbour prediction where
        # there is one, else the pin's own prediction corrected by the median
        # error of all tracked pins; the full gate
        lost = np.flatnonzero(~ok & fin_r)
        n_now = int(np.count_nonzero(ok))
        if lost.size == 0 or n_now == 0:
            break
        if n_now != n_pred:
            sup = predict(lost)
            n_pred = n_now
        if n_now >= 3:                                  # a common error needs a few pins
            far = lost[~sup]
            disp[far] = prior[far] + np.median(err[ok], axis=0)
        if not free.any() or take(lost, gate).size == 0:
            break
    return idx, n_confident


# --------------------------------------------------------------------------
# Per-frame state
# --------------------------------------------------------------------------

_FILL_MODES = ("predict", "hold", "zero")


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
    prediction (a jump, or the first frame after a long gap) the frame is
    tracked again with the coarse annealed matching of
    :func:`track_with_neighbours`, and of the two answers the one whose
    pins move more like their layout neighbours is kept.

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
    matched to (-1 lost) and ``n_tracked`` their number.

    Parameters: ``max_dist_px`` the matching gate (default ``gate_frac`` x
    the layout pitch); ``pitch_px`` the pin spacing (default: measured from
    the reference; give it, or ``max_dist_px``, for a one-pin reference);
    ``velocity_gain`` how much of each pin's last change per frame is added
    to its prediction (constant-velocity model; 0 predicts the last value);
    ``k`` neighbours per pin for the predictions; ``grow_rounds`` how many
    rings of lost pins the neighbour prediction may grow into per frame.

    Cost per frame in steady state is one :func:`match_pins` call plus a few
    small array operations; buffers are allocated in :meth:`set_reference`
    only (``match_pins`` keeps its own per-thread scratch). The coarse
    re-acquisition costs about a hundred times more and only runs after a
    jump.
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
    ) -> None:
        self.max_dist_px = None if max_dist_px is None else _positive("max_dist_px", max_dist_px)
        self.pitch_px = None if pitch_px is None else _positive("pitch_px", pitch_px)
        self.gate_frac = _positive("gate_frac", gate_frac)
        if fill not in _FILL_MODES:
            raise ValueError(f"fill must be one of {_FILL_MODES}, got fill={fill!r}")
        self.fill = fill
        for name, v in (("reacquire_frac", reacquire_frac), ("min_tracked_frac", min_tracked_frac)):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (0.0 <= float(v) <= 1.0):
                raise ValueError(f"{name} must be a number in [0, 1], got {name}={v!r}")
        self.reacquire_frac = float(reacquire_frac)
        self.min_tracked_frac = float(min_tracked_frac)
        self.k = _count("k", k, 1)
        self.grow_rounds = _count("grow_rounds", grow_rounds, 0)
        if isinstance(velocity_gain, bool) or not isinstance(velocity_gain, (int, float)) or not (
                0.0 <= float(velocity_gain) <= 2.0):
            raise ValueError(f"velocity_gain must be a number in [0, 2], got velocity_gain={velocity_gain!r}")
        self.velocity_gain = float(velocity_gain)
        self.faults = FAULT_NO_REFERENCE
        self.n_tracked = 0
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

    @property
    def has_reference(self) -> bool:
        return self._ref is not None

    @property
    def reference(self) -> np.ndarray | None:
        """A copy of the reference pins (m, 2) float32, or None."""
        return None if self._ref is None else self._ref.astype(np.float32)

    def set_reference(self, pins) -> None:
        """Make ``pins`` (m, 2) px the reference layout (rows with NaN/inf are dropped)."""
        r = _points("pins", pins)
        r = r[_usable(r)]
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
        self._ref = self._ref + self._disp
        self._nb, self._valid = layout_neighbours(self._ref, self.k)
        self._disp[:] = 0.0
        self._vel[:] = 0.0
        self._vec[:] = 0.0

    # -- per frame ---------------------------------------------------------------
    def update(self, cur) -> tuple[np.ndarray, np.ndarray]:
        """Track one frame's pins ``cur`` (n, 2) px.

        Returns ``vectors`` float32 (m, 2) (current minus reference position,
        px) and ``lost`` bool (m,). Both are fresh arrays (copies of the
        preallocated buffers), safe to keep.
        """
        if self._ref is None:
            self.faults = FAULT_NO_REFERENCE
            self.n_tracked = 0
            return np.zeros((0, 2), np.float32), np.zeros(0, bool)
        faults = 0
        cols = None
        try:
            c = np.asarray(cur, dtype=np.float64)
            if c.ndim != 2 or c.shape[1] != 2:
                if c.size:
                    faults |= FAULT_BAD_INPUT
                c = np.zeros((0, 2))
        except (TypeError, ValueError):
            faults |= FAULT_BAD_INPUT
            c = np.zeros((0, 2))
        if not _all_usable(c):
            keep = _usable(c)
            cols = np.flatnonzero(keep)
            c = c[keep]
            faults |= FAULT_BAD_INPUT
        r = self._ref
        m = r.shape[0]
        # constant-velocity prediction: last vectors plus their last change
        np.multiply(self._vel, self.velocity_gain, out=self._pred)
        self._pred += self._disp
        if m and c.shape[0]:
            idx, n_conf = _match_and_grow(r, self._fin, c, self._pred, self._nb, self._valid,
                                          self._gate, self.grow_rounds, 2, self._work)
            n_ok = int(np.count_nonzero(idx >= 0))
            if n_conf < self.reacquire_frac * m and c.shape[0] >= self.reacquire_frac * m:
                # Most pins are far from their prediction (a jump): track the
                # frame again with the coarse matching as well.
                idx2, work2 = track_with_neighbours(
                    r, c, self._pitch, init_disp_px=self._pred, neighbours=(self._nb, self._valid),
                    gate_frac=self._gate / self._pitch, coarse=True, grow_rounds=self.grow_rounds)
                # keep the answer whose pins move more like their neighbours
                # (wrong assignments do not), the first one on a tie
                q1 = _consistency(self._work, idx >= 0, self._nb, self._valid, self._gate)
                q2 = _consistency(work2, idx2 >= 0, self._nb, self._valid, self._gate)
                if q2 > q1:
                    idx, n_ok = idx2, int(np.count_nonzero(idx2 >= 0))
                    self._work[:] = work2
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
        if n_ok >= self.min_tracked_frac * m:
            # exponential average of the change, so centroid noise is not
            # doubled into the prediction
            self._vel *= 1.0 - _VEL_ALPHA
            self._vel += _VEL_ALPHA * (self._work - self._disp)
            self._vel[lost] *= 0.8
            np.clip(self._vel, -0.5 * self._pitch, 0.5 * self._pitch, out=self._vel)
            np.copyto(self._disp, self._work)
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
