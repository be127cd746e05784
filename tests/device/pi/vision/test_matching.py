"""device/pi/vision/matching.py: one-to-one matching with a gate (match_pins,
mutual_match) - properties, hard inputs and the greedy answer."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from device.pi.vision.matching import gated_pairs, match_pins, match_pins_unchecked, mutual_match
from tests.pins import hex_pins
from tests.pins import points


# -- helpers ------------------------------------------------------------------------

def jittered_grid(rng, n: int, spacing: float = 10.0, jitter: float = 1.0) -> np.ndarray:
    side = int(math.ceil(math.sqrt(max(n, 1))))
    g = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2)[:n]
    return g * spacing + rng.uniform(-jitter, jitter, (n, 2))


def pair_d2(a, b):
    return ((np.asarray(a)[:, None, :] - np.asarray(b)[None, :, :]) ** 2).sum(-1)


def check_greedy(ref, cur, gate, idx):
    """One to one, inside the gate, and no blocking pair (=> the greedy answer)."""
    ref, cur = np.asarray(ref, float), np.asarray(cur, float)
    assert idx.shape == (ref.shape[0],) and idx.dtype.kind == "i"
    hit = idx >= 0
    assert len(set(idx[hit].tolist())) == int(hit.sum()), "a current pin used twice"
    if ref.shape[0] == 0 or cur.shape[0] == 0:
        assert not hit.any()
        return
    d2 = pair_d2(ref, cur)
    assert (d2[np.flatnonzero(hit), idx[hit]] <= gate * gate + 1e-9).all()
    mine = np.full(ref.shape[0], np.inf)
    mine[hit] = d2[np.flatnonzero(hit), idx[hit]]
    owner = np.full(cur.shape[0], np.inf)
    owner[idx[hit]] = mine[hit]
    spread = max(np.ptp(np.vstack([ref, cur]), axis=0).max(), 1.0)
    tol = 1e-6 * spread * spread + 1e-6
    blocking = (d2 <= gate * gate) & (d2 < mine[:, None] - tol) & (d2 < owner[None, :] - tol)
    assert not blocking.any(), "a closer free pair was left unmatched (not greedy)"


def greedy_reference(ref, cur, gate):
    """Slow, obvious greedy-by-distance matching for comparison."""
    d2 = pair_d2(ref, cur)
    order = np.argsort(d2, axis=None, kind="stable")
    idx = np.full(len(ref), -1)
    used = set()
    for k in order:
        i, j = divmod(int(k), d2.shape[1])
        if d2[i, j] > gate * gate:
            break
        if idx[i] < 0 and j not in used:
            idx[i] = j
            used.add(j)
    return idx


# -- match_pins -----------------------------------------------------------------------

def test_match_recovers_a_permutation_with_noise():
    rng = np.random.default_rng(1)
    ref = hex_pins(10, 20.0)                                    # 331 pins
    perm = rng.permutation(len(ref))
    cur = ref[perm] + rng.normal(0, 1.0, ref.shape)
    idx = match_pins(ref, cur, 8.0)
    assert (perm[idx] == np.arange(len(ref))).all()


def test_match_marks_lost_pins_and_never_invents():
    ref = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0]])
    cur = np.array([[10.5, 0.0], [0.2, 0.1]])                     # pin 2 missing
    idx = match_pins(ref, cur, 3.0)
    assert idx.tolist() == [1, 0, -1]
    assert match_pins(ref, cur + 5.0, 3.0).tolist() == [-1, -1, -1]   # all beyond the gate


def test_match_prefers_the_shortest_pair():
    # ref 1 is nearer to cur 0 than ref 0 is: ref 0 must not take it
    ref = np.array([[0.0, 0.0], [3.0, 0.0]])
    cur = np.array([[2.0, 0.0], [6.0, 0.0]])
    assert match_pins(ref, cur, 4.0).tolist() == [-1, 0]
    assert match_pins(ref, cur, 4.0).tolist() == greedy_reference(ref, cur, 4.0).tolist()


@pytest.mark.parametrize("m,n", [(0, 0), (0, 5), (5, 0)])
def test_match_empty_sets(m, n):
    idx = match_pins(np.zeros((m, 2)), np.ones((n, 2)), 2.0)
    assert idx.shape == (m,) and (idx == -1).all()


def test_match_one_pin_and_empty_lists():
    assert match_pins([[1.0, 1.0]], [[1.5, 1.0]], 1.0).tolist() == [0]
    assert match_pins([[1.0, 1.0]], [[3.5, 1.0]], 1.0).tolist() == [-1]
    assert match_pins([], [], 1.0).shape == (0,)


def test_match_non_finite_rows_never_match():
    ref = np.array([[0.0, 0.0], [np.nan, 0.0], [10.0, 10.0], [1e300, 0.0]])
    cur = np.array([[np.inf, 0.0], [0.1, 0.0], [10.0, 10.2], [np.nan, np.nan]])
    assert match_pins(ref, cur, 1.0).tolist() == [1, -1, 2, -1]


@pytest.mark.parametrize("gate", [0, -1.0, float("nan"), float("inf"), "3", None, True])
def test_match_bad_gate_names_the_field(gate):
    with pytest.raises(ValueError, match="max_dist_px"):
        match_pins([[0.0, 0.0]], [[0.0, 0.0]], gate)


@pytest.mark.parametrize("field,ref,cur", [("ref", np.zeros((3, 3)), np.zeros((3, 2))),
                                           ("cur", np.zeros((3, 2)), np.zeros(5))])
def test_match_bad_shapes_name_the_field(field, ref, cur):
    with pytest.raises(ValueError, match=field):
        match_pins(ref, cur, 1.0)



@settings(max_examples=150, deadline=None)
@given(ref=points, cur=points, gate=st.floats(0.1, 200.0))
def test_match_is_one_to_one_and_greedy(ref, cur, gate):
    idx = match_pins(ref, cur, gate)
    check_greedy(ref, cur, gate, idx)


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(n=st.integers(1, 200), seed=st.integers(0, 2**31 - 1),
       drop=st.floats(0.0, 0.5), n_dup=st.integers(0, 10), n_extra=st.integers(0, 10))
def test_match_permutation_dropout_duplicates(n, seed, drop, n_dup, n_extra):
    """Pins 10 px apart, moved < 2 px, shuffled, some dropped, some detected
    twice, some spurious far away: every kept pin finds itself, dropped pins
    are lost, nothing is used twice."""
    rng = np.random.default_rng(seed)
    ref = jittered_grid(rng, n)
    keep = np.flatnonzero(rng.random(n) >= drop)
    cur = ref[keep] + rng.uniform(-1.4, 1.4, (keep.size, 2))
    ids = keep.copy()
    if keep.size and n_dup:
        d = rng.choice(keep.size, n_dup)
        cur = np.vstack([cur, cur[d]])                             # exact duplicates
        ids = np.concatenate([ids, ids[d]])
    if n_extra:
        cur = np.vstack([cur, 1e4 + rng.random((n_extra, 2))])    # spurious, far away
        ids = np.concatenate([ids, np.full(n_extra, -1)])
    perm = rng.permutation(len(cur))
    cur, ids = cur[perm], ids[perm]
    idx = match_pins(ref, cur, 4.0)
    check_greedy(ref, cur, 4.0, idx)
    hit = idx >= 0
    assert set(np.flatnonzero(hit)) == set(keep.tolist())
    assert (ids[idx[hit]] == np.flatnonzero(hit)).all()


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(m=st.integers(1, 160), n=st.integers(1, 160), seed=st.integers(0, 2**31 - 1),
       gate=st.floats(0.5, 30.0))
def test_unchecked_matching_is_the_greedy_answer_small_and_large(m, n, seed, gate):
    """Few pairs take the all-pairs path, many the cell-grid path: both are the
    greedy answer and the same as match_pins; up to 40 x 40 pins the slow
    reference's answer itself."""
    rng = np.random.default_rng(seed)
    ref = rng.integers(0, 400, (m, 2)).astype(np.float64) + rng.random((m, 2)) * 1e-3
    cur = np.vstack([ref[rng.permutation(m)[:min(m, n)]] + rng.normal(0, gate / 2, (min(m, n), 2)),
                     rng.uniform(0, 400, (max(0, n - m), 2))])
    idx = match_pins_unchecked(ref, cur, gate)
    check_greedy(ref, cur, gate, idx)
    assert (idx == match_pins(ref, cur, gate)).all()
    if m <= 40 and n <= 40:
        assert (idx == greedy_reference(ref, cur, gate)).all()


