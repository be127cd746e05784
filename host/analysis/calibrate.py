"""``host calibrate``: fit a pipeline profile from a no-contact clip.

It finds the dome, then searches the adaptive-threshold block and offset for
the setting under which the blobs look most like a pin lattice: many blobs, a
steady count from frame to frame, and nearest-neighbour distances that agree
with each other. Blob-size limits and the pin pitch follow from the blobs
found with that setting, and the rest pin layout (the pins found in most of the
frames, at their median positions) from the same frames. The result is a
``[vision]`` and a ``[layout]`` section (``device/profile.py``) that the Pi loads as
it is and that ``host train --profile`` maps every frame onto.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from device.pi.vision.extract import PinDetector, VisionParams, find_dome, to_gray
from device.pi.vision.matching import match_pins
from device.pi.vision.pipeline import MarkerStream
from device.profile import parse_pipeline_profile
from host.analysis.frames import nearest_neighbour_px
from host.data.dataset import atomic_write_text

BLOCKS = (7, 9, 11, 15, 21, 31)
OFFSETS = (4, 6, 8, 10, 12, 14, 16, 20, 25, 30)


def _score(frames, params, dome):
    det = PinDetector(params, frames[0].shape, dome)
    counts, areas, nns = [], [], []
    for g in frames:
        xy, a = det.detect(g)
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


def calibrate(frames: list[np.ndarray], name: str = "calibrated") -> dict:
    """Fit ``[vision]`` parameters from no-contact frames (gray or BGR)."""
    grays = [to_gray(f) for f in frames]
    if not grays:
        raise ValueError("calibrate needs at least one frame")
    domes = [d for d in (find_dome(g) for g in grays[:5]) if d is not None]
    if not domes:
        raise ValueError("no dome found in the first frames: is the sensor in view?")
    dome = tuple(float(v) for v in np.median(np.array(domes), axis=0))
    g0 = grays[0]
    binary_input = np.count_nonzero((g0 == 0) | (g0 == 255)) > 0.97 * g0.size
    blur = 0.0 if binary_input else 1.0
    shrink = 1.0 if binary_input else 0.75
    best = (-1.0, None, None)
    for block in BLOCKS:
        for offset in OFFSETS:
            p = VisionParams(block=block, offset=float(offset), blur_sigma_px=blur,
                             min_area_px=3, max_area_px=5000, roi_shrink=shrink)
            s, info = _score(grays, p, dome)
            if s > best[0]:
                best = (s, p, info)
    score, p, info = best
    if p is None:
        raise ValueError("no threshold setting found pins: is this a TacTip clip?")
    area = info["area_px"]
    vision = {"block": p.block, "offset": p.offset, "blur_sigma_px": blur,
              "min_area_px": int(max(3, round(0.3 * area))),
              "max_area_px": int(max(round(3.0 * area), round(0.3 * area) + 1)),
              "roi_shrink": shrink, "pitch_px": round(info["pitch_px"], 2),
              "n_pins": int(round(info["count"])),
              "dome_px": [round(v, 1) for v in dome]}
    # the count with the final area limits
    final = VisionParams(block=p.block, offset=p.offset, blur_sigma_px=blur,
                         min_area_px=vision["min_area_px"], max_area_px=vision["max_area_px"],
                         roi_shrink=shrink)
    _, fin = _score(grays, final, dome)
    if fin is not None:
        vision["n_pins"] = int(round(fin["count"]))
    layout = rest_layout(grays, final, dome, vision["pitch_px"])
    vision.update(rest_contact(grays, vision))
    return {"name": name, "vision": vision, "layout": layout, "frames": len(grays),
            "fit": {"score": score, "regular_fraction": info["regular"],
                    "count_steadiness": info["steady"], "median_pin_area_px": area}}


#: a rest pin must be found in at least this share of the calibration frames
MIN_SEEN = 0.5


def rest_layout(grays, params: VisionParams, dome, pitch_px: float) -> list[list[float]]:
    """The rest pin layout [[x, y], ...] px: the pins of the frame with the most
    detections, each matched in every frame within 0.4 pitch, kept when seen in at
    least ``MIN_SEEN`` of the frames, at its median position; sorted by angle
    around the dome centre within rings of one pitch, so the order is stable."""
    det = PinDetector(params, grays[0].shape, dome)
    found = [det.detect(g)[0].astype(np.float64) for g in grays]
    ref = max(found, key=len)
    pos = np.full((len(found), len(ref), 2), np.nan)
    for k, xy in enumerate(found):
        idx = match_pins(ref, xy, 0.4 * pitch_px)
        ok = idx >= 0
        pos[k, ok] = xy[idx[ok]]
    seen = np.isfinite(pos[..., 0]).mean(axis=0) >= MIN_SEEN
    pins = np.nanmedian(pos[:, seen], axis=0) if seen.any() else np.zeros((0, 2))
    d = pins - np.asarray(dome[:2], np.float64)
    ring = np.round(np.hypot(d[:, 0], d[:, 1]) / max(pitch_px, 1e-9))
    order = np.lexsort((np.arctan2(d[:, 1], d[:, 0]), ring))
    return [[round(float(x), 2), round(float(y), 2)] for x, y in pins[order]]


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
        raise ValueError(f"the contact threshold these frames need ({contact_px} px of mean "
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
    lines.append(f"dome_px = [{', '.join(str(x) for x in v['dome_px'])}]")
    lay = res.get("layout") or []
    if lay:
        lines += ["", f"# the rest pin layout: {len(lay)} pins found in at least "
                      f"{MIN_SEEN:.0%} of the frames; every model reads them in this order",
                  "[layout]", 'kind = "points"', "pins_px = ["]
        lines += [f"  [{x}, {y}]," for x, y in lay]
        lines.append("]")
    return "\n".join(lines) + "\n"


def write_profile(res: dict, out: Path | str) -> Path:
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, profile_toml(res))
    return out
