"""host/analysis/rest_pins.py on synthetic hex lattices: what it keeps equals the
lattice, each rejection has its reason, and centres are sub-pixel true under glare."""
from __future__ import annotations

import numpy as np
import pytest

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


def test_a_clipped_pin_and_a_wandering_pin_are_kept_but_loose():
    """A pin whose core is clipped at full scale (an LED glare core) and a pin whose
    centre wanders by 1 px over the rest frames stay in the layout, flagged loose;
    the other pins are steady (their centres move by noise only)."""
    sites = _sites()
    i_clip = int(np.argmin(np.hypot(*(sites - (CX - 25, CY + 10)).T)))
    i_wander = int(np.argmin(np.hypot(*(sites - (CX + 25, CY - 10)).T)))
    amps = np.full(len(sites), 120.0)
    amps[i_clip] = 400.0                                  # clipped at 255 over its core
    frames = []
    for k in range(6):
        pins = sites.copy()
        pins[i_wander, 0] += (0.0, 1.0, -1.0)[k % 3]      # median distance 1 px < 0.1 pitch
        frames.append(_render(pins, amps, noise=1.0, seed=k))
    rest = find_rest_pins(frames, Region(SIZE, SIZE, (CX, CY, R)), 6.0, PITCH)
    assert len(rest.pins) == len(sites)                   # neither is rejected
    kept = rest.reason == "kept"
    loose_xy = rest.xy[kept & rest.loose]
    assert len(loose_xy) == 2
    assert _nearest(sites[[i_clip, i_wander]], loose_xy).max() < 1.0
    i = int(np.argmin(np.hypot(*(rest.xy - sites[i_clip]).T)))
    assert rest.clipped[i] == 1.0 and rest.wander_px[i] < 0.3
    j = int(np.argmin(np.hypot(*(rest.xy - sites[i_wander]).T)))
    assert rest.wander_px[j] > 0.9 and rest.clipped[j] == 0.0
    steady = kept & ~rest.loose
    assert rest.wander_px[steady].max() < 0.3
    assert rest.pins_loose.sum() == 2 and len(rest.pins_loose) == len(rest.pins)


def test_agreement_reports_the_steady_pins_apart():
    """Two layouts of one lattice, shifted; one pin 2 px off in the second: the
    all-pins maximum shows it, the steady figures leave it out when it is loose."""
    from host.analysis.rest_pins import agreement
    a = _sites()
    b = a + [3.0, -2.0]
    b[5] += [2.0, 0.0]
    plain = agreement(a, b, PITCH)
    assert plain["max_px"] == pytest.approx(2.0, abs=0.01)
    assert plain["steady"]["max_px"] == plain["max_px"]      # nothing flagged: the same
    loose_b = np.zeros(len(b), bool)
    loose_b[5] = True
    ag = agreement(a, b, PITCH, None, loose_b)
    assert ag["matched"] == len(a) and ag["steady"]["matched"] == len(a) - 1
    assert ag["steady"]["max_px"] < 0.01 and ag["max_px"] == pytest.approx(2.0, abs=0.01)
    with pytest.raises(ValueError, match=r"loose_a \(3,\) for \d+ pins"):
        agreement(a, b, PITCH, np.zeros(3, bool), None)


def test_merged_pins_carry_their_flags_and_steady_positions():
    """A pin loose in two of three clips stays loose in the merge; one loose in one
    clip is steady, at the mean of the clips where it was steady."""
    from host.analysis.rest_pins import merge_with_flags
    a = _sites()
    lays = [a.copy(), a + [0.0, 0.0], a + [0.0, 0.0]]
    lays[1][0] += [1.5, 0.0]                           # pin 0 off (and loose) in clip 1
    flags = [np.zeros(len(a), bool) for _ in lays]
    flags[1][0] = True
    flags[0][1] = flags[2][1] = True                   # pin 1 loose in clips 0 and 2
    merged, loose = merge_with_flags(lays, PITCH, flags)
    assert len(merged) == len(a) and loose.sum() == 1
    i0 = int(np.argmin(np.hypot(*(merged - a[0]).T)))
    i1 = int(np.argmin(np.hypot(*(merged - a[1]).T)))
    assert not loose[i0] and np.hypot(*(merged[i0] - a[0])) < 0.01   # not pulled by clip 1
    assert loose[i1]


