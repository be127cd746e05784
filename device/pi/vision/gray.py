"""Gray frames: the shape of a frame the pipeline can read, and its gray image.

Split from :mod:`device.pi.vision.extract`, which re-exports both functions.
"""

from __future__ import annotations

import cv2
import numpy as np


# --------------------------------------------------------------------------
# Grayscale
# --------------------------------------------------------------------------


def image_shape(frame: np.ndarray, min_side: int = 8) -> tuple[int, int] | None:
    """(H, W) of a numeric gray (H,W), (H,W,1), BGR or BGRA frame whose sides are at
    least ``min_side``; None for anything else (no pixel is read)."""
    a = frame
    if not isinstance(a, np.ndarray) or a.ndim not in (2, 3):
        return None
    if a.ndim == 3 and a.shape[2] not in (1, 3, 4):
        return None
    if not (np.issubdtype(a.dtype, np.number) or a.dtype == np.bool_):
        return None
    h, w = int(a.shape[0]), int(a.shape[1])
    return (h, w) if min(h, w) >= min_side else None


def to_gray(frame: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Return a 2-D uint8 gray image from a gray (H,W), (H,W,1), BGR or BGRA frame.

    Non-uint8 input is clipped to [0, 255] (NaN becomes 0). With ``out`` given
    (uint8, shape (H,W)) the result is written there and ``out`` returned.
    """
    a = np.asarray(frame)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    if a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] not in (3, 4)):
        raise ValueError(f"frame must be (H,W), (H,W,1), (H,W,3) or (H,W,4), got shape={a.shape!r}")
    if a.dtype != np.uint8:
        a = np.nan_to_num(a.astype(np.float32, copy=False), nan=0.0, posinf=255.0, neginf=0.0)
        a = np.clip(a, 0, 255).astype(np.uint8)
    if a.ndim == 2:
        if out is None:
            return a if a.flags.c_contiguous else np.ascontiguousarray(a)
        np.copyto(out, a)
        return out
    code = cv2.COLOR_BGR2GRAY if a.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
    if out is None:
        return cv2.cvtColor(a, code)
    cv2.cvtColor(a, code, dst=out)
    return out