def test_mutual_match_keeps_only_pairs_that_choose_each_other():
    """Both pins are nearest to detection 0, which is nearest to pin 1: only that
    pair survives. Greedy matching (match_pins) gives pin 0 its second choice."""
    pred = np.array([[0.0, 0.0], [2.0, 0.0]])
    det = np.array([[1.2, 0.0], [-1.5, 0.0]])
    assert mutual_match(pred, det, 5.0).tolist() == [-1, 0]
    assert match_pins(pred, det, 5.0).tolist() == [1, 0]
    assert mutual_match(pred, det[::-1], 5.0).tolist() == [-1, 1]     # order does not matter
    assert mutual_match(pred, det, 0.5).tolist() == [-1, -1]          # the gate
    assert mutual_match(pred[:0], det, 5.0).tolist() == []
    assert mutual_match(pred, det[:0], 5.0).tolist() == [-1, -1]


# -- boundaries the mutation tester found untested (issue 24) ------------------------------

def test_match_with_unusable_rows_keeps_the_gate_and_the_row_numbers():
    """The path for sets with NaN rows matches the usable rows with the same gate
    (not a 1 px one) and reports rows of the full ``cur``, skipping the bad ones."""
    ref = np.array([[np.nan, 0.0], [0.0, 0.0], [50.0, 0.0], [100.0, 0.0]])
    cur = np.array([[np.nan, np.nan], [np.inf, 1.0], [104.0, 3.0], [57.0, 0.0], [0.0, 4.0]])
    assert match_pins(ref, cur, 6.0).tolist() == [-1, 4, -1, 2]
    assert match_pins(ref, cur, 8.0).tolist() == [-1, 4, 3, 2]
    assert match_pins(ref, cur, 3.0).tolist() == [-1, -1, -1, -1]
    # the same usable points without the bad rows give the same pairs
    assert match_pins(ref[1:], cur[2:], 8.0).tolist() == [2, 1, 0]
    # only bad rows on one side: nothing matches
    assert match_pins(ref, cur[:2], 8.0).tolist() == [-1] * 4
    assert match_pins(ref[:1], cur, 8.0).tolist() == [-1]


