"""Pin tracking (device/pi/vision/tracking.py) and the tactip_shear evaluation
(host/analysis/shear.py): one-to-one matching properties, large deformations, the
per-frame tracker on hard inputs, identity switches on simulated drags, and
pin assignment plus Ridge regressions on the real tactip_shear images."""

from __future__ import annotations

import dataclasses
import math
import tracemalloc

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from device.pi.vision.matching import match_pins
from device.pi.vision.neighbours import layout_neighbours, layout_pitch_px, track_with_neighbours
from device.pi.vision.tracking import FAULT_BAD_INPUT, FAULT_NO_REFERENCE, FAULT_TOO_FEW_PINS, Tracker
from device.profile import load_profile
from device.sim import Simulator, load_scene

from tests.realdata import real_data_dir

DRAGS = [f"drag-{a}" for a in range(0, 360, 45)]
MAX_SWITCH_FRAC = 0.005          # issue 8: identity switches <= 0.5% of pins per frame


# -- helpers ------------------------------------------------------------------------

def hex_layout(rings: int, pitch: float, centre=(220.0, 220.0)) -> np.ndarray:
    """A hexagonal pin layout with ``rings`` rings around a centre pin."""
    pts = []
    for q in range(-rings, rings + 1):
        for r in range(max(-rings, -q - rings), min(rings, -q + rings) + 1):
            pts.append((pitch * (q + r / 2.0), pitch * r * math.sqrt(3) / 2.0))
    return np.asarray(pts) + centre


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
    ref = hex_layout(10, 20.0)                                    # 331 pins
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


points = st.integers(0, 25).flatmap(
    lambda n: hnp.arrays(np.float64, (n, 2), elements=st.floats(-300, 300, allow_nan=False)))


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


# -- track_with_neighbours ---------------------------------------------------------------

def big_deformation(ref, pitch, rng):
    """A press-like field: radial expansion up to 1.2 pitch plus a shift of 1.3 pitch
    falling off towards the rim (pins move further than their spacing)."""
    c = ref.mean(axis=0)
    rel = ref - c
    r = np.hypot(rel[:, 0], rel[:, 1])
    rmax = r.max()
    expand = 1.2 * pitch * np.sin(np.pi * r / rmax)[:, None] * rel / np.maximum(r, 1e-9)[:, None]
    shift = 1.3 * pitch * np.array([0.8, -0.6]) * (1.0 - (r / rmax) ** 2)[:, None]
    return ref + expand + shift + rng.normal(0, 0.3, ref.shape)


def test_track_with_neighbours_follows_moves_larger_than_the_pitch():
    rng = np.random.default_rng(3)
    pitch = 20.0
    ref = hex_layout(10, pitch)
    moved = big_deformation(ref, pitch, rng)
    keep = np.flatnonzero(rng.random(len(ref)) >= 0.03)           # 3% of pins missing
    perm = rng.permutation(keep.size)
    cur = moved[keep][perm]
    ids = keep[perm]
    idx, disp = track_with_neighbours(ref, cur, layout_pitch_px(ref))
    hit = idx >= 0
    correct = hit & (ids[np.maximum(idx, 0)] == np.arange(len(ref)))
    wrong = hit & ~correct
    assert correct.sum() >= 0.97 * keep.size
    assert wrong.sum() <= 0.005 * len(ref)
    assert np.isfinite(disp).all() and disp.shape == ref.shape
    assert np.allclose(disp[correct], moved[correct] - ref[correct])
    # plain nearest-neighbour matching with the same gate cannot do this
    plain = match_pins(ref, cur, 0.4 * pitch)
    plain_ok = (plain >= 0) & (ids[np.maximum(plain, 0)] == np.arange(len(ref)))
    assert plain_ok.sum() < 0.6 * keep.size


