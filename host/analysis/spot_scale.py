"""Pin spots at each pin's own size, for a skin whose pins change size across the
frame (``host calibrate`` on a flat skin seen through a wide-angle lens: pins
about 30 px apart in the middle, 10 px at the rim).

A pin is a bright disc; the scale-normalised Laplacian of Gaussian
(``-sigma^2 * LoG``) of a disc of diameter d peaks at sigma about d / 2.8. The
spots are the local maxima of that response over space and a ladder of
``SIGMAS_PX`` (:func:`multiscale_spots`); each spot's radius is sigma * sqrt(2).
A stronger spot hides any weaker one closer than ``HIDE_RADII`` times the larger
of their radii, which drops the texture between two big pins (half a pitch from
each, within 2.8 radii of a pin whose pitch is about four radii) while the
neighbouring pins (a pitch away) stay.

:func:`local_pitch_px` gives each spot the pitch of its own part of the lattice.
"""
from __future__ import annotations

import math

import cv2
import numpy as np

#: the scale ladder (px): pins of about 4 to 24 px across
SIGMAS_PX = (1.5, 1.9, 2.4, 3.0, 3.8, 4.8, 6.0, 7.5)
#: a stronger spot hides a weaker one within this many times the larger radius
HIDE_RADII = 2.8
#: a spot's response must pass this (grey levels of the normalised LoG)
MIN_RESPONSE = 8.0


def multiscale_spots(gray: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                                     np.ndarray]:
    """Spots of one gray frame: centres (n, 2) px (sub-pixel: a parabola through the
    response's peak and its neighbours), strengths (n,) (the normalised LoG
    response) and radii (n,) px."""
    f = gray.astype(np.float32)
    stack = np.stack([-(s * s) * cv2.Laplacian(cv2.GaussianBlur(f, (0, 0), s), cv2.CV_32F)
                      for s in SIGMAS_PX])
    k = np.ones((5, 5), np.uint8)
    space = np.stack([cv2.dilate(r, k) for r in stack])
    up = np.concatenate([space[1:], np.full_like(space[:1], -np.inf)])
    down = np.concatenate([np.full_like(space[:1], -np.inf), space[:-1]])
    peak = (stack >= space) & (stack >= up) & (stack >= down) & (stack > MIN_RESPONSE)
    peak &= (mask > 0)[None]
    si, ys, xs = np.nonzero(peak)
    resp = stack[si, ys, xs].astype(np.float64)
    radius = np.asarray(SIGMAS_PX)[si] * math.sqrt(2.0)
    xy = np.column_stack([xs, ys]).astype(np.float64)
    keep = _hide_weaker(xy, resp, radius)
    xy, resp, radius, si = xy[keep], resp[keep], radius[keep], si[keep]
    xy += _subpixel(stack, si, xy.astype(np.int64))
    return xy, resp, radius


def _hide_weaker(xy, resp, radius) -> np.ndarray:
    keep = np.zeros(len(xy), bool)
    if not len(xy):
        return keep
    order = np.argsort(-resp)
    cell = max(1.0, HIDE_RADII * float(radius.max()))
    grid: dict[tuple[int, int], list[int]] = {}
    for i in order:
        cx, cy = int(xy[i, 0] // cell), int(xy[i, 1] // cell)
        near = [j for gx in (cx - 1, cx, cx + 1) for gy in (cy - 1, cy, cy + 1)
                for j in grid.get((gx, gy), ())]
        if near:
            nj = np.asarray(near)
            d = np.hypot(*(xy[nj] - xy[i]).T)
            if (d < HIDE_RADII * np.maximum(radius[nj], radius[i])).any():
                continue
        keep[i] = True
        grid.setdefault((cx, cy), []).append(i)
    return keep


def _subpixel(stack, si, ij) -> np.ndarray:
    """A parabola's vertex through each peak and its left/right (up/down) neighbours."""
    if not len(si):
        return np.zeros((0, 2))
    _, h, w = stack.shape
    x = np.clip(ij[:, 0], 1, w - 2)
    y = np.clip(ij[:, 1], 1, h - 2)
    c = stack[si, y, x]
    off = []
    for l, r in ((stack[si, y, x - 1], stack[si, y, x + 1]),
                 (stack[si, y - 1, x], stack[si, y + 1, x])):
        den = l - 2.0 * c + r
        with np.errstate(all="ignore"):
            o = np.where(den < 0, 0.5 * (l - r) / den, 0.0)
        off.append(np.clip(o, -0.5, 0.5))
    return np.column_stack(off).astype(np.float64)


def local_pitch_px(xy: np.ndarray, k: int = 6) -> np.ndarray:
    """Each point's local pitch (n,) px: the median nearest-neighbour distance of it
    and its ``k`` nearest points (inf with fewer than two points)."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    n = len(xy)
    if n < 2:
        return np.full(n, np.inf)
    d = np.hypot(*(xy[:, None] - xy[None]).transpose(2, 0, 1))
    np.fill_diagonal(d, np.inf)
    nn = d.min(axis=1)
    kk = min(k, n - 1)
    near = np.argsort(d, axis=1)[:, :kk]
    return np.median(np.column_stack([nn, nn[near]]), axis=1)