@pytest.mark.parametrize("far, usable", [(1.0e6, True), (-1.0e6, True), (1.0e6 + 1.0, False),
                                         (-1.0e6 - 1.0, False)])
def test_coordinates_up_to_a_million_px_are_usable_beyond_are_not(far, usable):
    ref = np.array([[far, 0.0], [far, 20.0]])
    cur = np.array([[far, 0.5], [far, 20.5]])
    want = [0, 1] if usable else [-1, -1]
    assert match_pins(ref, cur, 2.0).tolist() == want
    # a bad row on the other side sends both through the row-by-row path
    assert match_pins(ref, np.vstack([cur, [[np.nan, 0.0]]]), 2.0).tolist() == want


def test_a_pair_exactly_at_the_gate_matches():
    assert match_pins([[0.0, 0.0]], [[3.0, 4.0]], 5.0).tolist() == [0]
    assert match_pins([[0.0, 0.0], [np.nan, 0.0]], [[3.0, 4.0]], 5.0).tolist() == [0, -1]
    assert mutual_match(np.array([[0.0, 0.0]]), np.array([[3.0, 4.0]]), 5.0).tolist() == [0]
    assert mutual_match(np.array([[0.0, 0.0]]), np.array([[3.0, 4.0]]), 4.99).tolist() == [-1]


def test_a_bad_point_set_is_named_and_the_result_is_int64():
    with pytest.raises(ValueError, match=r"^cur must be an \(n, 2\) array.*cur\.shape=\(3,\)"):
        match_pins(np.zeros((2, 2)), np.zeros(3), 2.0)
    with pytest.raises(ValueError, match=r"^ref must"):
        match_pins(np.zeros((2, 3)), np.zeros((2, 2)), 2.0)
    for cur in (np.zeros((0, 2)), np.array([[0.5, 0.0]]), np.array([[np.nan, 0.0], [0.5, 0]])):
        idx = match_pins(np.zeros((2, 2)), cur, 2.0)
        assert idx.dtype == np.int64 and idx.shape == (2,)


# -- the cell-grid matching (issue 25): the same pairs and answer as brute force ---------

def brute_pairs(ref, cur, max_d2):
    d2 = pair_d2(ref, cur)
    rows, cols = np.nonzero(d2 <= max_d2)
    return {(int(i), int(j)): float(d2[i, j]) for i, j in zip(rows, cols)}


_centre = st.sampled_from([0.0, 333.3, -1.0e6 + 3000.0, 1.0e6 - 3000.0])   # all within +-1e6


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(m=st.integers(0, 120), n=st.integers(0, 120), seed=st.integers(0, 2**31 - 1),
       gate=st.sampled_from([0.01, 0.5, 1.0, 3.0, 5.0, 12.0, 40.0]), centre=_centre,
       lattice=st.booleans())
