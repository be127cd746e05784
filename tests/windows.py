"""Synthetic windows whose class sets the mean pin displacement: easy to learn.

Shared by the learning, report and runtime tests (through the ``synthetic_windows``
fixture in tests/conftest.py, or imported directly).
"""
from __future__ import annotations

import numpy as np

from host.data.windows import WindowSet

T = 3
def synthetic(n_groups=6, per_group=20, n_pins=5, Tn=T, classes=("a", "b"), imu=True,
              targets=False, seed=0) -> WindowSet:
    """Windows whose class sets the mean pin displacement: easy to learn."""
    rng = np.random.default_rng(seed)
    N = n_groups * per_group
    groups = np.repeat(np.arange(n_groups), per_group)
    lab = np.array([classes[g % len(classes)] for g in groups], object)
    level = np.array([classes.index(x) for x in lab], float)
    v = (rng.normal(0, 0.3, (N, Tn, n_pins, 2)) + level[:, None, None, None] * 2.0)
    y = None
    if targets:
        y = 3.0 * v[:, -1, :, 0].mean(axis=1) + 1.0
    return WindowSet(
        task="pressure" if targets else "surface", window=Tn,
        vectors=v.astype(np.float32), lost=np.zeros((N, Tn, n_pins), bool),
        imu=rng.normal(0, 0.1, (N, Tn, 6)).astype(np.float32) if imu else None,
        grids=rng.random((N, Tn, 4, 4)).astype(np.float32), frames=None,
        contact=np.ones(N, bool), labels=None if targets else lab, targets=y, groups=groups,
        t_index=np.tile(np.arange(per_group) + Tn - 1, n_groups),
        trial_len=np.full(N, per_group + Tn - 1), classes=[] if targets else sorted(classes),
        source={"trials": [{"group": g} for g in range(n_groups)]})
