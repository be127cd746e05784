"""Bounded running statistics for the leg runtime (latency and CPU time per frame).

A runtime that runs for days cannot keep every sample. :class:`BoundedStats` keeps:

* the newest ``capacity`` samples in a ring buffer (a fixed numpy array);
* a fixed-bin histogram of every sample of the run: geometric bins, each 1 % wider
  than the one before, from :data:`LOW` to :data:`HIGH` (values outside fall in the
  first or the last bin), plus the count, sum, minimum and maximum.

So memory is fixed when the object is built, whatever the run's length.
``percentile`` is exact while the run has no more samples than the ring holds, and
after that it reads the histogram: within 1 % of the true value for samples inside
``LOW..HIGH``. Non-finite samples are counted in ``rejected`` and not kept.
"""
from __future__ import annotations

import math

import numpy as np

#: lower and upper edge of the histogram (the unit is the caller's: ms here)
LOW = 1e-3
HIGH = 1e5
#: each bin is this much wider than the one before
GROWTH = 1.01
#: samples the ring buffer keeps by default
CAPACITY = 4096

_LOG_G = math.log(GROWTH)
_N_BINS = int(math.ceil(math.log(HIGH / LOW) / _LOG_G)) + 1


class BoundedStats:
    """Count, mean, min, max and percentiles of a stream of non-negative samples in
    fixed memory (see the module docstring)."""

    def __init__(self, capacity: int = CAPACITY):
        if not isinstance(capacity, int) or capacity < 1:
            raise ValueError(f"capacity must be a whole number >= 1, got {capacity!r}")
        self.capacity = capacity
        self._ring = np.zeros(capacity, np.float64)
        self._hist = np.zeros(_N_BINS, np.int64)
        self.count = 0
        self.rejected = 0
        self.total = 0.0
        self.min = math.inf
        self.max = -math.inf

    def add(self, x: float) -> None:
        x = float(x)
        if not math.isfinite(x):
            self.rejected += 1
            return
        self._ring[self.count % self.capacity] = x
        self.count += 1
        self.total += x
        if x < self.min:
            self.min = x
        if x > self.max:
            self.max = x
        b = 0 if x <= LOW else int(math.log(x / LOW) / _LOG_G) + 1
        self._hist[min(b, _N_BINS - 1)] += 1

    def __len__(self) -> int:
        return self.count

    @property
    def retained(self) -> int:
        """Samples held in the ring buffer (at most ``capacity``)."""
        return min(self.count, self.capacity)

    def recent(self) -> np.ndarray:
        """A copy of the retained samples, oldest first."""
        n = self.retained
        if self.count <= self.capacity:
            return self._ring[:n].copy()
        k = self.count % self.capacity
        return np.concatenate([self._ring[k:], self._ring[:k]])

    @property
    def mean(self) -> float | None:
        return self.total / self.count if self.count else None

    def percentile(self, q: float) -> float | None:
        """The ``q``-th percentile (0..100) of every sample of the run; None before
        the first sample."""
        if not 0.0 <= q <= 100.0:
            raise ValueError(f"q must be in 0..100, got {q!r}")
        if self.count == 0:
            return None
        if self.count <= self.capacity:
            return float(np.percentile(self._ring[:self.count], q))
        rank = q / 100.0 * (self.count - 1)
        b = int(np.searchsorted(np.cumsum(self._hist), rank, side="right"))
        b = min(b, _N_BINS - 1)
        # the bin's geometric middle, kept inside what was actually seen
        mid = LOW if b == 0 else LOW * GROWTH ** (b - 0.5)
        return float(min(max(mid, self.min), self.max))