def test_track_with_neighbours_grows_from_a_prior():
    """Without the coarse stage: a good prior for part of the layout and the
    neighbour prediction grows tracking into the rest."""
    rng = np.random.default_rng(4)
    ref = hex_layout(6, 20.0)
    shift = np.array([13.0, 0.0])                                  # 0.65 pitch everywhere
    cur = ref + shift + rng.normal(0, 0.2, ref.shape)
    prior = np.zeros_like(ref)
    near = np.hypot(*(ref - ref.mean(0)).T) < 30
    prior[near] = shift                                            # only the middle is known
    idx, disp = track_with_neighbours(ref, cur, 20.0, init_disp_px=prior, coarse=False)
    assert (idx == np.arange(len(ref))).all()
    assert np.allclose(disp, shift, atol=1.0)
    idx0, _ = track_with_neighbours(ref, cur, 20.0, coarse=False, grow_rounds=0)
    assert (idx0 == np.arange(len(ref))).mean() < 0.5              # no prior, no growth: lost/swapped


def test_track_with_neighbours_edge_cases():
    idx, disp = track_with_neighbours(np.zeros((0, 2)), np.ones((4, 2)), 10.0)
    assert idx.shape == (0,) and disp.shape == (0, 2)
    idx, disp = track_with_neighbours([[5.0, 5.0]], np.zeros((0, 2)), 10.0)
    assert idx.tolist() == [-1] and np.isfinite(disp).all()
    idx, disp = track_with_neighbours([[5.0, 5.0]], [[7.0, 5.0]], 10.0)
    assert idx.tolist() == [0] and np.allclose(disp, [[2.0, 0.0]])
    ref = np.array([[0.0, 0.0], [np.nan, 1.0], [20.0, 0.0]])
    cur = np.array([[np.inf, 0.0], [0.5, 0.0], [20.5, 0.0]])
    idx, disp = track_with_neighbours(ref, cur, 20.0)
    assert idx.tolist() == [1, -1, 2] and np.isfinite(disp).all()


@pytest.mark.parametrize("kw,field", [({"pitch_px": 0.0}, "pitch_px"), ({"pitch_px": np.nan}, "pitch_px"),
                                      ({"gate_frac": -1.0}, "gate_frac"),
                                      ({"anneal_steps": 0}, "anneal_steps"),
                                      ({"init_disp_px": np.zeros((2, 2))}, "init_disp_px")])
def test_track_with_neighbours_bad_arguments_name_the_field(kw, field):
    args = {"ref": np.zeros((3, 2)) + [[0, 0], [10, 0], [0, 10]], "cur": np.zeros((3, 2)), "pitch_px": 10.0}
    args.update(kw)
    with pytest.raises(ValueError, match=field):
        track_with_neighbours(**args)


@settings(max_examples=60, deadline=None)
@given(ref=points, cur=points, pitch=st.floats(1.0, 50.0), coarse=st.booleans())
def test_track_with_neighbours_outputs_are_finite_and_one_to_one(ref, cur, pitch, coarse):
    idx, disp = track_with_neighbours(ref, cur, pitch, coarse=coarse, anneal_steps=4)
    assert idx.shape == (len(ref),) and disp.shape == (len(ref), 2)
    assert np.isfinite(disp).all()
    hit = idx >= 0
    assert len(set(idx[hit].tolist())) == int(hit.sum())
    assert (idx < len(cur)).all()


def test_layout_neighbours_and_pitch():
    ref = hex_layout(3, 10.0)
    assert layout_pitch_px(ref) == pytest.approx(10.0)
    nb, valid = layout_neighbours(ref, 6)
    centre = int(np.argmin(np.hypot(*(ref - ref.mean(0)).T)))
    assert valid[centre].all()
    assert np.allclose(np.hypot(*(ref[nb[centre]] - ref[centre]).T), 10.0)
    assert layout_pitch_px(np.zeros((1, 2))) == 0.0
    nb1, valid1 = layout_neighbours(np.zeros((1, 2)))
    assert nb1.shape == (1, 6) and not valid1.any()


# -- Tracker ------------------------------------------------------------------------------

def test_tracker_without_reference_flags_a_fault():
    tr = Tracker()
    vec, lost = tr.update(np.ones((5, 2)))
    assert tr.faults & FAULT_NO_REFERENCE
    assert vec.shape == (0, 2) and lost.shape == (0,) and np.isfinite(vec).all()