def test_gated_pairs_are_exactly_the_pairs_within_the_gate(m, n, seed, gate, centre, lattice):
    """Every pair within the gate and no other, with the brute-force squared
    distances to the bit: on random points, and on an integer lattice where many
    pairs lie exactly at the gate and on cell borders (gate 5: 3-4-5 triangles),
    near the origin and near the edges of the usable square (+-1e6 px)."""
    rng = np.random.default_rng(seed)
    if lattice:
        ref = rng.integers(-20, 20, (m, 2)).astype(np.float64) + centre
        cur = rng.integers(-20, 20, (n, 2)).astype(np.float64) + centre
    else:
        spread = 50.0 * gate if gate > 0.1 else 10.0
        ref = centre + rng.uniform(-spread, spread, (m, 2))
        cur = np.vstack([ref[: n // 2] + rng.normal(0, gate, (min(n // 2, m), 2)),
                         centre + rng.uniform(-spread, spread, (n - min(n // 2, m), 2))])
    rows, cols, d2 = gated_pairs(ref, cur, gate * gate)
    got = {(int(i), int(j)): float(v) for i, j, v in zip(rows, cols, d2)}
    assert len(got) == rows.size                         # no pair twice
    assert got == brute_pairs(ref, cur, gate * gate)
    assert (np.diff(rows) >= 0).all()                    # grouped by row


def test_gated_pairs_keeps_pairs_exactly_at_the_gate_across_cells():
    ref = np.array([[0.0, 0.0], [10.0, 10.0], [-7.0, 3.0]])
    cur = np.array([[3.0, 4.0], [10.0, 15.0], [-7.0, -2.0], [5.0, 0.0], [6.0, 0.0]])
    rows, cols, d2 = gated_pairs(ref, cur, 25.0)
    assert sorted(zip(rows.tolist(), cols.tolist())) == [(0, 0), (0, 3), (1, 1), (2, 2)]
    assert d2.tolist() == [25.0] * 4


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(m=st.integers(0, 150), n=st.integers(0, 150), seed=st.integers(0, 2**31 - 1),
       gate=st.floats(0.3, 40.0), centre=_centre, crowd=st.floats(0.2, 3.0))
def test_grid_matching_is_the_brute_force_greedy_answer(m, n, seed, gate, centre, crowd):
    """The fast matcher gives the slow greedy reference's assignment on random point
    sets: empty sets, 0 and 1 pins, crowded sets (many candidates per pin, so the
    rounds of mutual best pairs run), sparse ones, and coordinates near +-1e6 px."""
    rng = np.random.default_rng(seed)
    spread = crowd * gate * math.sqrt(max(m, n, 1))
    ref = centre + rng.uniform(-spread, spread, (m, 2))
    k = min(m, n)
    cur = np.vstack([ref[rng.permutation(m)[:k]] + rng.normal(0, gate / 2, (k, 2)),
                     centre + rng.uniform(-spread, spread, (n - k, 2))])[rng.permutation(n)]
    idx = match_pins_unchecked(ref, cur, gate)
    assert idx.dtype == np.int64 and idx.shape == (m,)
    assert (idx == greedy_reference(ref, cur, gate)).all()
    assert (idx == match_pins(ref, cur, gate)).all()


def test_grid_matching_resolves_a_chain_of_shared_candidates():
    """A row of pins each with two candidates, the nearer one shared with the next
    pin: only the greedy order (closest pair first, then the next free one) gives
    this answer; enough pins for the cell-grid path."""
    x = np.arange(100) * 10.0
    ref = np.stack([x, np.zeros(100)], 1)
    cur = np.stack([x + 4.0 + np.linspace(0, 0.5, 100), np.zeros(100)], 1)
    idx = match_pins_unchecked(ref, cur, 7.0)
    assert (idx == greedy_reference(ref, cur, 7.0)).all()
    assert (idx == np.arange(100)).all()                 # each pin's own right neighbour
    # shifted past half the spacing the nearest is the left neighbour's: pin 0 loses out
    idx = match_pins_unchecked(ref, cur + [2.0, 0.0], 7.0)
    assert (idx == greedy_reference(ref, cur + [2.0, 0.0], 7.0)).all()
    assert idx[0] == -1 and (idx[1:] == np.arange(99)).all()


def test_gated_pairs_with_crowded_cells_are_still_exact():
    """Many detections in one cell (duplicates, a gate wider than the spacing) take
    the range-by-range path: the same pairs and matching as brute force."""
    rng = np.random.default_rng(5)
    ref = rng.uniform(0, 300, (150, 2))
    cur = np.vstack([np.repeat(ref[:3], 12, axis=0) + rng.normal(0, 0.2, (36, 2)),
                     ref[3:] + rng.normal(0, 0.5, (147, 2))])[rng.permutation(183)]
    for gate in (1.5, 4.0, 30.0):                   # the last: many pins per cell
        rows, cols, d2 = gated_pairs(ref, cur, gate * gate)
        got = {(int(i), int(j)): float(v) for i, j, v in zip(rows, cols, d2)}
        assert got == brute_pairs(ref, cur, gate * gate)
        idx = match_pins_unchecked(ref, cur, gate)
        assert (idx == greedy_reference(ref, cur, gate)).all()
