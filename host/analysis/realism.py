"""Measure TacTip frames the same way whether they are real or simulated.

Every function here takes a sequence of frames (2-D gray or BGR uint8 arrays)
and the :class:`device.pi.vision.extract.VisionParams` of the front end, runs the very
same Pi code (``device.pi.vision.extract``) over them and returns a plain ``dict`` of
finite numbers (JSON-ready). Comparing the dict of a real clip with the dict
of a simulated clip tells how far the simulator is from reality.

Hard cases (no dome found, no pins) give finite numbers (0.0) and a message in
``faults``; nothing returns NaN.

Units are in the key names: ``_px`` pixels, ``_px2`` square pixels, ``_gray``
gray levels (0..255), ``_deg`` degrees.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Iterable

import cv2
import numpy as np

from device.pi.vision.extract import (ROBOSKIN_PARAMS, PinDetector, VisionParams, dome_mask,
                                      to_gray)
from host.extras import need
from device.sim import Simulator, load_scene
from host.analysis.drag import measure_drag_displacement
from host.analysis.frames import finite, frame_list, locate_dome, nearest_neighbour_px, stat
from host.analysis.glare import measure_glare

__all__ = [
    "pin_appearance",
    "measure_static",
    "REALISM_FIGURES",
    "REST_THRESHOLD_GRAY",
    "rest_frame_count",
    "fit_glare",
    "recording_realism",
    "spec_realism",
    "realism_table",
    "side_by_side_png",
]


def pin_appearance(
    gray: np.ndarray, xy: np.ndarray, inner_px: float = 5.0, outer_px: float = 8.0
) -> tuple[np.ndarray, np.ndarray]:
    """Peak gray (max of 3x3 at the centroid) and local background (median of the
    annulus ``inner_px``..``outer_px``) for each pin. Pins too near the border are skipped.
    """
    g = to_gray(gray)
    h, w = g.shape
    ro = int(math.ceil(outer_px))
    yy, xx = np.mgrid[-ro : ro + 1, -ro : ro + 1]
    rr = np.hypot(xx, yy)
    ring = (rr >= inner_px) & (rr <= outer_px)
    peaks, bgs = [], []
    for x, y in np.asarray(xy, dtype=np.float64).reshape(-1, 2):
        xi, yi = int(round(x)), int(round(y))
        if xi - ro < 0 or yi - ro < 0 or xi + ro >= w or yi + ro >= h:
            continue
        patch = g[yi - ro : yi + ro + 1, xi - ro : xi + ro + 1]
        peaks.append(float(patch[ro - 1 : ro + 2, ro - 1 : ro + 2].max()))
        bgs.append(float(np.median(patch[ring])))
    return np.asarray(peaks), np.asarray(bgs)


def _pin_profile_sigma(gray: np.ndarray, xy: np.ndarray, half: int = 6) -> float:
    """Gaussian sigma (px) of the mean background-subtracted pin patch, 0 if unknown."""
    g = to_gray(gray).astype(np.float32)
    h, w = g.shape
    acc = np.zeros((2 * half + 1, 2 * half + 1), np.float64)
    n = 0
    for x, y in np.asarray(xy, dtype=np.float64).reshape(-1, 2):
        # resample the patch centred on the sub-pixel centroid
        if x - half - 1 < 0 or y - half - 1 < 0 or x + half + 1 >= w or y + half + 1 >= h:
            continue
        patch = cv2.getRectSubPix(g, (2 * half + 1, 2 * half + 1), (float(x), float(y)))
        acc += patch
        n += 1
    if n == 0:
        return 0.0
    acc /= n
    yy, xx = np.mgrid[-half : half + 1, -half : half + 1]
    r2 = (xx**2 + yy**2).astype(np.float64)
    edge = acc[r2 >= (half - 1) ** 2]
    amp = acc - float(np.median(edge))
    peak = amp[half, half]
    if peak <= 0:
        return 0.0
    sel = (amp > 0.15 * peak) & (r2 <= (half - 1) ** 2)
    if np.count_nonzero(sel) < 4:
        return 0.0
    # log A - r^2 / (2 s^2): linear in r^2
    slope, _ = np.polyfit(r2[sel], np.log(amp[sel]), 1)
    if slope >= 0:
        return 0.0
    return finite(math.sqrt(-1.0 / (2.0 * slope)))


# --------------------------------------------------------------------------
# Static appearance
# --------------------------------------------------------------------------


def measure_static(
    frames: Iterable[np.ndarray],
    params: VisionParams,
    dome: tuple[float, float, float] | None = None,
) -> dict:
    """Pin count, size, spacing, brightness and glare of (rest) frames.

    Returns a dict with:
      dome_cx_px, dome_cy_px, dome_r_px: the region used (found on the frames if not given)
      n_frames
      pin_count_median, pin_count_iqr, pin_count_min, pin_count_max: pins per frame
      pin_area_px2_median, pin_diameter_px_median: diameter = 2 sqrt(area / pi)
      pin_spacing_px_median: median over frames of the median nearest-neighbour distance
      pin_peak_gray_median, pin_background_gray_median, pin_contrast_gray_median:
          max of 3x3 at each centroid, median of the annulus 0.8..1.25 pin diameters
      pin_sigma_px: Gaussian sigma of the mean pin profile (meaningful for soft,
          camera-blurred pins; a binarised disc is not Gaussian)
      glare_area_px2_median: per-frame total area of blobs above max_area_px (removed
          as glare) inside the ROI, median over frames
      glare_count_median: number of such blobs per frame, median
      faults: list of strings (empty when all went well)
    """
    fl = frame_list(frames)
    faults: list[str] = []
    if dome is None:
        dome = locate_dome(fl)
        if dome is None:
            faults.append("no dome found; whole frame used")
    det = PinDetector(params, fl[0].shape[:2], dome)
    counts, areas_all, spacings = [], [], []
    peaks, bgs, sigmas = [], [], []
    glare_area, glare_count = [], []
    for f in fl:
        gray = to_gray(f)
        xy, areas = det.detect_all(gray)
        pin = (areas >= params.min_area_px) & (areas <= params.max_area_px)
        big = areas > params.max_area_px
        pxy = xy[pin]
        counts.append(int(pin.sum()))
        areas_all.extend(areas[pin].tolist())
        nn = nearest_neighbour_px(pxy)
        if nn.size:
            spacings.append(float(np.median(nn)))
        glare_area.append(float(areas[big].sum()))
        glare_count.append(int(big.sum()))
        if len(pxy):
            # background annulus and profile window scale with the pin size
            d_px = 2.0 * math.sqrt(float(np.median(areas[pin])) / math.pi)
            pk, bg = pin_appearance(gray, pxy, inner_px=0.8 * d_px, outer_px=1.25 * d_px)
            peaks.extend(pk.tolist())
            bgs.extend(bg.tolist())
            sigmas.append(_pin_profile_sigma(gray, pxy, half=max(4, int(round(d_px)))))
    if sum(counts) == 0:
        faults.append("no pins found in any frame")
    a = np.asarray(areas_all, np.float64)
    peaks_a, bgs_a = np.asarray(peaks), np.asarray(bgs)
    cx, cy, r = dome if dome is not None else (fl[0].shape[1] / 2.0, fl[0].shape[0] / 2.0, 0.0)
    return {
        "dome_cx_px": finite(cx),
        "dome_cy_px": finite(cy),
        "dome_r_px": finite(r),
        "n_frames": len(fl),
        "pin_count_median": stat(counts, np.median),
        "pin_count_iqr": stat(counts, lambda v: np.percentile(v, 75) - np.percentile(v, 25)),
        "pin_count_min": stat(counts, np.min),
        "pin_count_max": stat(counts, np.max),
        "pin_area_px2_median": stat(a, np.median),
        "pin_diameter_px_median": stat(2.0 * np.sqrt(a / math.pi), np.median),
        "pin_spacing_px_median": stat(spacings, np.median),
        "pin_peak_gray_median": stat(peaks_a, np.median),
        "pin_background_gray_median": stat(bgs_a, np.median),
        "pin_contrast_gray_median": stat(peaks_a - bgs_a, np.median),
        "pin_sigma_px": stat([s for s in sigmas if s > 0], np.median),
        "glare_area_px2_median": stat(glare_area, np.median),
        "glare_count_median": stat(glare_count, np.median),
        "faults": faults,
    }


# --------------------------------------------------------------------------
# The realism check: the simulator against the user's recordings, measured alike
# --------------------------------------------------------------------------

#: a leading frame is at rest (no contact) while its mean absolute difference from
#: frame 0 inside the dome stays below this (MPEG noise alone gives ~3 grey levels)
REST_THRESHOLD_GRAY = 4.5
#: simulated rest frames (the ``no-touch`` scene) measured against the real rest
SIM_REST_FRAMES = 16
#: the simulator's glare blobs: sigma fitted within these bounds [px]; a real glare
#: broader than the upper bound is a haze whose area is reported, not compared
GLARE_SIGMA_BOUNDS_PX = (6.0, 20.0)

#: (label, where in the result, key) of each figure compared; all within 20%
REALISM_FIGURES = [
    (label, part, key)
    for part, figures in (
        ("static", (("visible pin count", "pin_count_median"),
                    ("pin diameter [px]", "pin_diameter_px_median"),
                    ("pin spacing [px]", "pin_spacing_px_median"))),
        ("glare", (("glare blob area [px^2]", "glare_half_amplitude_area_px2_median"),
                   ("glare blob amplitude [grey]", "glare_amplitude_gray_median"))),
        ("drag", (("drag displacement p90 [px]", "displacement_px_p90"),)),
    )
    for label, key in figures
]


def rest_frame_count(frames, dome=None, threshold_gray: float = REST_THRESHOLD_GRAY) -> int:
    """How many leading frames are at rest: the run from frame 0 whose mean absolute
    difference from frame 0, inside the dome (the whole frame without one), stays below
    ``threshold_gray``. At least 1 for a non-empty clip, 0 for an empty one."""
    fl = list(frames)
    if not fl:
        return 0
    if dome is None:
        dome = locate_dome(fl[:5])
    g0 = to_gray(fl[0]).astype(np.float32)
    mask = (dome_mask(g0.shape, dome) > 0) if dome is not None else np.ones(g0.shape, bool)
    if not mask.any():
        mask[:] = True
    n = 1
    for f in fl[1:]:
        if float(np.mean(np.abs(to_gray(f).astype(np.float32) - g0)[mask])) >= threshold_gray:
            break
        n += 1
    return n


def _sim_frames(scene_name: str, effects: tuple, seed: int,
                limit: int | None = None) -> list[np.ndarray]:
    sim = Simulator(load_scene(scene_name).with_effects(*effects), seed=seed)
    n = sim.n_frames if limit is None else min(limit, sim.n_frames)
    return [sim.render(i) for i in range(n)]


def fit_glare(real_glare: dict, seed: int = 0, rounds: int = 3, frames: int = 4) -> dict:
    """The simulator's ``glare`` effect fitted to a real glare measurement (from
    :func:`host.analysis.glare.measure_glare` on the real rest frames): ``peak``
    scaled until the simulated blob amplitude matches, ``sigma_px`` until the blob
    area at half amplitude matches, within :data:`GLARE_SIGMA_BOUNDS_PX`. Starts from
    the simulated profile's own glare. Returns {"effect": dict or None (no glare
    seen), "sigma_at_bound": bool}."""
    amp = float(real_glare.get("glare_amplitude_gray_median", 0.0))
    area = float(real_glare.get("glare_half_amplitude_area_px2_median", 0.0))
    if amp <= 0 or area <= 0:
        return {"effect": None, "sigma_at_bound": False}
    g = load_scene("no-touch").profile.glare
    peak, sigma = float(g.peak or 70.0), float(g.sigma_px or 15.0)
    lo, hi = GLARE_SIGMA_BOUNDS_PX
    at_bound = False
    for _ in range(rounds):
        eff = {"name": "glare", "peak": round(peak, 1), "sigma_px": round(sigma, 1)}
        rest = _sim_frames("no-touch", (eff, "camera_noise"), seed, frames)
        m = measure_glare(rest, locate_dome(rest))
        s_amp = float(m.get("glare_amplitude_gray_median", 0.0))
        s_area = float(m.get("glare_half_amplitude_area_px2_median", 0.0))
        if s_amp > 0:
            peak = float(np.clip(peak * amp / s_amp, 1.0, 255.0))
        if s_area > 0:
            want = sigma * math.sqrt(area / s_area)
            at_bound = want > hi
            sigma = float(np.clip(want, lo, hi))
    return {"effect": {"name": "glare", "peak": round(peak, 1), "sigma_px": round(sigma, 1)},
            "sigma_at_bound": at_bound}


def _measure_set(rest: list, drag: list | None, params: VisionParams) -> dict:
    dome = locate_dome(rest)
    return {"static": measure_static(rest, params, dome),
            "glare": measure_glare(rest, dome),
            "drag": measure_drag_displacement(drag, params, dome) if drag else {}}


def drag_scene(label: str) -> str | None:
    """The simulator's ``{label}-drag`` scene, or None when it has none."""
    name = f"{label}-drag"
    try:
        load_scene(name)
    except Exception:       # an unknown scene name: the simulator's own error
        return None
    return name


