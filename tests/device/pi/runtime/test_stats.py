"""Bounded running statistics (device/pi/runtime/stats.py): fixed memory, exact
percentiles while the ring holds the run, within 1 % after."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from device.pi.runtime.stats import BoundedStats


def test_memory_is_fixed_however_many_samples():
    s = BoundedStats(capacity=64)
    for i in range(10_000):
        s.add(0.5 + (i % 97) * 0.01)
    assert s.count == 10_000 and s.retained == 64 and len(s.recent()) == 64
    # the ring keeps the newest samples, oldest first
    assert np.allclose(s.recent(), [0.5 + (i % 97) * 0.01 for i in range(10_000 - 64, 10_000)])


def test_percentiles_are_exact_while_the_ring_holds_the_run():
    xs = np.random.default_rng(0).lognormal(0.0, 1.0, 500)
    s = BoundedStats(capacity=500)
    for x in xs:
        s.add(x)
    for q in (0, 50, 99, 100):
        assert s.percentile(q) == pytest.approx(np.percentile(xs, q))


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(0.01, 1000.0), min_size=50, max_size=400), st.sampled_from([50, 90, 99]))
def test_percentiles_past_the_ring_are_within_one_percent(xs, q):
    s = BoundedStats(capacity=8)
    for x in xs:
        s.add(x)
    got = s.percentile(q)
    srt = np.sort(xs)
    r = q / 100 * (len(xs) - 1)
    # the order statistics around the rank bracket the answer, with 1 % slack
    lo, hi = srt[math.floor(r)], srt[math.ceil(r)]
    assert lo / 1.01 <= got <= hi * 1.01


def test_non_finite_samples_are_counted_not_kept():
    s = BoundedStats(capacity=4)
    for x in (1.0, math.nan, math.inf, 2.0):
        s.add(x)
    assert s.count == 2 and s.rejected == 2 and s.mean == pytest.approx(1.5)
    assert BoundedStats().percentile(50) is None
    with pytest.raises(ValueError):
        BoundedStats(capacity=0)
