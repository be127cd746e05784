"""The sensor dome: where it is in a frame (once per view, not per frame) and its mask.

Split from :mod:`device.pi.vision.extract`, which re-exports both functions.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from device.pi.vision.gray import to_gray


# --------------------------------------------------------------------------
# Dome (region of interest)
# --------------------------------------------------------------------------

_MIN_SIDE_PX = 32          # smaller frames cannot hold a usable dome
_MIN_RADIUS_FRAC = 0.08    # dome radius relative to the shorter image side
_MAX_RADIUS_FRAC = 0.6
_MIN_FILL = 0.7            # contour area / enclosing-circle area
_MIN_CONTRAST = 30.0       # surround minus dome interior, gray levels
_MAX_BORDER_FRAC = 0.05    # share of the dome outline allowed on the image border (cables)
_BINARY_FRAC = 0.97        # share of pixels at exactly 0 or 255 for "binary image"


def find_dome(gray: np.ndarray) -> tuple[float, float, float] | None:
    """Find the sensor dome: returns ``(cx, cy, r)`` in px, or None.

    Two kinds of view are recognised:

    * a camera view (e.g. roboskin): the dome is a dark disc inside a very
      bright surround. The largest dark region of a blurred, Otsu-thresholded
      image that is nearly circular, lies (almost) off the image border and is
      at least 30 gray levels darker than its surround is taken; ``r`` is its
      equivalent radius (sqrt(area/pi)) and the centre its centroid.
    * an already binarised image (e.g. tactip_shear: white pins on black):
      the dome is the disc filled with pins, found from local pin density.

    Returns None for frames without a dome (uniform, saturated, noise, too
    small). Never raises for 2-D/colour numeric input.
    """
    try:
        g = to_gray(gray)
    except (ValueError, TypeError, cv2.error):
        return None
    h, w = g.shape
    if min(h, w) < _MIN_SIDE_PX:
        return None
    lo, hi = int(g.min()), int(g.max())
    if hi - lo < 2 * _MIN_CONTRAST:
        return None
    n_extreme = int(np.count_nonzero(g == 0)) + int(np.count_nonzero(g == 255))
    if n_extreme >= _BINARY_FRAC * g.size:
        return _dome_from_binary(g)
    return _dome_from_dark_disc(g)


def _circle_ok(cnt: np.ndarray, h: int, w: int) -> tuple[float, float, float, float] | None:
    """Centroid, equivalent radius and area of a contour if it is dome-like."""
    area = float(cv2.contourArea(cnt))
    if area <= 0.0:
        return None
    r_eq = math.sqrt(area / math.pi)
    side = min(h, w)
    if not (_MIN_RADIUS_FRAC * side <= r_eq <= _MAX_RADIUS_FRAC * side):
        return None
    (_, _), r_enc = cv2.minEnclosingCircle(cnt)
    if r_enc <= 0 or area / (math.pi * r_enc * r_enc) < _MIN_FILL:
        return None
    m = cv2.moments(cnt)
    if m["m00"] <= 0:
        return None
    return m["m10"] / m["m00"], m["m01"] / m["m00"], r_eq, area


def _ring_means(g: np.ndarray, cx: float, cy: float, r: float) -> tuple[float, float]:
    """Mean gray inside 0.8 r and in the annulus 1.15 r .. 1.4 r (clipped to image)."""
    h, w = g.shape
    mask = np.zeros((h, w), np.uint8)
    c = (int(round(cx)), int(round(cy)))
    cv2.circle(mask, c, max(1, int(round(1.4 * r))), 255, -1)
    cv2.circle(mask, c, max(1, int(round(1.15 * r))), 0, -1)
    outer = cv2.mean(g, mask=mask)[0] if cv2.countNonZero(mask) else float("nan")
    mask[:] = 0
    cv2.circle(mask, c, max(1, int(round(0.8 * r))), 255, -1)
    inner = cv2.mean(g, mask=mask)[0] if cv2.countNonZero(mask) else float("nan")
    return inner, outer


def _dome_from_dark_disc(g: np.ndarray) -> tuple[float, float, float] | None:
    h, w = g.shape
    sigma = max(1.0, min(h, w) / 160.0)
    b = cv2.GaussianBlur(g, (0, 0), sigma)
    t, dark = cv2.threshold(b, 0, 255, cv2.THRESH_BINARY_INV + cv2.THRESH_OTSU)
    contours, _ = cv2.findContours(dark, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    best = None
    for cnt in contours:
        pts = cnt.reshape(-1, 2)
        on_border = (pts[:, 0] <= 0) | (pts[:, 1] <= 0) | (pts[:, 0] >= w - 1) | (pts[:, 1] >= h - 1)
        if np.count_nonzero(on_border) > _MAX_BORDER_FRAC * len(pts):
            continue  # vignetted corners and edges run along the border
        fit = _circle_ok(cnt, h, w)
        if fit is None:
            continue
        if best is None or fit[3] > best[3]:
            best = fit
    if best is None:
        return None
    cx, cy, r, _ = best
    inner, outer = _ring_means(b, cx, cy, r)
    if not (math.isfinite(inner) and math.isfinite(outer)) or outer - inner < _MIN_CONTRAST:
        return None
    return float(cx), float(cy), float(r)


def _dome_from_binary(g: np.ndarray) -> tuple[float, float, float] | None:
    h, w = g.shape
    fg = (g > 127).astype(np.uint8)
    n, _, stats, _ = cv2.connectedComponentsWithStats(fg, connectivity=8)
    if n < 8:
        return None
    areas = stats[1:, cv2.CC_STAT_AREA]
    typical = areas[areas >= max(4, np.percentile(areas, 50))]
    if typical.size == 0:
        return None
    d_pin = 2.0 * math.sqrt(float(np.median(typical)) / math.pi)
    k = int(max(3, round(3.0 * d_pin))) | 1
    density = cv2.blur(fg.astype(np.float32), (k, k))
    peak = float(np.percentile(density, 99))
    if peak <= 0.05:
        return None
    filled = (density >= 0.5 * peak).astype(np.uint8)
    contours, _ = cv2.findContours(filled, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    best = None
    for cnt in contours:
        fit = _circle_ok(cnt, h, w)
        if fit is not None and (best is None or fit[3] > best[3]):
            best = fit
    if best is None:
        return None
    cx, cy, r, _ = best
    return float(cx), float(cy), float(r)


def dome_mask(
    shape: tuple[int, int],
    dome: tuple[float, float, float] | None,
    shrink: float = 1.0,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """uint8 mask (255 inside) of the disc ``shrink * r`` around the dome centre.

    With ``dome`` None the whole frame is the region of interest.
    """
    h, w = int(shape[0]), int(shape[1])
    if out is None:
        out = np.empty((h, w), np.uint8)
    if dome is None:
        out[:] = 255
        return out
    cx, cy, r = dome
    out[:] = 0
    rr = max(0, int(round(r * shrink)))
    if rr > 0 and all(math.isfinite(v) for v in (cx, cy, r)):
        cv2.circle(out, (int(round(cx)), int(round(cy))), rr, 255, -1)
    return out


