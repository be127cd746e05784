"""device/pi/vision/neighbours.py: layout neighbours and tracking through
deformations larger than the pin pitch."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from device.pi.vision.matching import match_pins
from device.pi.vision.neighbours import (column_median, layout_neighbours, layout_pitch_px,
                                         neighbour_median, track_with_neighbours)
from tests.pins import hex_pins
from tests.pins import big_deformation, points


# -- track_with_neighbours ---------------------------------------------------------------

def test_track_with_neighbours_follows_moves_larger_than_the_pitch():
    rng = np.random.default_rng(3)
    pitch = 20.0
    ref = hex_pins(10, pitch)
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
    ref = hex_pins(6, 20.0)
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
                                      ({"outlier_sigmas": 8.0}, "outlier_sigmas"),
                                      ({"outlier_sigmas": 0.0}, "outlier_sigmas"),
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
    ref = hex_pins(3, 10.0)
    assert layout_pitch_px(ref) == pytest.approx(10.0)
    nb, valid = layout_neighbours(ref, 6)
    centre = int(np.argmin(np.hypot(*(ref - ref.mean(0)).T)))
    assert valid[centre].all()
    assert np.allclose(np.hypot(*(ref[nb[centre]] - ref[centre]).T), 10.0)
    assert layout_pitch_px(np.zeros((1, 2))) == 0.0
    nb1, valid1 = layout_neighbours(np.zeros((1, 2)))
    assert nb1.shape == (1, 6) and not valid1.any()


def test_nearest_neighbour_px_is_the_one_copy_and_skips_unusable_rows():
    """The pitch, the host's realism and calibration spacing and the localiser's label
    check all measure nearest-neighbour distances with this function."""
    from device.pi.vision.neighbours import nearest_neighbour_px
    from host.analysis import frames

    xy = np.array([[0.0, 0.0], [3.0, 0.0], [3.0, 4.0], [np.nan, 1.0]])
    np.testing.assert_allclose(nearest_neighbour_px(xy), [3.0, 3.0, 4.0])
    assert nearest_neighbour_px(np.zeros((1, 2))).shape == (0,)
    assert layout_pitch_px(xy) == 3.0
    assert frames.nearest_neighbour_px is nearest_neighbour_px


@settings(max_examples=60, deadline=None)
@given(k=st.integers(1, 60), d=st.integers(1, 4), seed=st.integers(0, 2**31 - 1))
def test_column_median_is_numpys_median(k, d, seed):
    a = np.random.default_rng(seed).normal(0, 5, (k, d)).round(1)    # ties included
    np.testing.assert_array_equal(column_median(a), np.median(a, axis=0))


@settings(max_examples=60, deadline=None)
@given(m=st.integers(2, 40), seed=st.integers(0, 2**31 - 1), frac=st.floats(0.0, 1.0))
def test_neighbour_median_matches_a_slow_reference(m, seed, frac):
    rng = np.random.default_rng(seed)
    ref = rng.uniform(0, 100, (m, 2))
    nb, valid = layout_neighbours(ref, 6)
    obs = rng.normal(0, 3, (m, 4))
    ok = rng.random(m) < frac
    rows = np.flatnonzero(rng.random(m) < 0.6)
    med, count = neighbour_median(obs, ok, nb, valid, rows)
    for j, i in enumerate(rows):
        use = [n for n, v in zip(nb[i], valid[i]) if v and ok[n]]
        assert count[j] == len(use)
        want = np.median(obs[use], axis=0) if use else np.zeros(4)
        np.testing.assert_allclose(med[j], want, rtol=0, atol=1e-12)


@settings(max_examples=80, deadline=None)
@given(m=st.integers(2, 60), k=st.integers(1, 8), seed=st.integers(0, 2**31 - 1),
       grid=st.booleans())
def test_layout_neighbours_are_the_nearest_with_ties_by_index(m, k, seed, grid):
    """The k nearest of each pin, ties broken by the lower index (coarse integer
    layouts have many ties), as a stable sort of each whole row gives them."""
    rng = np.random.default_rng(seed)
    ref = (rng.integers(0, 4, (m, 2)).astype(float) if grid else rng.uniform(0, 50, (m, 2)))
    nb, valid = layout_neighbours(ref, k)
    d2 = ((ref[:, None, :] - ref[None, :, :]) ** 2).sum(axis=2)
    np.fill_diagonal(d2, np.inf)
    kk = min(k, m - 1)
    want = np.argsort(d2, axis=1, kind="stable")[:, :kk]
    assert (nb[:, :kk] == want).all()
    dist2 = np.take_along_axis(d2, want, axis=1)
    assert (valid[:, :kk] == (dist2 <= 4.0 * dist2[:, :1])).all()


def test_a_pin_far_from_every_current_pin_stays_near_its_prior_at_the_largest_slack():
    """At the largest outlier_sigmas the floored soft-matching weights must not pull a
    pin with no current pin anywhere near it to the centroid of the cloud."""
    ref = hex_pins(3, 16.0)
    cur = ref[1:] + [1.0, 0.0]                      # pin 0 has no current pin
    far = np.vstack([ref[:1] + [900.0, 900.0], ref[1:]])   # and sits far from the rest
    idx, disp = track_with_neighbours(far, cur, 16.0, outlier_sigmas=6.0, smooth=0.0)
    assert idx[0] == -1
    assert np.hypot(*disp[0]) < 16.0


def test_the_smoothing_gives_the_same_field_by_gathering_as_by_the_dense_product(monkeypatch):
    """Above _DENSE_SMOOTH_PINS the coarse matching's smoothing gathers each pin's
    neighbours instead of multiplying by the dense (m, m) graph (issue 25: linear in
    pins): the same displacement field to float rounding, and the same assignment."""
    import device.pi.vision.neighbours as nbm

    rng = np.random.default_rng(3)
    ref = hex_pins(10, 20.0)                                          # 331 pins
    ref = ref[rng.permutation(len(ref))[:300]]                        # an irregular rim
    cur = ref + np.array([26.0, -9.0]) + rng.normal(0, 0.8, ref.shape)
    cur = cur[rng.permutation(len(cur))[:280]]                        # pins missing
    neighbours = layout_neighbours(ref)
    monkeypatch.setattr(nbm, "_DENSE_SMOOTH_PINS", 10**6)
    idx_d, disp_d = track_with_neighbours(ref, cur, 20.0, neighbours=neighbours, anneal_steps=6)
    monkeypatch.setattr(nbm, "_DENSE_SMOOTH_PINS", 0)
    idx_s, disp_s = track_with_neighbours(ref, cur, 20.0, neighbours=neighbours, anneal_steps=6)
    assert (idx_s == idx_d).all()
    assert np.abs(disp_s - disp_d).max() < 1e-6
    assert (idx_d >= 0).sum() >= 250                                  # and it tracked
