"""Pin clouds shared by the tracking tests (tests/device/pi/vision/...)."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

__all__ = ["points", "hex_pins", "big_deformation"]

#: any (n, 2) float64 cloud of up to 25 pins in [-300, 300] px
points = st.integers(0, 25).flatmap(
    lambda n: hnp.arrays(np.float64, (n, 2), elements=st.floats(-300, 300, allow_nan=False)))


def hex_pins(rings: int, pitch: float, centre=(220.0, 220.0)) -> np.ndarray:
    """A hexagonal pin layout with ``rings`` rings around a centre pin, row by row
    (the sensor profiles' ``hex_layout`` orders pins ring by ring instead)."""
    pts = []
    for q in range(-rings, rings + 1):
        for r in range(max(-rings, -q - rings), min(rings, -q + rings) + 1):
            pts.append((pitch * (q + r / 2.0), pitch * r * math.sqrt(3) / 2.0))
    return np.asarray(pts) + centre


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
