"""Describe a pin layout as a centre pin plus concentric rings of evenly spaced pins."""

from __future__ import annotations

import math

import numpy as np

from host.analysis.frames import finite

__all__ = ["fit_radial_layout"]


def fit_radial_layout(
    xy: np.ndarray,
    centre_guess: tuple[float, float] | None = None,
    search_px: float = 15.0,
    ring_gap_px: float = 3.0,
    min_ring_pins: int = 4,
    max_pins_per_ring: int = 64,
) -> dict:
    """Describe pins as a centre pin plus concentric rings of evenly spaced pins.

    ``xy`` are pin centroids (pooled from a few rest frames is fine; duplicates
    within a ring do not change the result much). The centre is the point
    that makes the pins' radii most clustered (searched within ``search_px``
    of ``centre_guess``, default the mean of the points), then refined by
    least squares on ring membership. Radii closer than ``ring_gap_px`` form
    one ring; points farther than ``ring_gap_px`` from the fitted ring radius
    are outliers; rings with fewer than ``min_ring_pins`` points, or whose
    angles fit no even spacing with at least half the sites seen, are dropped.
    Pass the pins of one frame (or of an average of rest frames), not pins
    pooled from several frames.
    For each ring the pin count is the smallest n >= 4 such that at least 80 %
    of its points lie within ``ring_gap_px`` (along the arc) of an n-fold
    lattice, so a few spurious blobs do not change it; the phase is the angle
    of the first lattice site (degrees from +x towards +y, i.e. clockwise on
    screen, in [0, 360/n)). ``symmetry`` is the n-fold resultant length.

    Returns ``centre_x_px``, ``centre_y_px``, ``centre_pin`` (bool),
    ``rings`` (list of dicts: radius_px, radius_sd_px, count, phase_deg,
    n_points, symmetry), ``total_pins`` and ``residual_rms_px``.
    """
    p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    empty = {"centre_x_px": 0.0, "centre_y_px": 0.0, "centre_pin": False, "rings": [],
             "total_pins": 0, "residual_rms_px": 0.0}
    if len(p) < min_ring_pins:
        return empty
    c0 = np.asarray(centre_guess if centre_guess is not None else p.mean(axis=0), np.float64)

    def sharpness(cands: np.ndarray) -> np.ndarray:
        out = np.empty(len(cands))
        for i, c in enumerate(cands):
            r = np.hypot(*(p - c).T)
            dr = r[:, None] - r[None, :]
            out[i] = np.exp(-0.5 * dr * dr).sum()
        return out

    for half, step in ((search_px, 1.0), (1.5, 0.25)):
        g = np.arange(-half, half + 1e-9, step)
        cands = np.array([(c0[0] + dx, c0[1] + dy) for dx in g for dy in g])
        c0 = cands[int(np.argmax(sharpness(cands)))]

    def rings_of(c: np.ndarray):
        r = np.hypot(*(p - c).T)
        order = np.argsort(r)
        groups, cur = [], [order[0]]
        for a, b in zip(order[:-1], order[1:]):
            if r[b] - r[a] > ring_gap_px:
                groups.append(cur)
                cur = []
            cur.append(b)
        groups.append(cur)
        return r, groups

    r, groups = rings_of(c0)
    centre_pin = any(float(np.median(r[gp])) < ring_gap_px for gp in groups)
    groups = [gp for gp in groups if len(gp) >= min_ring_pins and float(np.median(r[gp])) >= ring_gap_px]
    if not groups:
        return {**empty, "centre_x_px": float(c0[0]), "centre_y_px": float(c0[1]), "centre_pin": centre_pin,
                "total_pins": int(centre_pin)}
    # least-squares refinement of the centre and ring radii
    idx = np.concatenate(groups)
    ring_of = np.concatenate([[k] * len(gp) for k, gp in enumerate(groups)])
    params = np.concatenate([c0, [float(np.median(r[gp])) for gp in groups]])
    res = np.zeros(len(idx))
    for _ in range(10):
        d = p[idx] - params[:2]
        rr = np.maximum(np.hypot(*d.T), 1e-9)
        res = rr - params[2 + ring_of]
        J = np.zeros((len(idx), len(params)))
        J[:, 0] = -d[:, 0] / rr
        J[:, 1] = -d[:, 1] / rr
        J[np.arange(len(idx)), 2 + ring_of] = -1.0
        step_ = np.linalg.lstsq(J, -res, rcond=None)[0]
        params += step_
        if np.abs(step_).max() < 1e-4:
            break
    c = params[:2]
    rings = []
    r_all = np.hypot(*(p - c).T)
    for k, gp in enumerate(groups):
        rad = float(params[2 + k])
        gp = np.asarray(gp)[np.abs(r_all[gp] - rad) <= ring_gap_px]  # radial outliers out
        if len(gp) < min_ring_pins:
            continue
        d = p[gp] - c
        ang = np.arctan2(d[:, 1], d[:, 0])
        best_n, best_R, phase = 0, 0.0, 0.0
        for n in range(4, min(max_pins_per_ring, 2 * len(gp)) + 1):
            z = np.mean(np.exp(1j * n * ang))
            ph = float(np.angle(z)) / n
            step_rad = 2.0 * math.pi / n
            dev = (ang - ph + 0.5 * step_rad) % step_rad - 0.5 * step_rad
            tol = min(ring_gap_px, 0.25 * rad * step_rad)
            if np.mean(np.abs(dev) * rad <= tol) >= 0.8:
                best_n, best_R = n, float(np.abs(z))
                phase = math.degrees(ph) % (360.0 / n)
                break
        if best_n == 0:
            continue  # no even spacing explains these points: not a ring of pins
        rings.append({
            "radius_px": round(finite(params[2 + k]), 2),
            "radius_sd_px": round(finite(np.std(np.hypot(*d.T))), 2),
            "count": int(best_n),
            "phase_deg": round(finite(phase), 2),
            "n_points": int(len(gp)),
            "symmetry": round(finite(best_R), 3),
        })
    return {
        "centre_x_px": round(finite(c[0]), 2),
        "centre_y_px": round(finite(c[1]), 2),
        "centre_pin": bool(centre_pin),
        "rings": rings,
        "total_pins": int(centre_pin) + int(sum(rg["count"] for rg in rings)),
        "residual_rms_px": round(finite(np.sqrt(np.mean(res**2))), 3),
    }