def recording_realism(name: str, label: str, frames: list, params: VisionParams,
                      seed: int = 0) -> dict:
    """One recording against the simulator, measured alike: rest figures from its
    leading rest frames (:func:`rest_frame_count`) against :data:`SIM_REST_FRAMES`
    frames of ``no-touch`` with the glare fitted to them (:func:`fit_glare`) and
    camera noise; drag displacement over the whole recording against the
    ``{label}-drag`` scene (left out, with a note, when the simulator has none)."""
    notes: list[str] = []
    n_rest = rest_frame_count(frames)
    if n_rest < 2:
        notes.append(f"only {n_rest} rest frame(s) before contact (mean difference from "
                     f"frame 0 >= {REST_THRESHOLD_GRAY} grey levels); rest figures are rough")
    rest = frames[:n_rest]
    scene = drag_scene(label)
    if scene is None:
        notes.append(f"no simulated scene {label}-drag (device/sim/scenes/{label}-drag.toml): "
                     f"drag displacement not compared")
    real = _measure_set(rest, frames if scene else None, params)
    glare = fit_glare(real["glare"], seed)
    effects = tuple(e for e in (glare["effect"], "camera_noise") if e)
    sim_rest = _sim_frames("no-touch", effects, seed, SIM_REST_FRAMES)
    sim = _measure_set(sim_rest, _sim_frames(scene, effects, seed) if scene else None, params)
    rows = []
    for fig, part, key in REALISM_FIGURES:
        if key not in real[part]:
            continue
        r, s = float(real[part][key]), float(sim[part].get(key, 0.0))
        ratio = s / r if r else (1.0 if s == 0 else float("inf"))
        row = {"figure": fig, "real": r, "sim": s, "ratio": finite(ratio, 0.0),
               "within_20pct": bool(abs(ratio - 1.0) <= 0.2)}
        if key == "glare_half_amplitude_area_px2_median" and glare["sigma_at_bound"]:
            row["not_compared"] = (f"the real glare is a broad haze (half-amplitude area "
                                   f"{r:.0f} px^2); the simulator's separate Gaussian blobs "
                                   f"reach sigma {GLARE_SIGMA_BOUNDS_PX[1]:.0f} px at most")
        rows.append(row)
    return {"recording": name, "label": label, "rest_frames": n_rest, "frames": len(frames),
            "sim_scene": scene, "sim_effects": list(effects), "rows": rows, "notes": notes}