def test_tracker_tracks_a_drag_and_rezeroes():
    ref = hex_layout(4, 12.0)
    tr = Tracker()
    tr.set_reference(ref)
    assert tr.faults == 0
    for k in range(1, 31):                                          # 0.8 px per frame to the right
        vec, lost = tr.update((ref + [0.8 * k, 0.0])[::-1])         # reversed order
    assert not lost.any() and np.allclose(vec, [24.0, 0.0], atol=1e-4)
    assert (tr.idx == np.arange(len(ref))[::-1]).all()
    tr.rezero()
    vec, lost = tr.update(ref + [24.0, 0.0])
    assert np.allclose(vec, 0.0, atol=1e-4) and vec.shape == (len(ref), 2)


def test_tracker_reacquires_after_a_jump():
    rng = np.random.default_rng(5)
    ref = hex_layout(8, 16.0)
    tr = Tracker()
    tr.set_reference(ref)
    moved = big_deformation(ref, 16.0, rng)                         # in one frame
    vec, lost = tr.update(moved)
    correct = ~lost & (tr.idx == np.arange(len(ref)))
    assert correct.mean() >= 0.97
    assert (~lost & ~correct).sum() == 0


@pytest.mark.parametrize("fill", ["predict", "hold", "zero"])
def test_tracker_fill_modes_for_lost_pins(fill):
    ref = hex_layout(3, 10.0)
    tr = Tracker(fill=fill)
    tr.set_reference(ref)
    for x in (1.0, 2.0, 3.0, 3.0):                                  # moves, then rests at 3 px
        tr.update(ref + [x, 0.0])
    cur = np.delete(ref + [3.0, 0.0], 5, axis=0)                    # pin 5 disappears
    vec, lost = tr.update(cur)
    assert lost.tolist() == [i == 5 for i in range(len(ref))]
    expected = {"predict": [3.0, 0.0], "hold": [3.0, 0.0], "zero": [0.0, 0.0]}[fill]
    assert np.allclose(vec[5], expected, atol=1e-4)
    for x in (3.5, 4.0, 4.0):                                       # everything else moves on
        vec, lost = tr.update(np.delete(ref + [x, 0.0], 5, axis=0))
    assert lost[5] and not lost[np.arange(len(ref)) != 5].any()
    if fill == "predict":                                           # follows its neighbours
        assert np.allclose(vec[5], [4.0, 0.0], atol=0.6)
    else:
        assert np.allclose(vec[5], expected, atol=1e-4)
    vec, lost = tr.update(ref + [4.0, 0.0])                         # it comes back
    assert not lost.any() and np.allclose(vec, [4.0, 0.0], atol=1e-4)


@pytest.mark.parametrize("kw,field", [({"max_dist_px": 0}, "max_dist_px"), ({"pitch_px": -2.0}, "pitch_px"),
                                      ({"fill": "last"}, "fill"), ({"reacquire_frac": 2.0}, "reacquire_frac"),
                                      ({"min_tracked_frac": "x"}, "min_tracked_frac"), ({"k": 0}, "k"),
                                      ({"velocity_gain": -1.0}, "velocity_gain")])
def test_tracker_bad_arguments_name_the_field(kw, field):
    with pytest.raises(ValueError, match=field):
        Tracker(**kw)
    with pytest.raises(ValueError, match="pins"):
        Tracker().set_reference(np.zeros((4, 3)))


garbage = st.one_of(
    hnp.arrays(np.float64, st.tuples(st.integers(0, 40), st.just(2)),
               elements=st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                                  st.floats(0, 300))),
    hnp.arrays(np.float32, st.tuples(st.integers(0, 40), st.integers(0, 4))),
    hnp.arrays(np.float64, st.integers(0, 5)),
    st.none(), st.text(max_size=3), st.just([[1.0, "a"]]), st.integers(),
)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(frames=st.lists(garbage, min_size=1, max_size=6), with_ref=st.booleans())
def test_tracker_never_raises_and_stays_finite(frames, with_ref):
    ref = hex_layout(3, 10.0, centre=(150.0, 150.0))
    tr = Tracker()
    if with_ref:
        tr.set_reference(ref)
    good = ref + [1.0, -1.0]
    for cur in frames + [good]:
        vec, lost = tr.update(cur)
        assert np.isfinite(vec).all()
        if with_ref:
            assert vec.shape == (len(ref), 2) and lost.shape == (len(ref),)
            assert vec.dtype == np.float32 and lost.dtype == bool
            hit = tr.idx >= 0
            assert len(set(tr.idx[hit].tolist())) == int(hit.sum())
            if not hit.any():
                assert tr.faults & FAULT_TOO_FEW_PINS
        else:
            assert tr.faults == FAULT_NO_REFERENCE
    if with_ref:
        assert tr.n_tracked == len(ref)                               # recovers on a good frame


