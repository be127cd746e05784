"""Synthetic TacTip-like frames with known answers, shared by the marker front-end
tests (tests/device/pi/vision/test_extract.py) and the realism measures
(tests/host/analysis/test_*.py): a dark dome in a bright surround with Gaussian pins on
rings, and degenerate frames (black, white, saturated, noise) for property tests."""
from __future__ import annotations

import cv2
import numpy as np
from hypothesis import strategies as st

from device.profile import VisionParams

__all__ = ["DOME", "RINGS", "PHASE_DEG", "SYNTH_PARAMS", "ring_layout", "render", "match",
           "DEGENERATE_KINDS", "degenerate_frames"]

DOME = (160.0, 120.0, 100.0)  # cx, cy, r in a 240x320 frame
RINGS = ((14.0, 12), (24.0, 12), (36.0, 24), (48.0, 24), (60.0, 24))
PHASE_DEG = 3.0
SYNTH_PARAMS = VisionParams(block=11, offset=14.0, blur_sigma_px=1.0, min_area_px=6,
                            max_area_px=100, roi_shrink=0.9)


def ring_layout(centre=DOME[:2], rings=RINGS, phase_deg=PHASE_DEG, centre_pin=True) -> np.ndarray:
    """Pin centres (n, 2) on rings of (radius px, count) around ``centre``, plus a
    centre pin."""
    pts = [tuple(centre)] if centre_pin else []
    for r, n in rings:
        a = np.radians(phase_deg + np.arange(n) * 360.0 / n)
        pts += list(zip(centre[0] + r * np.cos(a), centre[1] + r * np.sin(a)))
    return np.asarray(pts, np.float64)


def render(pins: np.ndarray, h=240, w=320, dome=DOME, pin_sigma=1.4, pin_amp=120.0,
           inside=70.0, surround=250.0, glare=(), bgr=False) -> np.ndarray:
    """Dark dome in a bright surround, Gaussian pins, optional flat glare discs (x, y, radius)."""
    yy, xx = np.mgrid[:h, :w].astype(np.float64)
    cx, cy, r = dome
    img = np.where((xx - cx) ** 2 + (yy - cy) ** 2 <= r * r, inside, surround)
    for x, y in pins:
        x0, x1 = int(max(0, x - 6)), int(min(w, x + 7))
        y0, y1 = int(max(0, y - 6)), int(min(h, y + 7))
        sub = (xx[y0:y1, x0:x1] - x) ** 2 + (yy[y0:y1, x0:x1] - y) ** 2
        img[y0:y1, x0:x1] += pin_amp * np.exp(-0.5 * sub / pin_sigma**2)
    for gx, gy, gr in glare:
        img[(xx - gx) ** 2 + (yy - gy) ** 2 <= gr * gr] = 255.0
    g = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    return cv2.cvtColor(g, cv2.COLOR_GRAY2BGR) if bgr else g


def match(found: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Distance from each true point to the nearest found point."""
    if len(found) == 0:
        return np.full(len(truth), np.inf)
    d = np.sqrt(((truth[:, None, :] - found[None, :, :]) ** 2).sum(-1))
    return d.min(axis=1)


#: the kinds of frame degenerate_frames draws
DEGENERATE_KINDS = ("black", "white", "saturated", "noise")


@st.composite
def degenerate_frames(draw):
    """(kind, frame): a constant, saturated or noise frame of 1..96 x 1..128 px, grey
    or colour."""
    h = draw(st.integers(1, 96))
    w = draw(st.integers(1, 128))
    kind = draw(st.sampled_from(DEGENERATE_KINDS))
    colour = draw(st.booleans())
    shape = (h, w, 3) if colour else (h, w)
    if kind == "black":
        f = np.zeros(shape, np.uint8)
    elif kind == "white":
        f = np.full(shape, 255, np.uint8)
    elif kind == "saturated":
        level = draw(st.integers(0, 255))
        f = np.full(shape, level, np.uint8)
        if colour:
            f[:, :, draw(st.integers(0, 2))] = 255  # one clipped channel
    else:
        seed = draw(st.integers(0, 2**32 - 1))
        f = np.random.default_rng(seed).integers(0, 256, shape, dtype=np.uint8)
    return kind, f

