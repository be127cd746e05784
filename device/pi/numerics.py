"""Cheap guards for the hot path.

``np.nan_to_num`` costs ~15 µs even on a clean 300-element array; checking first
costs ~2 µs, and on the Pi almost every array is clean. :func:`finite` gives the same
result as ``np.nan_to_num(a, nan=, posinf=, neginf=)`` (a float array, NaN and inf
replaced) and only pays for the replacement when something needs replacing.
:func:`softmax` and :func:`sigmoid` are finite for any input; :func:`sigmoid1` is
:func:`sigmoid` of one Python float: the same number at a fraction of the cost.
"""
from __future__ import annotations

import math

import numpy as np

#: logits are clipped to this before exp(); exp(-LOGIT_CLIP) underflows to 0 cleanly
LOGIT_CLIP = 1.0e4


def finite(a, nan: float = 0.0, posinf: float = 0.0, neginf: float = 0.0,
           dtype=np.float32) -> np.ndarray:
    """``a`` as a ``dtype`` array with NaN -> ``nan``, +inf -> ``posinf``,
    -inf -> ``neginf``. May return ``a`` itself when it is already clean."""
    x = np.asarray(a, dtype=dtype)
    if np.isfinite(x).all():
        return x
    return np.nan_to_num(x, nan=nan, posinf=posinf, neginf=neginf)


def _clean_logits(z) -> np.ndarray:
    z = np.asarray(z, dtype=np.float64)
    return np.clip(finite(z, 0.0, LOGIT_CLIP, -LOGIT_CLIP, dtype=np.float64),
                   -LOGIT_CLIP, LOGIT_CLIP)


def softmax(z, axis: int = -1) -> np.ndarray:
    """exp(z) / sum(exp(z)) along ``axis``, float64, finite for any input.

    NaN counts as 0 (no evidence) and +-inf as +-LOGIT_CLIP; the maximum is
    subtracted first, so the largest term is exp(0) = 1 and the sum is >= 1.
    """
    z = _clean_logits(z)
    if z.size == 0:
        return z
    e = np.exp(z - z.max(axis=axis, keepdims=True))
    return e / e.sum(axis=axis, keepdims=True)


def sigmoid(z) -> np.ndarray:
    """1 / (1 + exp(-z)), float64, finite for any input, without overflow:
    exp() only ever sees -|z|."""
    z = _clean_logits(z)
    e = np.exp(-np.abs(z))
    return np.where(z >= 0, 1.0 / (1.0 + e), e / (1.0 + e))


def sigmoid1(z: float) -> float:
    """``float(sigmoid(z))`` for one number: the same cleaning (NaN -> 0, +-inf and
    beyond -> +-LOGIT_CLIP) and the same arithmetic, with numpy's ``exp`` (libm's
    ``math.exp`` may differ in the last bit), so the result is identical."""
    z = float(z)
    if math.isnan(z):
        z = 0.0
    elif z > LOGIT_CLIP:
        z = LOGIT_CLIP
    elif z < -LOGIT_CLIP:
        z = -LOGIT_CLIP
    e = float(np.exp(-abs(z)))
    return 1.0 / (1.0 + e) if z >= 0 else e / (1.0 + e)