def test_tracker_flags_bad_rows_but_uses_the_rest():
    ref = hex_layout(2, 10.0)
    tr = Tracker()
    tr.set_reference(ref)
    cur = np.vstack([ref, [[np.nan, 1.0], [np.inf, np.inf], [1e300, 0.0]]])[::-1]
    vec, lost = tr.update(cur)
    assert tr.faults & FAULT_BAD_INPUT
    assert not lost.any() and np.allclose(vec, 0.0)
    assert np.allclose(cur[tr.idx], ref)                            # indices into the caller's array


def test_tracker_no_allocation_growth():
    rng = np.random.default_rng(6)
    ref = hex_layout(10, 20.0)
    tr = Tracker()
    tr.set_reference(ref)
    frames = [np.delete(ref + rng.normal(0, 0.3, ref.shape), rng.choice(len(ref), 5), axis=0)
              for _ in range(20)]
    for f in frames:                                                # warm up
        tr.update(f)
    tracemalloc.start()
    try:
        for f in frames * 5:
            tr.update(f)
        before = tracemalloc.get_traced_memory()[0]
        for f in frames * 10:
            tr.update(f)
        after = tracemalloc.get_traced_memory()[0]
    finally:
        tracemalloc.stop()
    assert after - before < 16_000


# -- simulated drags: identity switches -----------------------------------------------

def switch_counts(tracker_input):
    """Track a simulated scene against its first frame; per frame the number of
    reference pins assigned to a current pin of another true identity (an
    identity switch), the share of pins lost, and the number of reference pins.

    ``tracker_input`` yields (pins (n, 2), true identity of each pin (n,), -1
    for none)."""
    tr = Tracker()
    counts = []
    lost = []
    ref_ids = None
    for f, (cur, ids) in enumerate(tracker_input):
        if f == 0:
            tr.set_reference(cur)
            ref_ids = ids.copy()
            continue
        _, ls = tr.update(cur)
        hit = (tr.idx >= 0) & (ref_ids >= 0)
        counts.append(int((ids[tr.idx[hit]] != ref_ids[hit]).sum()))
        lost.append(float(ls.mean()))
    return np.array(counts), np.array(lost), len(ref_ids)


def true_pins(sim, seed, noise_px=0.3, drop=0.02):
    """The visible true pins of each frame plus noise, shuffled, a few dropped."""
    rng = np.random.default_rng(seed)
    P, V = sim.truth["pins_px"], sim.truth["visible"]
    for f in range(sim.n_frames):
        ids = np.flatnonzero(V[f] & (rng.random(V.shape[1]) >= (drop if f else 0.0)))
        ids = ids[rng.permutation(ids.size)]
        yield P[f][ids] + rng.normal(0, noise_px, (ids.size, 2)), ids


def scene(name, profile):
    s = load_scene(name)
    if profile != s.profile.name:
        prof = load_profile(profile)
        s = dataclasses.replace(s, profile=prof, width=prof.width, height=prof.height)
    return s


@pytest.mark.parametrize("profile", ["roboskin", "tactip331"])
@pytest.mark.parametrize("name", DRAGS)
def test_drag_identity_switches_true_pins(name, profile):
    sim = Simulator(scene(name, profile), seed=0)
    counts, lost, m = switch_counts(true_pins(sim, seed=len(name)))
    rate = counts / m
    print(f"{profile} {name}: switches per frame mean {rate.mean():.4%} max {rate.max():.4%}, "
          f"lost mean {lost.mean():.2%}")
    assert rate.max() <= MAX_SWITCH_FRAC
    assert lost.mean() <= 0.05


