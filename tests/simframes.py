"""Simulated sensor frames with a reference set, and garbage made from them, for the
plausibility and pipeline tests (issue 24)."""
from __future__ import annotations

import copy
import functools

import numpy as np

from device.pi.vision.pipeline import MarkerStream
from device.sim import Simulator, load_scene

N_FRAMES = 16          # the reference is set by frame 4; frames 10.. are pressed


@functools.lru_cache(maxsize=1)
def sim_stream():
    sim = Simulator(load_scene("walk"), seed=0)
    frames = [sim.render(i).copy() for i in range(N_FRAMES)]
    s = MarkerStream("roboskin")
    for f in frames[:8]:
        s.process(f)
    assert s.reference is not None and s.plausibility.reference is not None
    return frames, s


def referenced():
    """(a fresh copy of a stream with its reference set, the simulated frames)."""
    frames, s = sim_stream()
    s = copy.deepcopy(s)
    s.detector.set_dome(s.detector.dome)     # a deep copy loses the detector's buffer views
    return s, frames


def finite_features(ff):
    for a in (ff.vectors, ff.grid, ff.pins):
        assert np.isfinite(a).all()
    for x in (ff.shear_x, ff.shear_y, ff.magnitude, ff.magnitude_sum):
        assert np.isfinite(x)


def garbage(kind: str, base: np.ndarray, rng) -> np.ndarray:
    h, w = base.shape[:2]
    if kind == "black":
        return np.zeros_like(base)
    if kind == "white":
        return np.full_like(base, 255)
    if kind == "salt":
        f = base.copy()
        f[rng.random((h, w)) < 0.1] = 255
        f[rng.random((h, w)) < 0.1] = 0
        return f
    if kind == "random":
        return rng.integers(0, 256, base.shape, dtype=np.uint8)
    if kind == "nan":
        f = base.astype(np.float32)
        f[rng.random((h, w)) < 0.01] = np.nan
        return f
    if kind == "inf":
        f = base.astype(np.float64)
        f[rng.random((h, w)) < 0.01] = rng.choice([np.inf, -np.inf, 1e308, -1e308])
        return f
    if kind == "uint16":
        return base.astype(np.uint16) * 4             # a 10-bit camera: up to 1020
    if kind == "bool":
        return base > 127
    raise ValueError(kind)
