"""Small measures shared by the realism checks: frame lists, the dome over a
few frames, nearest-neighbour spacing (device.pi.vision.neighbours), and finite statistics (0.0 instead of NaN).
"""

from __future__ import annotations

import math
from typing import Iterable, Sequence

import numpy as np

from device.pi.vision.extract import find_dome
from device.pi.vision.neighbours import nearest_neighbour_px  # the one copy; re-exported

__all__ = ["finite", "stat", "frame_list", "locate_dome", "nearest_neighbour_px"]


def finite(x: float, default: float = 0.0) -> float:
    """``x`` as a float, or ``default`` when it is NaN or infinite."""
    x = float(x)
    return x if math.isfinite(x) else default


def stat(values: Sequence[float] | np.ndarray, fn, default: float = 0.0) -> float:
    """``fn(values)`` as a finite float; ``default`` for no values or a non-finite result."""
    a = np.asarray(values, dtype=np.float64)
    if a.size == 0:
        return default
    return finite(fn(a), default)


def frame_list(frames: Iterable[np.ndarray]) -> list[np.ndarray]:
    """The frames as a list of arrays (ValueError when empty or of mixed sizes)."""
    out = [np.asarray(f) for f in frames]
    if not out:
        raise ValueError("frames must hold at least one frame, got frames=[] (0 frames)")
    shape = out[0].shape[:2]
    for i, f in enumerate(out):
        if f.shape[:2] != shape:
            raise ValueError(f"all frames must share one size, got frames[{i}].shape={f.shape!r} vs {shape!r}")
    return out


def locate_dome(frames: Sequence[np.ndarray], max_frames: int = 5) -> tuple[float, float, float] | None:
    """Median dome (cx, cy, r) over the first few frames where one is found."""
    found = []
    for f in frames[: max(1, max_frames)]:
        d = find_dome(f)
        if d is not None:
            found.append(d)
    if not found:
        return None
    cx, cy, r = np.median(np.asarray(found), axis=0)
    return float(cx), float(cy), float(r)