def detected_pins(sim):
    """Pins found by the vision front end on the rendered frames, each with the
    identity of the true pin it belongs to (-1 when none)."""
    from device.pi.vision.extract import ROBOSKIN_PARAMS, TACTIP_SHEAR_PARAMS, PinDetector, find_dome

    params = ROBOSKIN_PARAMS if sim.scene.profile.name == "roboskin" else TACTIP_SHEAR_PARAMS
    frame0 = sim.render(0)
    det = PinDetector(params, frame0.shape[:2], find_dome(frame0))
    gate = 0.45 * layout_pitch_px(sim.rest_pins_px)
    P, V = sim.truth["pins_px"], sim.truth["visible"]
    for f in range(sim.n_frames):
        xy, _ = det.detect(sim.render(f))
        vis = np.flatnonzero(V[f])
        j = match_pins(xy, P[f][vis], gate)
        yield xy, np.where(j >= 0, vis[np.maximum(j, 0)], -1)


@pytest.mark.parametrize("profile", ["roboskin", "tactip331"])
@pytest.mark.parametrize("name", DRAGS)
def test_drag_identity_switches_detected_pins(name, profile):
    sim = Simulator(scene(name, profile), seed=0)
    counts, lost, m = switch_counts(detected_pins(sim))
    assert m >= 0.8 * sim.truth["visible"][0].sum()            # the detector found the layout
    rate = counts / m
    print(f"{profile} {name} (detected): switches per frame mean {rate.mean():.4%} "
          f"max {rate.max():.4%}, lost mean {lost.mean():.2%}")
    assert rate.max() <= MAX_SWITCH_FRAC


# -- real data: tactip_shear ----------------------------------------------------------------

@pytest.fixture(scope="module")
def shear_result():
    from host.analysis.shear import evaluate_tactip_shear

    data = real_data_dir("tactip_shear/targets_images.csv", "tactip_shear/images/image_1.png")
    return evaluate_tactip_shear(data)


@pytest.mark.real
@pytest.mark.slow
def test_tactip_shear_pins_found_and_assigned(shear_result):
    r = shear_result
    print(f"tactip_shear: {r['n_reference_pins']} layout pins, pitch {r['pitch_px']:.1f} px; "
          f"{r['frac_images_95']:.1%} of {r['n_images']} images have >= 95% assigned "
          f"(5th percentile {r['assigned_frac_p5']:.1%}); {r['track_ms_per_image']:.1f} ms/image")
    assert r["n_images"] == 400
    assert 320 <= r["n_reference_pins"] <= 335                     # the 331-pin layout, rim fragments dropped
    assert r["frac_images_95"] >= 0.95


@pytest.mark.real
@pytest.mark.slow
def test_tactip_shear_regression_beats_the_mean(shear_result):
    ratios = {k: v["ratio"] for k, v in shear_result["ratios"].items()}
    raw = {k: v["ratio"] for k, v in shear_result["ratios_raw_features"].items()}
    print("MAE(mean) / MAE(ridge):", {k: round(v, 2) for k, v in ratios.items()},
          "raw vectors + lost flags:", {k: round(v, 2) for k, v in raw.items()})
    assert ratios["pose_z"] >= 3.0
    assert ratios["shear_x"] >= 2.0
    assert ratios["shear_y"] >= 2.0
    for key in ("pose_Rx", "pose_Ry"):                             # reported; must at least beat the mean
        assert math.isfinite(ratios[key]) and ratios[key] > 1.0


def test_mutual_match_keeps_only_pairs_that_choose_each_other():
    """Both pins are nearest to detection 0, which is nearest to pin 1: only that
    pair survives. Greedy matching (match_pins) gives pin 0 its second choice."""
    from device.pi.vision.matching import match_pins, mutual_match
    pred = np.array([[0.0, 0.0], [2.0, 0.0]])
    det = np.array([[1.2, 0.0], [-1.5, 0.0]])
    assert mutual_match(pred, det, 5.0).tolist() == [-1, 0]
    assert match_pins(pred, det, 5.0).tolist() == [1, 0]
    assert mutual_match(pred, det[::-1], 5.0).tolist() == [-1, 1]     # order does not matter
    assert mutual_match(pred, det, 0.5).tolist() == [-1, -1]          # the gate
    assert mutual_match(pred[:0], det, 5.0).tolist() == []
    assert mutual_match(pred, det[:0], 5.0).tolist() == [-1, -1]
