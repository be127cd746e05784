"""``host calibrate``: fit a pipeline profile from no-contact frames.

It finds the dome (or, with no round dome in view, takes the whole frame), then
searches the adaptive-threshold block and offset for the setting under which the
blobs look most like a pin lattice: many blobs, a steady count from frame to
frame, and nearest-neighbour distances that agree with each other. Blob-size
limits follow from the blobs found with that setting. The rest pin layout comes
from :mod:`host.analysis.rest_pins`: the pins found in most of the frames at a
steady position, with glare, duplicates and blobs cut by the region's edge
rejected; the pitch is the layout's median nearest-neighbour distance, and
``n_pins`` is the layout's length.

The frames must be at rest, and :func:`calibrate` refuses (a :class:`NotAtRest`
naming the frames) when they are not: when pins move more than ``STILL_PX``
(median over the pins matched, the pipeline's still test) between two of the
frames, when fewer than ``MIN_PIN_SHARE`` of the blobs the threshold finds per
frame are steady pins, or when more than ``MAX_LOOSE_SHARE`` of the pins kept are
loose by wandering (a pin whose core is clipped by glare is loose but not moving).
It also refuses a layout whose pins are not on a lattice (``MIN_LATTICE``) and,
given the sensor's pin count, one more than ``PIN_TOLERANCE`` off it.
:mod:`host.analysis.still` finds a clip's still stretch.

The result is a ``[vision]`` and a ``[layout]`` section (``device/profile.py``)
that the Pi loads as it is and that ``host train --profile`` maps every frame onto. Without a dome, ``dome_px`` is the circle
around the pins (with ``roi_shrink = 1``), so the pipeline needs no dome.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from device.pi.vision.extract import PinDetector, VisionParams, find_dome, to_gray
from device.pi.vision.matching import match_pins
from device.pi.vision.pipeline import MarkerStream
from device.profile import parse_pipeline_profile
from host.analysis.frames import nearest_neighbour_px
from host.analysis.rest_pins import (MIN_SEEN, WANDER_PITCH, Region, RestPins, agreement, find_rest_pins,
                                     merge_with_flags, nn_px)
from host.analysis.spot_scale import local_pitch_px
from host.data.dataset import atomic_write_text
from device.errors import InputError, TacfootError

BLOCKS = (7, 9, 11, 15, 21, 31)
OFFSETS = (4, 6, 8, 10, 12, 14, 16, 20, 25, 30)
#: the threshold search scores every setting on this many of the frames ...
SEARCH_FRAMES = 4
#: ... and this many of the best on all of them
SEARCH_KEEP = 6
#: rest frames: pins move at most this far (px, median over the pins matched) from
#: one frame to the next (the pipeline's still test, ``MarkerStream.still_px``)
STILL_PX = 0.75
#: at least this share of the blobs found per frame must be steady pins ...
MIN_PIN_SHARE = 0.5
#: ... and at most this share of those pins loose by wandering
MAX_LOOSE_SHARE = 0.5
#: at least this share of the pins at the lattice spacing (:func:`lattice_regularity`)
MIN_LATTICE = 0.85
#: a layout may be this share of the expected pin count off it (at least 3 pins)
PIN_TOLERANCE = 0.03
#: a threshold setting finding more blobs than this in a frame finds noise, not pins
#: (the densest skin seen has about 1200 blobs a frame); it is not scored further
MAX_BLOBS = 2500


class NotAtRest(TacfootError, ValueError):
    """The frames given are not a still, no-contact stretch; the message names them."""


def frame_motion(grays: list[np.ndarray], params: VisionParams, dome, pitch_px: float
                 ) -> np.ndarray:
    """(len(grays) - 1,) px: how far the pins move from each frame to the next, the
    median over the pins matched one to one within half a pitch (inf when fewer than
    3 match), the blobs found under ``params`` in ``dome``."""
    det = PinDetector(params, grays[0].shape, dome)
    pins = [det.detect(g)[0] for g in grays]
    out = np.full(max(0, len(pins) - 1), np.inf)
    for k, (a, b) in enumerate(zip(pins, pins[1:])):
        idx = match_pins(a, b, 0.5 * pitch_px)
        ok = idx >= 0
        if ok.sum() >= 3:
            out[k] = float(np.median(np.hypot(*(b[idx[ok]] - a[ok]).T)))
    return out


def frames_text(start: int, n: int) -> str:
    return f"frame {start}" if n == 1 else f"frames {start}..{start + n - 1}"


def check_still(motion: np.ndarray, start: int) -> None:
    """A :class:`NotAtRest` naming the frames when ``motion`` (:func:`frame_motion`
    of frames ``start`` ..) passes ``STILL_PX`` anywhere."""
    if len(motion) and not np.all(motion <= STILL_PX):
        k = int(np.argmax(np.nan_to_num(motion, nan=np.inf, posinf=1e9)))
        moved = "no pins in common" if not np.isfinite(motion[k]) else f"{motion[k]:.2f} px"
        raise NotAtRest(f"{frames_text(start, len(motion) + 1)} are not at rest: the pins "
                        f"move {moved} (median) from frame {start + k} to {start + k + 1}, "
                        f"more than {STILL_PX} px; calibrate from still frames without "
                        f"contact (--start, --frames)")


def _score(frames, params, dome):
    det = PinDetector(params, frames[0].shape, dome)
    counts, areas, nns = [], [], []
    for g in frames:
        xy, a = det.detect(g)
        if len(xy) > MAX_BLOBS:
            return -1.0, None
        counts.append(len(xy))
        areas.append(a)
        nns.append(nearest_neighbour_px(xy))
    counts = np.array(counts, float)
    if counts.min() < 8:
        return -1.0, None
    nn = np.concatenate(nns)
    med = np.median(nn)
    regular = np.mean(np.abs(nn - med) <= 0.25 * med)
    steady = 1.0 - min(1.0, counts.std() / counts.mean())
    # a lattice of many, evenly spaced, steady blobs
    score = np.median(counts) * regular ** 2 * steady
    return float(score), {"count": float(np.median(counts)), "pitch_px": float(med),
                          "area_px": float(np.median(np.concatenate(areas))),
                          "regular": float(regular), "steady": float(steady)}


def is_binary(gray: np.ndarray) -> bool:
    """Whether a frame is already binarised (nearly every pixel 0 or 255)."""
    return bool(np.count_nonzero((gray == 0) | (gray == 255)) > 0.97 * gray.size)


def fit_threshold(grays: list[np.ndarray], dome) -> tuple[VisionParams, dict, float]:
    """The threshold block and offset under which the blobs look most like a pin
    lattice (inside ``dome``, or the whole frame with None): (params, the fit's
    figures, score)."""
    binary_input = is_binary(grays[0])
    blur = 0.0 if binary_input else 1.0
    shrink = 1.0 if binary_input or dome is None else 0.75
    settings = [VisionParams(block=block, offset=float(offset), blur_sigma_px=blur,
                             min_area_px=3, max_area_px=5000, roi_shrink=shrink)
                for block in BLOCKS for offset in OFFSETS]
    # coarse to fine: every setting on a few frames, the best few on all of them
    few = grays[::max(1, len(grays) // SEARCH_FRAMES)][:SEARCH_FRAMES]
    if len(few) < len(grays):
        rough = [_score(few, p, dome)[0] for p in settings]
        settings = [settings[i] for i in np.argsort(rough)[::-1][:SEARCH_KEEP]]
    best = (-1.0, None, None)
    for p in settings:
        s, info = _score(grays, p, dome)
        if s > best[0]:
            best = (s, p, info)
    score, p, info = best
    if p is None:
        where = "" if dome is not None else "no dome in view and "
        raise InputError(f"{where}no threshold setting found pins: is this a TacTip clip?")
    return p, info, score


def stretched(gray: np.ndarray) -> np.ndarray:
    """``gray`` with its 0.5th..99.5th percentile stretched to 0..255: a dark
    exposure's dome stands out as a camera's does."""
    lo, hi = np.percentile(gray, (0.5, 99.5))
    if hi - lo < 1:
        return gray
    return np.clip((gray.astype(np.float32) - lo) * (255.0 / (hi - lo)), 0, 255).astype(np.uint8)


def find_region(grays: list[np.ndarray]):
    """The dome (cx, cy, r) px found in most of the first frames, or None when no
    round dome is in view (the pins are then searched on the whole frame)."""
    domes = [d for d in (find_dome(g) or find_dome(stretched(g)) for g in grays[:5])
             if d is not None]
    if len(domes) * 2 <= min(5, len(grays)):
        return None
    return tuple(float(v) for v in np.median(np.array(domes), axis=0))


def lattice_regularity(pins: np.ndarray) -> float:
    """The share of ``pins`` whose nearest-neighbour distance is within 25 % of their
    local pitch (:func:`local_pitch_px`): near 1 for a lattice, lower with texture
    or glare spots between the pins."""
    pins = np.asarray(pins, np.float64).reshape(-1, 2)
    if len(pins) < 3:
        return 0.0
    nn, lp = nn_px(pins), local_pitch_px(pins)
    return float(np.mean(np.abs(nn - lp) <= 0.25 * lp))


def rest_pins(grays: list[np.ndarray], dome, params: VisionParams, info: dict
              ) -> tuple[RestPins, Region, str]:
    """The rest pins (two passes: the second with the pitch of the first's pins) and
    the spot scale used: ``"one"`` (one pin size from the threshold fit) or, with no
    dome in view, ``"per-pin"`` (:func:`multiscale_spots`, each pin at its own size)
    when its pins form the more regular lattice (:func:`lattice_regularity`): a
    flat skin seen through a wide-angle lens has pins 3x larger in the middle than
    at the rim, and one size finds the texture between the big pins."""
    h, w = grays[0].shape
    region = Region(w, h, None if dome is None else
                    (dome[0], dome[1], dome[2] * params.roi_shrink))
    pin_d = 2.0 * math.sqrt(max(info["area_px"], 1.0) / math.pi)
    pitch = info["pitch_px"]
    rest = find_rest_pins(grays, region, pin_d, pitch)
    for _ in range(2):
        nn = nn_px(rest.pins)
        if len(nn) < 3 or not np.isfinite(np.median(nn)):
            break
        pitch = float(np.median(nn))
        rest = find_rest_pins(grays, region, pin_d, pitch)
    if dome is not None:
        return rest, region, "one"
    multi = find_rest_pins(grays, region, pin_d, float(np.percentile(nn_px(rest.pins), 10))
                           if len(rest.pins) >= 3 else pitch, multiscale=True)
    if lattice_regularity(multi.pins) > lattice_regularity(rest.pins):
        return multi, region, "per-pin"
    return rest, region, "one"


def calibrate(frames: list[np.ndarray], name: str = "calibrated", start: int = 0,
              expect_pins: int | None = None) -> dict:
    """Fit ``[vision]`` parameters and the rest ``[layout]`` from no-contact frames
    (gray or BGR); ``start`` is the first frame's index in its clip (recorded only);
    ``expect_pins`` the sensor's pin count, when known.
    The result's ``rest`` (:class:`RestPins`) and ``region`` (:class:`Region`) say
    which blobs were kept and why the others were not. Frames that are not at rest
    (see the module's rules) are a :class:`NotAtRest` naming them."""
    grays = [to_gray(f) for f in frames]
    if not grays:
        raise InputError("calibrate needs at least one frame")
    dome = find_region(grays)
    p, info, score = fit_threshold(grays, dome)
    motion = frame_motion(grays, p, dome, info["pitch_px"])
    check_still(motion, start)
    rest, region, scale = rest_pins(grays, dome, p, info)
    pins = rest.pins
    which = frames_text(start, len(grays))
    if len(pins) < 3:
        raise NotAtRest(f"{which}: only {len(pins)} rest pins found: is this a TacTip clip "
                        f"at rest?")
    if len(pins) < MIN_PIN_SHARE * info["count"]:
        raise NotAtRest(f"{which}: only {len(pins)} steady pins of the {info['count']:.0f} "
                        f"blobs found per frame (under {MIN_PIN_SHARE:.0%}): the frames are "
                        f"not at rest, or the skin is not in view; calibrate from still "
                        f"frames without contact (--start, --frames)")
    kept = rest.reason == "kept"
    wandering = int(np.count_nonzero(~(rest.wander_px[kept] <= WANDER_PITCH * rest.pitch_px))
                    if rest.wander_px is not None else 0)
    if wandering > MAX_LOOSE_SHARE * len(pins):
        raise NotAtRest(f"{which}: {wandering} of the {len(pins)} pins found are loose, their "
                        f"centres wandering over the frames (over {MAX_LOOSE_SHARE:.0%}): the "
                        f"frames are not at rest; calibrate from still frames without contact "
                        f"(--start, --frames)")
    n_loose = int(rest.pins_loose.sum())
    if n_loose > MAX_LOOSE_SHARE * len(pins) and not is_binary(grays[0]):
        raise NotAtRest(f"{which}: {n_loose} of the {len(pins)} pins found are loose, most "
                        f"of them with a core clipped at full scale (over {MAX_LOOSE_SHARE:.0%}):"
                        f" the exposure is too bright for a layout; lower it and calibrate "
                        f"again")
    check_layout(pins, which, expect_pins)
    pitch = float(np.median(nn_px(pins)))
    area = info["area_px"]
    if dome is None:    # no dome in view: the region is the circle around the pins
        lo, hi = pins.min(axis=0), pins.max(axis=0)
        c = (lo + hi) / 2.0
        dome = (float(c[0]), float(c[1]), float(np.hypot(*(hi - lo)) / 2.0 + pitch))
    vision = {"block": p.block, "offset": p.offset, "blur_sigma_px": p.blur_sigma_px,
              "min_area_px": int(max(3, round(0.3 * area))),
              "max_area_px": int(max(round(3.0 * area), round(0.3 * area) + 1)),
              "roi_shrink": p.roi_shrink, "pitch_px": round(pitch, 2),
              "n_pins": int(len(pins)), "dome_px": [round(v, 1) for v in dome]}
    vision["contrast_ref"] = rest_contrast(grays, p, dome)
    order = layout_order(pins, dome, pitch)
    layout = order_layout(pins, dome, pitch)
    loose = np.flatnonzero(rest.pins_loose[order])
    vision.update(rest_contact(grays, vision))
    return {"name": name, "vision": vision, "layout": layout, "frames": len(grays),
            "loose": [int(i) for i in loose],
            "start": int(start), "region": region, "rest": rest,
            "motion_px": round(float(motion.max()), 3) if len(motion) else 0.0,
            "blobs": rest.counts(), "dome_in_view": region.disc is not None,
            "spot_scale": scale, "lattice_regularity": round(lattice_regularity(pins), 3),
            "fit": {"score": score, "regular_fraction": info["regular"],
                    "count_steadiness": info["steady"], "median_pin_area_px": area}}


def check_layout(pins: np.ndarray, which: str, expect_pins: int | None = None) -> None:
    """A :class:`NotAtRest` naming the frames (``which``) when fewer than
    ``MIN_LATTICE`` of ``pins`` are at the lattice spacing, or when ``expect_pins``
    is given and the count is more than ``PIN_TOLERANCE`` of it (at least 3) off."""
    reg = lattice_regularity(pins)
    if reg < MIN_LATTICE:
        raise NotAtRest(f"{which}: only {reg:.0%} of the {len(pins)} pins found are at the "
                        f"lattice spacing (under {MIN_LATTICE:.0%}): glare or texture, not a "
                        f"pin lattice at rest; calibrate from still frames without contact "
                        f"(--start, --frames)")
    if expect_pins is not None:
        tol = max(3, round(PIN_TOLERANCE * expect_pins))
        if abs(len(pins) - expect_pins) > tol:
            raise NotAtRest(f"{which}: {len(pins)} pins found, the sensor has {expect_pins} "
                            f"(--pins; more than {tol} off): the frames are not at rest, or "
                            f"the exposure hides or adds pins (see --overlay)")


def rest_contrast(grays, params: VisionParams, dome) -> float:
    """``contrast_ref``: the median over the rest frames of the dome's local contrast
    (:meth:`PinDetector.local_contrast`, gray levels) under ``params`` in ``dome``, as
    the pipeline measures it when it sets its reference and scales its offset."""
    det = PinDetector(params, grays[0].shape, dome)
    got = []
    for g in grays:
        det.threshold(g)
        got.append(det.local_contrast())
    return round(float(np.median(got)), 2)


def layout_order(pins: np.ndarray, dome, pitch_px: float) -> np.ndarray:
    """The rows of ``pins`` sorted by angle around the region's centre within rings
    of one pitch, so the order is stable."""
    pins = np.asarray(pins, np.float64).reshape(-1, 2)
    d = pins - np.asarray(dome[:2], np.float64)
    ring = np.round(np.hypot(d[:, 0], d[:, 1]) / max(pitch_px, 1e-9))
    return np.lexsort((np.arctan2(d[:, 1], d[:, 0]), ring))


def order_layout(pins: np.ndarray, dome, pitch_px: float) -> list[list[float]]:
    """The layout [[x, y], ...] px in :func:`layout_order`."""
    pins = np.asarray(pins, np.float64).reshape(-1, 2)
    return [[round(float(x), 2), round(float(y), 2)]
            for x, y in pins[layout_order(pins, dome, pitch_px)]]


def loose_flags(res: dict) -> np.ndarray:
    """(len(layout),) bool: the layout's loose pins (``res["loose"]`` indices)."""
    flags = np.zeros(len(res["layout"]), bool)
    flags[np.asarray(res.get("loose", []), np.int64)] = True
    return flags


#: in a merge, a clip whose layout matches fewer than this share of the smaller
#: layout's pins (aligned by a shift) disagrees with that clip
MATCH_SHARE = 0.85


def clip_outliers(results: list[dict]) -> dict[int, str]:
    """{index: why} of the calibrations (of clips of one sensor, to be merged) that
    disagree with the others: a pin count more than ``PIN_TOLERANCE`` (at least 3)
    off the clips' median, or a layout that matches fewer than ``MATCH_SHARE`` of
    the pins of most of the others. With two clips that disagree, both are named."""
    counts = np.array([len(r["layout"]) for r in results], float)
    med = float(np.median(counts))
    tol = max(3, round(PIN_TOLERANCE * med))
    pitch = results[0]["vision"]["pitch_px"]
    lays = [np.asarray(r["layout"], np.float64).reshape(-1, 2) for r in results]
    out = {}
    for i, n in enumerate(counts):
        if abs(n - med) > tol:
            out[i] = f"{int(n)} pins, the clips' median {med:g} (more than {tol} off)"
            continue
        bad = 0
        for j in range(len(lays)):
            if j != i:
                ag = agreement(lays[i], lays[j], pitch)
                bad += ag["matched"] < MATCH_SHARE * min(ag["pins"])
        if 2 * bad > len(lays) - 1 or (len(lays) == 2 and bad):
            out[i] = (f"a layout that matches under {MATCH_SHARE:.0%} of the pins of "
                      f"{bad} of the other {len(lays) - 1}")
    return out


def merge_results(results: list[dict]) -> dict:
    """One profile from the calibrations of several clips of one sensor: the first
    clip's ``[vision]`` and region, and the rest layout of the pins more than half of
    the clips found (each clip's layout shifted onto the first's; a pin loose in half
    of them or more stays loose). ``agreement`` compares every pair of clips
    (:func:`agreement`, with ``steady``: over the pins loose in neither)."""
    first = results[0]
    pitch = first["vision"]["pitch_px"]
    lays = [np.asarray(r["layout"], np.float64).reshape(-1, 2) for r in results]
    flags = [loose_flags(r) for r in results]
    merged, merged_loose = merge_with_flags(lays, pitch, flags)
    vision = dict(first["vision"], n_pins=int(len(merged)))
    pairs = [dict(agreement(lays[i], lays[j], pitch, flags[i], flags[j]), clips=[i, j])
             for i in range(len(lays)) for j in range(i + 1, len(lays))]
    order = layout_order(merged, vision["dome_px"], pitch)
    return dict(first, vision=vision, layout=order_layout(merged, vision["dome_px"], pitch),
                loose=[int(i) for i in np.flatnonzero(merged_loose[order])],
                frames=sum(r["frames"] for r in results), clips_merged=len(results),
                agreement=pairs)


#: contact thresholds sit this far above the largest value seen on the rest frames
CONTACT_MARGIN = 1.5


def rest_contact(grays, vision: dict) -> dict:
    """``grid_contact`` and ``contact_px`` for the fitted ``vision``: the defaults,
    raised to ``CONTACT_MARGIN`` times the largest contact-grid cell change and
    mean pin displacement that the rest frames show, so that none of them reads as
    contact (a low threshold offset gives a busier binary image than the default). A
    ValueError when the displacement threshold would pass the pin pitch (the frames
    are not at rest, and the profile could not be loaded)."""
    prof = parse_pipeline_profile({"vision": dict(vision)}, source="<calibrate>")
    stream = MarkerStream(prof)
    grid_max, mag_max = 0.0, 0.0
    for g in grays:
        ff = stream.process(g)
        if stream.reference is not None:
            grid_max = max(grid_max, float(ff.grid.max()))
            mag_max = max(mag_max, float(ff.magnitude_sum) / max(1, len(ff.vectors)))
    contact_px = round(max(prof.contact_px, CONTACT_MARGIN * mag_max), 3)
    if contact_px > prof.pitch_px:
        raise InputError(f"the contact threshold these frames need ({contact_px} px of mean "
                         f"pin travel) is beyond the pin pitch ({prof.pitch_px} px): the "
                         f"leading frames are not at rest; calibrate from a clip that starts "
                         f"without contact")
    return {"grid_contact": round(min(1.0, max(prof.grid_contact,
                                               CONTACT_MARGIN * grid_max)), 4),
            "contact_px": contact_px}


def profile_toml(res: dict) -> str:
    v = res["vision"]
    lines = ["# Pipeline profile fitted by `host calibrate` from a no-contact clip.",
             f"# {res['frames']} frames; {res['fit']['regular_fraction']:.0%} of pins at the "
             f"lattice spacing; count steadiness {res['fit']['count_steadiness']:.3f}.",
             "[profile]", f'name = "{res["name"]}"', "", "[vision]"]
    for k in ("block", "offset", "blur_sigma_px", "min_area_px", "max_area_px", "roi_shrink",
              "pitch_px", "n_pins", "grid_contact", "contact_px"):
        lines.append(f"{k} = {v[k]}")
    if v.get("contrast_ref"):
        lines.append(f"contrast_ref = {v['contrast_ref']}")
    if not res.get("dome_in_view", True):
        lines.append("# no dome in view: the region is the circle around the pins")
    lines.append(f"dome_px = [{', '.join(str(x) for x in v['dome_px'])}]")
    lay = res.get("layout") or []
    if lay:
        merged = res.get("clips_merged", 1)
        lines += ["", f"# the rest pin layout: {len(lay)} pins, each found in at least "
                      f"{MIN_SEEN:.0%} of the rest frames at a steady position"
                      + (f" in more than half of {merged} clips" if merged > 1 else "")
                      + "; every model reads them in this order",
                  ]
        loose = res.get("loose") or []
        if loose:
            lines += [f"# {len(loose)} of them loose (a glare-clipped core or a centre that "
                      f"wanders over the rest frames; their rest position is less certain), "
                      f"rows: {', '.join(str(i) for i in loose)}"]
        lines += ["[layout]", 'kind = "points"', "pins_px = ["]
        lines += [f"  [{x}, {y}]," for x, y in lay]
        lines.append("]")
    return "\n".join(lines) + "\n"


def write_profile(res: dict, out: Path | str) -> Path:
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, profile_toml(res))
    return out