def spec_realism(recordings, params: VisionParams | None = None, seed: int = 0,
                 progress: bool = False) -> dict:
    """:func:`recording_realism` of each of ``recordings``: (name, label, frames or a
    function returning them), e.g. the rows of a user's data spec. ``all_within_20pct``
    is over every compared figure."""
    tqdm = need("tqdm").tqdm

    params = params or ROBOSKIN_PARAMS
    out = {"pairs": []}
    for name, label, frames in tqdm(list(recordings), desc="realism", unit="recording",
                                    disable=not progress or None, leave=False):
        fl = [to_gray(f) for f in (frames() if callable(frames) else frames)]
        if not fl:
            out["pairs"].append({"recording": name, "label": label, "rows": [],
                                 "notes": ["no frames (not a video, image folder or trial)"]})
            continue
        out["pairs"].append(recording_realism(name, label, fl, params, seed))
    out["all_within_20pct"] = all(r["within_20pct"] for p in out["pairs"] for r in p["rows"]
                                  if "not_compared" not in r)
    return out


def realism_table(res: dict) -> str:
    lines = []
    for p in res["pairs"]:
        lines.append(f"real {p['recording']} ({p['label']}) vs simulated "
                     f"{p.get('sim_scene') or 'no drag scene'} (+ no-touch rest, "
                     f"{p.get('rest_frames', 0)} real rest frames)")
        lines += [f"note: {n}" for n in p.get("notes", [])]
        if not p["rows"]:
            lines.append("")
            continue
        lines.append(f"| figure | real | simulated | sim/real | within 20% |")
        lines.append("|---|---:|---:|---:|:-:|")
        for r in p["rows"]:
            verdict = "yes" if r["within_20pct"] else "NO"
            if "not_compared" in r:
                verdict = f"not compared: {r['not_compared']}"
            lines.append(f"| {r['figure']} | {r['real']:.1f} | {r['sim']:.1f} | "
                         f"{r['ratio']:.2f} | {verdict} |")
        lines.append("")
    return "\n".join(lines)


