"""Layout neighbours and tracking through deformations larger than the pin pitch.

Deep presses move pins further than the pin spacing, so nearest-pin matching
swaps neighbours. :func:`track_with_neighbours` runs an annealed soft one-to-one
matching of the two clouds (softassign) to predict every pin's displacement;
pins are matched at the predicted positions, and lost pins are predicted again
from their tracked layout neighbours and matched again, growing outward from
confident matches. :class:`device.pi.vision.tracking.Tracker` uses the same
growth per frame.
"""

from __future__ import annotations

import math

import numpy as np

from device.checks import finite_number, positive_number, whole_number
from device.pi.vision import native
from device.pi.vision.matching import (all_rows_usable, as_points, match_pins, match_pins_unchecked,
                                       pair_d2, usable_rows)

__all__ = ["layout_pitch_px", "nearest_neighbour_px", "layout_neighbours", "track_with_neighbours",
           "match_and_grow", "neighbour_median", "neighbour_consistency", "column_median"]


# --------------------------------------------------------------------------
# Layout helpers
# --------------------------------------------------------------------------


def _nearest_d2(name: str, points) -> np.ndarray:
    """Squared distance from each usable point to its nearest other one (k,)."""
    r = as_points(name, points)
    r = r[usable_rows(r)]
    if r.shape[0] < 2:
        return np.zeros(0, np.float64)
    d2 = pair_d2(r, r)
    np.fill_diagonal(d2, np.inf)
    return d2.min(axis=1)


def nearest_neighbour_px(points) -> np.ndarray:
    """Distance from each point to its nearest other point, px (k,): rows with NaN,
    inf or beyond ``MAX_COORD_PX`` are left out; empty for fewer than two."""
    return np.sqrt(_nearest_d2("points", points))


def layout_pitch_px(ref) -> float:
    """Typical pin spacing of a layout: the median nearest-neighbour distance, px.

    Returns 0.0 for fewer than two finite pins.
    """
    d2 = _nearest_d2("ref", ref)
    return float(np.sqrt(np.median(d2))) if len(d2) else 0.0


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
    k = whole_number("k", k, 1)
    r = as_points("ref", ref)
    m = r.shape[0]
    nb = np.tile(np.arange(m)[:, None], (1, k))
    valid = np.zeros((m, k), bool)
    if m < 2:
        return nb, valid
    cap2 = np.inf if max_dist_px is None else positive_number("max_dist_px", max_dist_px) ** 2
    finite = usable_rows(r)
    rr = np.where(finite[:, None], r, 0.0)
    d2 = pair_d2(rr, rr)
    d2[~finite, :] = np.inf
    d2[:, ~finite] = np.inf
    np.fill_diagonal(d2, np.inf)
    kk = min(k, m - 1)
    # the kk nearest of each row, ties by index (as a stable sort of the whole row
    # would give): only the entries up to each row's kk-th smallest value are sorted
    kth = np.partition(d2, kk - 1, axis=1)[:, kk - 1]
    rows, cols = np.nonzero(d2 <= kth[:, None])
    vals = d2[rows, cols]
    o = np.lexsort((cols, vals, rows))
    rows, cols, vals = rows[o], cols[o], vals[o]
    first = np.searchsorted(rows, np.arange(m))
    keep = np.arange(rows.size) - first[rows] < kk
    order = cols[keep].reshape(m, kk)
    dist2 = vals[keep].reshape(m, kk)
    nb[:, :kk] = order
    valid[:, :kk] = (dist2 <= 4.0 * dist2[:, :1]) & (dist2 <= cap2)
    return nb, valid


def neighbour_consistency(disp: np.ndarray, ok: np.ndarray, nb: np.ndarray, valid: np.ndarray, tol: float) -> int:
    """How many tracked pins move like their tracked neighbours (within ``tol`` px
    of their median displacement). Wrong assignments break this."""
    rows = np.flatnonzero(ok)
    if rows.size == 0:
        return 0
    med, count = neighbour_median(disp, ok, nb, valid, rows)
    dev = disp[rows] - med
    good = (count > 0) & (dev[:, 0] * dev[:, 0] + dev[:, 1] * dev[:, 1] <= tol * tol)
    return int(np.count_nonzero(good))


