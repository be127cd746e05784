"""Contact grid (eq. 1), average vector and magnitude sum (eq. 3): values and hard cases."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from device.pi.vision.features import (ContactGrid, average_vector, direction_deg, magnitude_sum,
                                shear_and_sum, vector_features)


def test_grid_marks_the_changed_cell_and_fades_by_gamma():
    g = ContactGrid(n=4, gamma=0.1, contact_threshold=0.2)
    ref = np.zeros((40, 40), np.uint8)
    g.set_reference(ref)
    hit = ref.copy()
    hit[:10, :10] = 255                      # cell (0, 0) changes completely
    grid, contact = g.update(hit)
    glob = 100 / 1600
    assert grid[0, 0] == pytest.approx(1.0 - glob - 0.1, abs=0.01)
    assert contact and grid[1:, 1:].max() == 0.0
    # the stimulus ends: the cell fades by gamma a frame
    first = float(grid[0, 0])
    values = [float(g.update(ref)[0][0, 0]) for _ in range(3)]
    assert np.allclose(np.diff([first] + values), -0.1, atol=0.011)
    for _ in range(20):
        grid, contact = g.update(ref)
    assert grid.max() == 0.0 and not contact


def test_grid_ignores_a_change_over_the_whole_dome():
    g = ContactGrid(n=4, gamma=0.01)
    ref = np.zeros((40, 40), np.uint8)
    g.set_reference(ref)
    grid, contact = g.update(np.full_like(ref, 255))
    assert grid.max() == 0.0 and not contact     # the global mean is subtracted


@pytest.mark.parametrize("shape,n", [((3, 2), 8), ((1, 1), 256), ((7, 640), 16)])
def test_grid_larger_than_image_does_not_divide_by_zero(shape, n):
    g = ContactGrid(n=n)
    g.set_reference(np.zeros(shape, np.uint8))
    grid, _ = g.update(np.full(shape, 255, np.uint8))
    assert grid.shape == (n, n) and np.isfinite(grid).all()


def test_grid_without_reference_or_with_a_new_size_reports_no_contact():
    g = ContactGrid(n=4)
    grid, contact = g.update(np.full((10, 10), 255, np.uint8))
    assert not contact and np.isfinite(grid).all()
    g.set_reference(np.zeros((10, 10), np.uint8))
    grid, contact = g.update(np.full((12, 10), 255, np.uint8))
    assert not contact


@pytest.mark.parametrize("kw,match", [({"n": 0}, "grid n"), ({"gamma": -1}, "gamma"),
                                      ({"contact_threshold": float("nan")}, "contact_threshold")])
def test_grid_bad_parameters_name_the_field(kw, match):
    with pytest.raises(ValueError, match=match):
        ContactGrid(**kw)


@settings(max_examples=60, deadline=None)
@given(h=st.integers(1, 60), w=st.integers(1, 60), n=st.integers(1, 40),
       seed=st.integers(0, 2**31), gamma=st.floats(0, 1))
def test_grid_any_binary_images_stay_finite_and_bounded(h, w, n, seed, gamma):
    rng = np.random.default_rng(seed)
    g = ContactGrid(n=n, gamma=gamma)
    g.set_reference((rng.random((h, w)) > 0.5).astype(np.uint8) * 255)
    for _ in range(3):
        grid, contact = g.update((rng.random((h, w)) > 0.5).astype(np.uint8) * 255)
        assert np.isfinite(grid).all() and grid.min() >= 0 and grid.max() <= 1
        assert isinstance(contact, bool)


def test_average_vector_direction_and_magnitude_sum():
    v = np.array([[3.0, 4.0], [1.0, 0.0], [np.nan, 1.0]])
    valid = np.array([True, True, True])
    assert average_vector(v, valid) == pytest.approx((2.0, 2.0))   # the NaN row is skipped
    assert magnitude_sum(v, valid) == pytest.approx(6.0)
    assert average_vector(v, np.array([False, True, True])) == pytest.approx((1.0, 0.0))
    assert direction_deg(0.0, 1.0) == pytest.approx(90.0)          # image y points down
    assert direction_deg(-1.0, 0.0) == pytest.approx(180.0)


@settings(max_examples=100, deadline=None)
@given(arrays(np.float64, st.tuples(st.integers(0, 50), st.just(2)),
              elements=st.floats(allow_nan=True, allow_infinity=True)))
def test_vector_features_are_finite_for_any_input(v):
    ax, ay = average_vector(v)
    s = magnitude_sum(v)
    finite = np.isfinite(v).all(axis=1)
    used = np.clip(v[finite], -1e6, 1e6)           # an independent oracle, float64
    if len(used):
        assert (ax, ay) == pytest.approx(tuple(used.mean(axis=0)), rel=1e-9, abs=1e-9)
        assert s == pytest.approx(np.hypot(used[:, 0], used[:, 1]).sum(), rel=1e-9)
    else:
        assert (ax, ay, s) == (0.0, 0.0, 0.0)
    assert math.isfinite(ax) and math.isfinite(ay) and math.isfinite(s)
    assert math.isfinite(direction_deg(ax, ay))
    f = vector_features(v, ~finite)
    assert f.shape == (3 * len(v),) and np.isfinite(f).all()


@pytest.mark.parametrize("kind", ["float255", "float01", "bool", "int64", "nan"])
def test_contact_grid_converts_a_binary_of_another_dtype_and_counts_it(kind):
    """A float/bool binary image was silently 'no contact'; now non-zero is foreground,
    the contact is the uint8 image's and ``converted`` says it happened."""
    ref = np.zeros((64, 64), np.uint8)
    cur = ref.copy()
    cur[:16, :16] = 255                                   # one corner changed
    want = ContactGrid(4, 0.01, 0.03)
    want.set_reference(ref)
    g_want, c_want = want.update(cur)
    assert c_want
    conv = {"float255": lambda b: b.astype(np.float32), "float01": lambda b: b / 255.0,
            "bool": lambda b: b > 0, "int64": lambda b: b.astype(np.int64),
            "nan": lambda b: np.where(b > 0, np.nan, 0.0)}[kind]
    grid = ContactGrid(4, 0.01, 0.03)
    grid.set_reference(conv(ref))
    g, c = grid.update(conv(cur))
    assert c and np.array_equal(g, g_want) and grid.converted == 2 and not grid.bad_input
    g, c = grid.update(np.zeros((8, 8), np.uint8))        # another size: flagged
    assert not c and grid.bad_input