def test_the_overlay_draws_loose_pins_in_their_own_colour():
    from host.analysis.rest_pins import COLOURS, OVERLAY_SCALE, RestPins, overlay_image
    xy = np.array([[150.0, 150.0], [180.0, 150.0], [150.0, 185.0]])
    rest = RestPins(xy=xy, seen=np.ones(3), strength=np.full(3, 50.0),
                    reason=np.array(["kept", "kept", "glare"]), pitch_px=PITCH, frames=4,
                    wander_px=np.zeros(3), clipped=np.array([0.0, 1.0, 0.0]),
                    loose=np.array([False, True, False]))
    img = overlay_image(np.full((SIZE, SIZE), 60, np.uint8), rest, Region(SIZE, SIZE))
    s = OVERLAY_SCALE

    palette = np.array([(60, 60, 60), COLOURS["kept"], COLOURS["loose"], COLOURS["glare"]],
                       np.float64)

    def has(colour, x, y):
        """Some pixel near (x, y) is closer to ``colour`` than to any other drawn one
        (the lines are anti-aliased) and within 80 levels of it (summed over the channels)."""
        box = img[int(y * s) - 12:int(y * s) + 13, int(x * s) - 12:int(x * s) + 13]
        d = np.abs(box.reshape(-1, 1, 3).astype(np.float64) - palette[None]).sum(axis=2)
        k = [tuple(p) for p in palette].index(tuple(float(c) for c in colour))
        return bool(((d.argmin(axis=1) == k) & (d[:, k] < 80)).any())

    assert has(COLOURS["loose"], 180, 150) and not has(COLOURS["kept"], 180, 150)
    assert has(COLOURS["kept"], 150, 150) and not has(COLOURS["loose"], 150, 150)
    assert has(COLOURS["glare"], 150, 185)


def test_a_pin_seen_in_most_frames_is_kept_only_on_a_lattice_site():
    """Under MIN_SEEN (4 of 6 frames) a spot is still a pin where its neighbours'
    lattice predicts one; the same spot between the rows is not, nor a faint one (a
    fifth of the pins' strength) on the site."""
    from host.analysis.rest_pins import MIN_SEEN, SITE_SEEN
    sites = _sites()
    i = int(np.argmin(np.hypot(*(sites - (CX + 10, CY - 5)).T)))
    between = sites[i] + [0.5 * PITCH, 0.25 * PITCH]          # off the lattice, inside
    assert SITE_SEEN <= 4 / 6 < MIN_SEEN
    region = Region(SIZE, SIZE, (CX, CY, R))
    for extra, amp, expect in ((None, 120.0, len(sites)), (between, 120.0, len(sites) - 1),
                               (None, 24.0, len(sites) - 1)):
        frames = []
        for k in range(6):
            pins, amps = sites.copy(), np.full(len(sites), 120.0)
            amps[i] = amp
            if k >= 4:
                amps[i] = 0.0                                  # the pin missing in 2 frames
            if extra is not None:
                pins[i] = extra
            frames.append(_render(pins, amps, noise=1.0, seed=k))
        rest = find_rest_pins(frames, region, 6.0, PITCH)
        assert len(rest.pins) == expect
        j = int(np.argmin(np.hypot(*(rest.xy - (sites[i] if extra is None else extra)).T)))
        assert rest.seen[j] == pytest.approx(4 / 6)
        assert rest.reason[j] == ("kept" if expect == len(sites) else "unstable")
