"""The hot-path guards (device/pi/numerics.py): softmax and sigmoid are finite for any
input."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from device.pi.numerics import sigmoid, sigmoid1, softmax


finite_or_not = st.floats(allow_nan=True, allow_infinity=True, width=64)


@given(arrays(np.float64, st.integers(1, 12), elements=finite_or_not))
@settings(max_examples=200, deadline=None)
def test_softmax_is_finite_normalised_and_shift_invariant(z):
    p = softmax(z)
    assert np.isfinite(p).all() and (p >= 0).all() and (p <= 1).all()
    assert p.sum() == pytest.approx(1.0)
    zf = np.nan_to_num(z, nan=0.0, posinf=1e4, neginf=-1e4).clip(-1e4, 1e4)
    if np.isfinite(z).all() and np.abs(z).max() < 1e3:
        assert np.allclose(softmax(z + 123.0), p)
        assert zf[np.argmax(p)] >= zf.max() - 1e-9     # the top class has the top logit
        i, j = np.argmax(zf), np.argmin(zf)
        assert p[i] >= p[j]


@given(arrays(np.float64, st.integers(1, 12), elements=finite_or_not))
@settings(max_examples=200, deadline=None)
def test_sigmoid_is_finite_bounded_symmetric_and_monotone(z):
    s = sigmoid(z)
    assert np.isfinite(s).all() and (s >= 0).all() and (s <= 1).all()
    ok = ~np.isnan(z)
    assert np.allclose(sigmoid(-z[ok]), 1.0 - s[ok], atol=1e-12)
    order = np.argsort(np.nan_to_num(z[ok], posinf=1e308, neginf=-1e308), kind="stable")
    assert (np.diff(s[ok][order]) >= 0).all()



@given(finite_or_not)
@settings(max_examples=300, deadline=None)
def test_sigmoid_of_one_number_is_the_array_sigmoid_to_the_bit(z):
    s = sigmoid1(z)
    assert s == float(sigmoid(np.array([z]))[0])
    assert 0.0 <= s <= 1.0
