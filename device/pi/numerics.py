"""Cheap guards for the hot path.

``np.nan_to_num`` costs ~15 µs even on a clean 300-element array; checking first
costs ~2 µs, and on the Pi almost every array is clean. :func:`finite` gives the same
result as ``np.nan_to_num(a, nan=, posinf=, neginf=)`` (a float array, NaN and inf
replaced) and only pays for the replacement when something needs replacing.
"""
from __future__ import annotations

import numpy as np


def finite(a, nan: float = 0.0, posinf: float = 0.0, neginf: float = 0.0,
           dtype=np.float32) -> np.ndarray:
    """``a`` as a ``dtype`` array with NaN -> ``nan``, +inf -> ``posinf``,
    -inf -> ``neginf``. May return ``a`` itself when it is already clean."""
    x = np.asarray(a, dtype=dtype)
    if np.isfinite(x).all():
        return x
    return np.nan_to_num(x, nan=nan, posinf=posinf, neginf=neginf)