def column_median(a: np.ndarray) -> np.ndarray:
    """``np.median(a, axis=0)`` of a non-empty, finite (k, d) array, the same numbers
    at a fraction of the cost for the few dozen rows the tracker has."""
    s = np.sort(a, axis=0)
    k = s.shape[0]
    if k % 2:
        return s[k // 2].copy()
    return (s[k // 2 - 1] + s[k // 2]) / 2.0


def neighbour_median(obs: np.ndarray, ok: np.ndarray, nb: np.ndarray, valid: np.ndarray,
                      rows: np.ndarray | None = None):
    """Per pin, the median of ``obs`` over its valid, tracked neighbours.

    ``obs`` (m, d) per-pin values (e.g. displacements), ``ok`` (m,) tracked
    flags; ``rows`` (r,) restricts the answer to those pins. Returns ``med``
    (r, d) (0 where no neighbour is tracked) and ``count`` (r,).
    """
    if rows is not None:
        nb = nb[rows]
        valid = valid[rows]
    if nb.shape[1] == 0:                                  # no neighbours at all
        return np.zeros((nb.shape[0], obs.shape[1]), np.float64), np.zeros(nb.shape[0], np.int64)
    use = valid & ok[nb]                                  # (r, k)
    count = use.sum(axis=1)
    med = np.zeros((nb.shape[0], obs.shape[1]), np.float64)
    vals = obs[nb]                                         # (r, k, d)
    vals[~use] = np.inf                                    # inf sorts last
    vals.sort(axis=1)
    ar = np.arange(nb.shape[0])
    lo = (count - 1) // 2                                  # -1 (an inf) where count is 0
    both = vals[ar, lo] + vals[ar, count // 2]             # inf where no neighbour is tracked
    has = count > 0
    np.multiply(both, 0.5, out=med, where=has[:, None])
    return med, count


# --------------------------------------------------------------------------
# Large deformations
# --------------------------------------------------------------------------

#: Annealing schedule of the coarse soft matching, in units of the pin pitch.
_ANNEAL_START = 3.0
_ANNEAL_END = 0.1
#: The soft matching's exponents are floored here: exp(-60) = 9e-27 stays a normal
#: float32 after the Sinkhorn scalings (exp(-87), the smallest normal, does not).
_EXP_FLOOR = np.float32(-60.0)
#: Largest ``outlier_sigmas``: the slack exp(-s^2 / 2) must stay far above the floored
#: weights (at 6, 1.5e-8 against a few hundred pins x 9e-27).
_MAX_OUTLIER_SIGMAS = 6.0
#: Passes with the full gate over the pins the half-gate growth left lost.
_FINAL_ROUNDS = 4
#: up to this many pins the smoothing sums neighbours by a dense matrix product, above
#: by gathering them (faster from a few hundred pins on; the same numbers to ~1e-16)
_DENSE_SMOOTH_PINS = 256


def _anneal(ref: np.ndarray, use: np.ndarray, cur: np.ndarray, pitch: float, disp: np.ndarray,
            nb: np.ndarray, valid: np.ndarray, steps: int, sinkhorn_iters: int,
            outlier_sigmas: float, smooth: float, smooth_iters: int = 10,
            start: float = _ANNEAL_START) -> np.ndarray:
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

    sigma falls geometrically from ``start`` pitches (default 3), where the whole cloud is matched
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
    row = np.empty(m, np.float32)
    cc = np.empty((n, 3), np.float32)          # [x * col, y * col, col] of the current pins
    all_used = bool(np.all(use))
    k = np.empty((m, n), np.float32)
    kt = np.empty((n, m), np.float32)          # k transposed, contiguous: fast products
    # The smoothing sums each pin's valid neighbours. Up to _DENSE_SMOOTH_PINS pins
    # by one product with the neighbour graph as a dense matrix, transposed
    # (adj_t[j, i] = 1 when j is a neighbour of i); above, by gathering the k
    # neighbours (padding points at a zero column m), which grows with m, not m^2.
    dense = m <= _DENSE_SMOOTH_PINS
    deg = valid.sum(axis=1).astype(np.float64)
    if dense:
        adj_t = np.zeros((m, m), np.float64)
        rows = np.repeat(np.arange(m), nb.shape[1])
        np.add.at(adj_t, (nb.ravel()[valid.ravel()], rows[valid.ravel()]), 1.0)
        diag = np.diag_indices(m)
        # B transposed with the constant part below it, and the field with a 2 x 2
        # identity beside it: [v | I] [B; a] = B v + a in one product per sweep
        b_t = np.empty((m + 2, m), np.float64)
        x0 = np.zeros((2, m + 2), np.float64)
        x0[:, m:] = np.eye(2)
        x1 = x0.copy()
    else:
        nb_t = np.where(valid, nb, m).T.copy()          # (k, m)
        x_t = np.zeros((2, m + 1), np.float64)
    for sigma in np.geomspace(start, _ANNEAL_END, steps) * pitch:
        pos = ref + v - origin
        hp[:, :2] = pos
        hp[:, 3] = (pos * pos).sum(axis=1)
        np.matmul(hp, hc, out=k)
        np.maximum(k, 0.0, out=k)              # rounding can dip below 0
        k *= np.float32(-0.5 / (sigma * sigma))
        # weights near float32's smallest normal number (1e-38) turn subnormal when
        # the Sinkhorn factors scale them, and arithmetic on subnormals is tens of
        # times slower on most CPUs: the exponent is floored at -60 (a weight of
        # 1e-26 against the slack's 1e-2 at the default outlier_sigmas changes nothing)
        np.maximum(k, _EXP_FLOOR, out=k)
        np.exp(k, out=k)
        if not all_used:
            k[~use] = 0.0
        np.copyto(kt, k.T)
        for _ in range(sinkhorn_iters):          # warm-started column scaling
            np.matmul(k, col, out=row)
            row += kappa
            np.reciprocal(row, out=row)
            np.matmul(kt, row, out=col)
            col += kappa
            np.reciprocal(col, out=col)
        # the scaled weights diag(row) k diag(col), read through two products
        # instead of being formed
        cc[:, :2] = cur32 * col[:, None]
        cc[:, 2] = col
        kc = (k @ cc).astype(np.float64) * row[:, None].astype(np.float64)
        w = kc[:, 2]                           # matched mass of each pin, <= ~1
        wt = kc[:, :2] + w[:, None] * (origin - ref)   # w * (target - ref)
        has = w > 1e-12
        v[has] = wt[has] / w[has, None]        # the data term's own answer
        lam = smooth * sigma / pitch
        if lam <= 0.0:
            continue
        # Jacobi sweeps from the data, v <- (wt + lam adj v + eps v) / den, as
        # v <- a + B v with the constant parts folded once per temperature
        # The field is kept transposed, (2, m), and so is B: a (2, m) x (m + 2, m)
        # product per sweep is B v + a, at about half the cost of a product with a
        # two-column right-hand side.
        inv = 1.0 / (w + lam * deg + 1e-12)
        if dense:
            np.multiply(wt, inv[:, None], out=b_t[m:].T)
            np.multiply(adj_t, lam * inv, out=b_t[:m])
            b_t[diag] += 1e-12 * inv
            x0[:, :m] = v.T
            for _ in range(smooth_iters):
                np.matmul(x0, b_t, out=x1[:, :m])
                x0, x1 = x1, x0
            v = x0[:, :m].T.copy()
            continue
        a_t = (wt * inv[:, None]).T.copy()
        lam_inv = lam * inv
        eps_inv = 1e-12 * inv
        x_t[:, :m] = v.T
        for _ in range(smooth_iters):
            s = x_t[:, nb_t].sum(axis=1)                 # (2, m) neighbour sums
            s *= lam_inv
            s += a_t
            x_t[:, :m] *= eps_inv
            x_t[:, :m] += s
        v = x_t[:, :m].T.copy()
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
    anneal_start: float = _ANNEAL_START,
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
       (see ``_anneal``): ``anneal_steps`` temperatures from ``anneal_start``
       pitches down to 0.1, ``sinkhorn_iters`` normalisations each. From
       scratch the search starts at 3 pitches; from a good prior (a tracker's
       prediction) a start of 1.5 pitches and fewer steps find the same
       answer at a third of the cost. Without it the prediction is
       ``init_disp_px`` (or zero).
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

    ``outlier_sigmas`` (above 0, at most 6): in the soft matching a pin further
    than that many sigma from every current pin keeps its mass unmatched.

    Returns ``idx`` int64 (m,) (row of ``cur`` or -1 when lost) and
    ``disp_px`` float64 (m, 2): measured for tracked pins; for lost pins the
    neighbour prediction (or the coarse / prior prediction when no neighbour
    is tracked), so every value is finite. Rows with NaN, inf or a
    coordinate beyond ``MAX_COORD_PX`` are treated as absent; ``idx`` indexes
    the caller's ``cur``. Bad arguments raise ValueError naming the field.
    """
    pitch = positive_number("pitch_px", pitch_px)
    gate_frac = positive_number("gate_frac", gate_frac)
    anneal_steps = whole_number("anneal_steps", anneal_steps, 1)
    sinkhorn_iters = whole_number("sinkhorn_iters", sinkhorn_iters, 1)
    anneal_start = positive_number("anneal_start", anneal_start)
    outlier_sigmas = finite_number("outlier_sigmas", outlier_sigmas, 0.0, _MAX_OUTLIER_SIGMAS,
                                   lo_open=True)
    smooth = finite_number("smooth", smooth, 0)
    grow_rounds = whole_number("grow_rounds", grow_rounds, 0)
    min_support = whole_number("min_support", min_support, 1)
    r = as_points("ref", ref)
    c = as_points("cur", cur)
    m = r.shape[0]
    fin_r = usable_rows(r)
    r = np.where(fin_r[:, None], r, 0.0)
    cols = None
    if not all_rows_usable(c):
        keep = usable_rows(c)
        cols = np.flatnonzero(keep)
        c = c[keep]
    if init_disp_px is None:
        pred = np.zeros((m, 2))
    else:
        pred = as_points("init_disp_px", init_disp_px)
        if pred.shape[0] != m:
            raise ValueError(
                f"init_disp_px must have one row per reference pin ({m}), got init_disp_px.shape={pred.shape!r}"
            )
        pred = np.where(usable_rows(pred)[:, None], pred, 0.0)
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
                       outlier_sigmas, float(smooth), start=max(anneal_start, 2 * _ANNEAL_END))
        pred[~fin_r] = 0.0
    idx[:] = match_and_grow(r, fin_r, c, pred, nb, valid, gate_frac * pitch, grow_rounds, min_support,
                             pred)[0]
    if cols is not None:
        hit = idx >= 0
        idx[hit] = cols[idx[hit]]
    return idx, pred


def match_and_grow(r, fin_r, c, pred, nb, valid, gate, grow_rounds, min_support, disp):
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

    When every reference pin is finite this runs compiled (``tf_grow`` in
    ``match.c``, :mod:`device.pi.vision.native`) if the kernel is built: the same
    steps and the same numbers; this code is its specification and fallback.

    ``c`` (n, 2) float64 holds usable rows only (finite, within
    ``MAX_COORD_PX``: both callers drop the others first). ``disp`` (m, 2)
    float64 is written in place (it may be ``pred``): the
    measured displacement of tracked pins and the best prediction of lost
    ones. Returns ``idx`` and the number of confident matches of step 1.
    """
    all_fin = bool(fin_r.all())
    if all_fin:
        # compiled (device/pi/vision/match.c, tf_grow): the same steps, the same numbers
        done = native.grow_into(r, c, pred, nb, valid, gate, grow_rounds, min_support,
                                _FINAL_ROUNDS, disp)
        if done is not None:
            return done
    prior = np.array(pred, dtype=np.float64)            # the caller's prediction, kept
    if not all_fin:
        prior[~fin_r] = 0.0
    pos = r + prior
    if not all_fin:
        pos[~fin_r] = np.nan
    # every position usable (the tracker's case, and the current pins are checked
    # by the caller): the matching skips its argument checks
    match = match_pins_unchecked if all_fin and all_rows_usable(pos) else match_pins
    idx = match(pos, c, 0.5 * gate)
    ok = idx >= 0
    n_ok = int(np.count_nonzero(ok))
    n_fin = r.shape[0] if all_fin else int(np.count_nonzero(fin_r))
    if n_ok < 0.5 * n_fin:
        # A common jump (a lift, a slip): shift every prediction by the median
        # offset of one-to-one matches with a wide gate (robust to pins
        # entering or leaving the view, unlike the shift of the centroids).
        # Kept when it catches more pins confidently and keeps most of the
        # pins already caught (a prior that is right for part of the layout
        # is not overruled by the rest).
        wide = match(pos, c, 1.25 * gate)
        hit = wide >= 0
        if hit.any():
            shift = column_median(c[wide[hit]] - pos[hit])
            idx2 = match(pos + shift, c, 0.5 * gate)
            ok2 = idx2 >= 0
            n2 = int(np.count_nonzero(ok2))
            kept = int(np.count_nonzero(idx2[ok] == idx[ok]))
            if n2 > n_ok and 2 * kept >= n_ok:
                prior += shift
                pos += shift
                idx, ok, n_ok = idx2, ok2, n2
    n_confident = n_ok
    # the prediction errors and the displacements side by side (one array for the
    # neighbour medians): measured for tracked pins, predicted for lost ones
    ed = np.empty((r.shape[0], 4))
    err, dd = ed[:, :2], ed[:, 2:]
    dd[:] = prior
    hit = idx[ok]
    dd[ok] = c[hit] - r[ok]
    np.subtract(dd, prior, out=err)                      # prediction error (0 for lost pins)
    free = np.ones(c.shape[0], bool)
    free[hit] = False

    supported = np.zeros(r.shape[0], bool)   # lost pins with min_support tracked neighbours

    def predict(rows):
        """Neighbour predictions of lost ``rows``: written to dd and ``supported``;
        returns the support mask of ``rows``."""
        med, count = neighbour_median(ed, ok, nb, valid, rows)
        sup = count >= min_support
        supported[rows] = sup
        if sup.any():
            s_rows = rows[sup]
            own = prior[s_rows] + med[sup, :2]
            med_disp = med[sup, 2:]
            dev = own - med_disp
            agree = dev[:, 0] * dev[:, 0] + dev[:, 1] * dev[:, 1] <= gate * gate
            dd[s_rows] = np.where(agree[:, None], own, med_disp)
        return sup

    def take(rows, g):
        """Match ``rows`` at dd against the free pins (gate g); returns the rows caught."""
        fc = np.flatnonzero(free)
        sub = match(r[rows] + dd[rows], c[fc], g)
        hit = sub >= 0
        if not hit.any():
            return rows[:0]
        got = rows[hit]
        idx[got] = fc[sub[hit]]
        ok[got] = True
        free[idx[got]] = False
        dd[got] = c[idx[got]] - r[got]
        err[got] = dd[got] - prior[got]
        return got

    n_pred = -1                       # tracked count when the lost pins were last predicted
    rows = np.flatnonzero(~ok if all_fin else ~ok & fin_r)
    newly = np.zeros(r.shape[0], bool)
    for _ in range(grow_rounds):
        if rows.size == 0 or not ok.any():
            break
        sup = predict(rows)
        n_pred = int(np.count_nonzero(ok))
        if not sup.any() or not free.any():
            break
        got = take(rows[sup], 0.5 * gate)
        if got.size == 0:
            break
        # Only a lost pin with a newly tracked neighbour can be predicted anew; the
        # others keep the prediction that found no free pin within the gate (and
        # there are fewer free pins now), so they are not searched again.
        newly[:] = False
        newly[got] = True
        lost = np.flatnonzero(~ok if all_fin else ~ok & fin_r)
        rows = lost[(valid[lost] & newly[nb[lost]]).any(axis=1)]
        if rows.size == 0:
            n_pred = int(np.count_nonzero(ok))   # every lost pin's prediction is current
    for _ in range(_FINAL_ROUNDS):
        # last passes over every pin still lost: the neighbour prediction where
        # there is one, else the pin's own prediction corrected by the median
        # error of all tracked pins; the full gate
        lost = np.flatnonzero(~ok if all_fin else ~ok & fin_r)
        n_now = int(np.count_nonzero(ok))
        if lost.size == 0 or n_now == 0:
            break
        if n_now != n_pred:
            predict(lost)
            n_pred = n_now
        far = lost[~supported[lost]]
        if n_now >= 3 and far.size:                     # a common error needs a few pins
            dd[far] = prior[far] + column_median(err[ok])
        if not free.any() or take(lost, gate).size == 0:
            break
    disp[:] = dd
    return idx, n_confident