# -- behaviour the mutation tester found unasserted (issue 24) ------------------------------

def test_shear_and_sum_equal_an_independent_computation():
    v = np.array([[3.0, 4.0], [-1.0, 0.0], [np.nan, 1.0], [0.0, -2.0], [2e6, 0.0]])
    valid = np.array([True, True, True, False, True])
    # rows 0, 1 and the clipped 1e6 one are used; NaN and the invalid row are not
    ax, ay, s = shear_and_sum(v, valid)
    assert (ax, ay) == pytest.approx(((3.0 - 1.0 + 1e6) / 3, 4.0 / 3))
    assert s == pytest.approx(5.0 + 1.0 + 1e6)
    assert average_vector(v) == pytest.approx(((3.0 - 1.0 + 1e6) / 4, (4.0 - 2.0) / 4))
    assert magnitude_sum(v) == pytest.approx(5.0 + 1.0 + 2.0 + 1e6)


@pytest.mark.parametrize("v, valid", [(np.full((4, 2), np.nan), None),
                                      (np.ones((3, 2)), np.zeros(3, bool)),
                                      (np.zeros((0, 2)), None)])
def test_zeros_when_no_pin_is_valid(v, valid):
    assert shear_and_sum(v, valid) == (0.0, 0.0, 0.0)
    assert average_vector(v, valid) == (0.0, 0.0) and magnitude_sum(v, valid) == 0.0


@pytest.mark.parametrize("dx, dy, deg", [(1.0, 0.0, 0.0), (0.0, 1.0, 90.0), (-1.0, 0.0, 180.0),
                                         (0.0, -1.0, 270.0), (1.0, -1.0, 315.0),
                                         (-1.0, -1.0, 225.0), (0.0, 0.0, 0.0),
                                         (np.nan, 1.0, 0.0), (1.0, np.inf, 0.0)])
def test_direction_of_negative_and_degenerate_vectors(dx, dy, deg):
    assert direction_deg(dx, dy) == pytest.approx(deg)


def test_vector_features_are_the_vectors_then_the_lost_flags():
    v = np.array([[1.5, -2.0], [np.nan, np.inf], [-np.inf, 3e7]])
    lost = np.array([False, True, True])
    f = vector_features(v, lost)
    assert f.dtype == np.float32
    np.testing.assert_array_equal(f, [1.5, -2.0, 0.0, 0.0, 0.0, 1e6, 0.0, 1.0, 1.0])


def test_contact_is_the_cell_change_minus_gamma_above_the_threshold():
    """One quadrant of a 2x2 grid changes fully: its cell minus the global mean is
    0.75; minus gamma 0.1 that is 0.65, so a 0.6 threshold sees contact, 0.7 not."""
    ref = np.zeros((4, 4), np.uint8)
    cur = ref.copy()
    cur[:2, :2] = 255
    for threshold, contact in ((0.6, True), (0.7, False)):
        g = ContactGrid(n=2, gamma=0.1, contact_threshold=threshold)
        g.set_reference(ref)
        grid, got = g.update(cur)
        assert got is contact
        np.testing.assert_allclose(grid, [[0.65, 0.0], [0.0, 0.0]], atol=1e-6)
    grid, got = g.update(ref)                    # lifted: no contact, the trace fades
    assert got is False
    np.testing.assert_allclose(grid, [[0.55, 0.0], [0.0, 0.0]], atol=1e-6)


def test_the_contact_grid_is_1_to_256_cells_a_side():
    assert ContactGrid(256).grid.shape == (256, 256) and ContactGrid(1).grid.shape == (1, 1)
    for bad in (0, 257, 8.0, True + 0.5):
        with pytest.raises(ValueError, match="1..256"):
            ContactGrid(bad)
