"""host/analysis/spot_scale.py: spots at each pin's own size on a synthetic skin
whose pins are small and close on one side, big and far apart on the other."""
from __future__ import annotations

import numpy as np

from host.analysis.spot_scale import local_pitch_px, multiscale_spots


def _skin():
    """Left half: 3 px pins 10 px apart; right half: 8 px pins 26 px apart, with faint
    texture specks halfway between the big pins (what one small size picks up)."""
    pins, sizes = [], []
    pins += [(8.3 + 10 * i, 8.6 + 10 * j) for i in range(9) for j in range(15)]
    sizes += [1.5] * (9 * 15)
    big = [(120.4 + 26 * i, 14.2 + 26 * j) for i in range(4) for j in range(6)]
    pins += big
    sizes += [4.0] * len(big)
    specks = [(x + 13, y) for x, y in big[:-6]]
    yy, xx = np.mgrid[0:160, 0:230].astype(np.float64)
    img = np.full(yy.shape, 40.0)
    for (x, y), s in zip(pins, sizes):
        img += 150 * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * s ** 2))
    for x, y in specks:
        img += 35 * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * 1.2 ** 2))
    return np.clip(img, 0, 255).astype(np.uint8), np.array(pins), np.array(specks)


def test_each_pin_is_found_once_at_its_own_size_and_the_specks_are_not():
    img, pins, specks = _skin()
    xy, strength, radius = multiscale_spots(img, np.full(img.shape, 255, np.uint8))
    d = np.hypot(*(pins[:, None] - xy[None]).transpose(2, 0, 1))
    assert (d.min(axis=1) < 0.5).all()                           # every pin, sub-pixel
    assert len(xy) == len(pins)                                  # nothing else: no specks
    near = d.argmin(axis=1)
    assert np.median(radius[near[-24:]]) > 2 * np.median(radius[near[:135]])
    assert strength.min() > 0


def test_local_pitch_follows_the_lattice():
    _, pins, _ = _skin()
    lp = local_pitch_px(pins)
    assert np.allclose(lp[:100], 10.0, atol=0.5)
    assert np.allclose(lp[-6:], 26.0, atol=0.5)
    assert np.isinf(local_pitch_px(np.zeros((1, 2)))).all()