def side_by_side_png(frame: np.ndarray, name: str, out_path, seed: int = 0) -> str:
    """A real frame (``name``: what it is) and a simulated ``no-touch`` frame next to
    each other, each cropped to its dome."""
    sim = _sim_frames("no-touch", ("glare", "camera_noise"), seed, 1)[0]
    tiles = []
    for img in (to_gray(frame), to_gray(sim)):
        d = locate_dome([img]) or (img.shape[1] / 2, img.shape[0] / 2, min(img.shape) / 2)
        r = int(max(8, d[2] * 1.1))
        x0, y0 = max(0, int(d[0]) - r), max(0, int(d[1]) - r)
        tile = img[y0:y0 + 2 * r, x0:x0 + 2 * r]
        tiles.append(cv2.resize(tile, (320, 320), interpolation=cv2.INTER_AREA))
    pair = np.hstack([tiles[0], np.full((320, 8), 255, np.uint8), tiles[1]])
    pair = cv2.cvtColor(pair, cv2.COLOR_GRAY2BGR)
    for text, x in ((f"real: {name}"[:40], 6), ("simulated: roboskin no-touch", 334)):
        cv2.putText(pair, text, (x, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 200), 1,
                    cv2.LINE_AA)
    Path(out_path).parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out_path), pair)
    return str(out_path)
