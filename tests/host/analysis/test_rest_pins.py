"""host/analysis/rest_pins.py on synthetic hex lattices: what it keeps equals the
lattice, each rejection has its reason, and centres are sub-pixel true under glare."""
from __future__ import annotations

import numpy as np

from host.analysis.rest_pins import Region, centres, find_rest_pins, lattice_error_px

PITCH = 12.0
SIZE = 220
CX, CY, R = 110.3, 109.7, 80.0


def _sites():
    """A hex lattice of pitch PITCH at a sub-pixel offset; the sites well inside the disc."""
    pts = [(CX + 0.37 + PITCH * (i + 0.5 * (j % 2)), CY - 0.21 + PITCH * np.sqrt(3) / 2 * j)
           for i in range(-9, 10) for j in range(-9, 10)]
    pts = np.array(pts)
    r = np.hypot(pts[:, 0] - CX, pts[:, 1] - CY)
    return pts[r < R - 2.0]


def _render(pins, amps, glare=(), noise=0.0, seed=0):
    yy, xx = np.mgrid[0:SIZE, 0:SIZE].astype(np.float64)
    img = np.full((SIZE, SIZE), 60.0)
    for (gx, gy, gs, ga) in glare:                        # broad LED glare blobs
        img += ga * np.exp(-((xx - gx) ** 2 + (yy - gy) ** 2) / (2 * gs ** 2))
    for (x, y), a in zip(pins, amps):
        img += a * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * 1.8 ** 2))
    img += np.random.default_rng(seed).normal(0, noise, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


def _nearest(a, b):
    return np.hypot(*(a[:, None] - b[None]).transpose(2, 0, 1)).min(axis=1)


def test_the_kept_pins_are_the_lattice_and_each_rejection_has_its_reason():
    sites = _sites()
    amps = np.full(len(sites), 120.0)
    faint = np.argsort(np.hypot(*(sites - (CX + 30, CY)).T))[0]
    amps[faint] = 25.0                                    # a faint pin on a lattice site
    # a spot between rows (off the lattice), and a glare blob
    off = (sites[0] + sites[1]) / 2.0 + np.array([0.0, 0.5 * PITCH])
    extra_pins = np.vstack([sites, off])
    extra_amps = np.append(amps, 25.0)
    glare = [(CX - 30, CY - 20, 14.0, 150.0)]
    frames = [_render(extra_pins, extra_amps, glare, noise=1.0, seed=k) for k in range(4)]
    region = Region(SIZE, SIZE, (CX, CY, R))
    rest = find_rest_pins(frames, region, pin_d_px=6.0, pitch_px=PITCH)
    kept = rest.pins
    assert len(kept) == len(sites)
    assert _nearest(sites, kept).max() < 0.35               # every site found, sub-pixel
    assert _nearest(np.array([sites[faint]]), kept)[0] < 0.5   # the faint pin is kept
    i_off = np.argmin(np.hypot(*(rest.xy - off).T))
    if np.hypot(*(rest.xy[i_off] - off)) < 2.0:             # found: rejected, with a reason
        assert rest.reason[i_off] in ("glare", "duplicate")
    assert set(rest.reason) <= {"kept", "glare", "duplicate", "edge", "unstable"}


def test_a_pin_seen_in_one_frame_of_four_is_unstable():
    sites = _sites()
    frames = [_render(sites, np.full(len(sites), 120.0), seed=k) for k in range(3)]
    blip = np.array([[CX + 0.5 * PITCH, CY + 0.29 * PITCH]])
    frames.append(_render(np.vstack([sites, blip]), np.full(len(sites) + 1, 120.0), seed=3))
    rest = find_rest_pins(frames, Region(SIZE, SIZE, (CX, CY, R)), 6.0, PITCH)
    assert len(rest.pins) == len(sites)
    i = np.argmin(np.hypot(*(rest.xy - blip[0]).T))
    assert rest.reason[i] in ("unstable", "duplicate")


def test_centres_stay_true_on_a_glare_gradient():
    """A faint pin on the flank of a glare blob: the plane-subtracted centroid stays
    within 0.2 px (a 3x3 top-hat centroid, the first round's rule, drifts 0.7 px)."""
    pin = np.array([[100.4, 99.7]])
    img = _render(pin, [30.0], glare=[(112.4, 99.7, 15.0, 150.0)])   # 5x the pin, 1 pitch off
    xy = centres(img, np.array([100]), np.array([100]), 6.0, PITCH)
    assert np.hypot(*(xy[0] - pin[0])) < 0.2


def test_lattice_error_is_small_on_a_site_and_large_between_rows():
    sites = _sites()
    i = np.argmin(np.hypot(*(sites - (CX, CY)).T))
    others = np.delete(sites, i, axis=0)
    assert lattice_error_px(sites[i], others, PITCH) < 0.01
    assert lattice_error_px(sites[i] + [0.0, 0.5 * PITCH], others, PITCH) > 0.2 * PITCH
