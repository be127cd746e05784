"""Glare (LED reflections on the dome) in detail: blobs, their statistics over
frames, and the radial brightness profile of the dome."""

from __future__ import annotations

import math
from typing import Iterable

import cv2
import numpy as np

from device.pi.vision.extract import dome_mask, to_gray
from host.analysis.frames import finite, frame_list, locate_dome, stat

__all__ = ["glare_blobs", "measure_glare", "radial_profile"]


def glare_blobs(
    gray: np.ndarray,
    dome: tuple[float, float, float],
    pin_diameter_px: float = 6.0,
    roi_shrink: float = 0.8,
    min_amplitude_gray: float = 40.0,
    background_px: int = 61,
) -> list[dict]:
    """Bright blurry blobs inside the dome, pins removed.

    Pins are removed by a grey opening (disc of about two pin diameters); the
    slowly varying dome background is a second opening with a
    ``background_px`` disc. Local maxima of the difference above
    ``min_amplitude_gray`` are glare blobs. For each: position (x, y and
    radius/angle from the dome centre; angle in degrees from +x towards +y,
    i.e. clockwise on screen), amplitude above background, peak gray,
    background gray, area at half amplitude (px^2) and the sigma of a
    Gaussian fitted to the blob (px).
    """
    g = to_gray(gray)
    cx, cy, r = dome
    k = int(max(3, round(2.0 * pin_diameter_px))) | 1
    no_pins = cv2.morphologyEx(g, cv2.MORPH_OPEN, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
    no_pins = cv2.GaussianBlur(no_pins, (0, 0), 2.0)
    kb = int(background_px) | 1
    bg = cv2.morphologyEx(no_pins, cv2.MORPH_OPEN, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (kb, kb)))
    top = cv2.subtract(no_pins, bg)
    mask = dome_mask(g.shape, dome, roi_shrink)
    top = cv2.bitwise_and(top, mask)
    # local maxima with a neighbourhood of about half the background scale
    kd = max(3, kb // 2) | 1
    dil = cv2.dilate(top, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (kd, kd)))
    ys, xs = np.nonzero((top == dil) & (top >= min_amplitude_gray))
    # one maximum per plateau
    seen = np.zeros(top.shape, np.uint8)
    out = []
    topf = top.astype(np.float64)
    h, w = g.shape
    half = kb // 2
    for y, x in sorted(zip(ys, xs), key=lambda p: -int(top[p[0], p[1]])):
        if seen[y, x]:
            continue
        cv2.circle(seen, (int(x), int(y)), kd // 2, 1, -1)
        amp = float(top[y, x])
        # half-amplitude area: the connected region around (x, y)
        _, lab = cv2.connectedComponents((top >= 0.5 * amp).astype(np.uint8), connectivity=8)
        area = float(np.count_nonzero(lab == lab[y, x]))
        # Gaussian sigma: log-linear fit over the connected region above 30 % of
        # the amplitude, inside a window around the peak
        x0, x1 = max(0, x - half), min(w, x + half + 1)
        y0, y1 = max(0, y - half), min(h, y + half + 1)
        sub = top[y0:y1, x0:x1]
        _, lab30 = cv2.connectedComponents((sub >= 0.3 * amp).astype(np.uint8), connectivity=8)
        sel = lab30 == lab30[y - y0, x - x0]
        gy, gx = np.nonzero(sel)
        r2 = ((gx + x0 - x) ** 2 + (gy + y0 - y) ** 2).astype(np.float64)
        sigma = 0.0
        if r2.size >= 6:
            slope, _ = np.polyfit(r2, np.log(topf[gy + y0, gx + x0]), 1)
            if slope < 0:
                sigma = finite(math.sqrt(-1.0 / (2.0 * slope)))
        dx, dy = x - cx, y - cy
        out.append({
            "x_px": float(x), "y_px": float(y),
            "radius_px": finite(math.hypot(dx, dy)),
            "radius_frac": finite(math.hypot(dx, dy) / r) if r > 0 else 0.0,
            "angle_deg": finite(math.degrees(math.atan2(dy, dx)) % 360.0),
            "amplitude_gray": amp,
            "peak_gray": float(no_pins[y, x]),
            "background_gray": float(bg[y, x]),
            "half_amplitude_area_px2": area,
            "sigma_px": sigma,
        })
    return out


def measure_glare(
    frames: Iterable[np.ndarray],
    dome: tuple[float, float, float] | None = None,
    pin_diameter_px: float = 6.0,
    roi_shrink: float = 0.8,
    min_amplitude_gray: float = 40.0,
) -> dict:
    """Glare blob statistics over frames: count, size, brightness (medians) and
    the blobs of the first frame in full."""
    fl = frame_list(frames)
    faults: list[str] = []
    if dome is None:
        dome = locate_dome(fl)
    if dome is None:
        return {"n_frames": len(fl), "glare_blob_count_median": 0.0, "blobs_first_frame": [],
                "faults": ["no dome found"]}
    per = [glare_blobs(f, dome, pin_diameter_px, roi_shrink, min_amplitude_gray) for f in fl]
    flat = [b for bl in per for b in bl]

    def med(key):
        return stat([b[key] for b in flat], np.median)

    return {
        "n_frames": len(fl),
        "glare_blob_count_median": stat([len(b) for b in per], np.median),
        "glare_amplitude_gray_median": med("amplitude_gray"),
        "glare_peak_gray_median": med("peak_gray"),
        "glare_background_gray_median": med("background_gray"),
        "glare_half_amplitude_area_px2_median": med("half_amplitude_area_px2"),
        "glare_sigma_px_median": med("sigma_px"),
        "glare_radius_frac_median": med("radius_frac"),
        "blobs_first_frame": per[0],
        "faults": faults,
    }


def radial_profile(gray: np.ndarray, centre: tuple[float, float], r_max: int) -> np.ndarray:
    """Median gray at each integer radius 0..r_max-1 around ``centre`` (NaN-free; 0 if empty)."""
    g = to_gray(gray)
    h, w = g.shape
    yy, xx = np.mgrid[:h, :w]
    rr = np.hypot(xx - centre[0], yy - centre[1]).astype(np.int64)
    out = np.zeros(int(r_max), np.float64)
    for k in range(int(r_max)):
        v = g[rr == k]
        out[k] = float(np.median(v)) if v.size else 0.0
    return out
