"""``host bench scaling``: how the marker pipeline's per-frame cost grows with the
number of pins (issue 25). Single-threaded, median and p99 per frame.

Sources, each timed with :class:`~device.pi.vision.pipeline.MarkerStream`:

- the roboskin clips (133 pins, profile ``roboskin``);
- ``tactip_shear/images/*.png`` (331 pins, profile ``tactip331``): independent presses
  with no time order, so the shallowest press (``image_1.png``) is fed first until
  it becomes the reference, then every image once, in name order (each frame is a
  new press: the tracker often re-acquires, as it would after a jump);
- ``roboskin/flatSkin.avi`` with a calibrated profile (``--flat-profile``, from
  ``host calibrate``), several hundred pins;
- simulated binary frames (the tactip331 sensor's image and motion) with hexagonal
  layouts of 127 to 721 pins, the pitch and pin size shrunk to fit the same dome.

Separately, :func:`device.pi.vision.matching.match_pins`, the tracker's steady
state (:meth:`Tracker.update`) and its coarse re-acquisition
(:func:`~device.pi.vision.neighbours.track_with_neighbours` with the tracker's
schedule, after a jump of more than a pitch) are timed alone on synthetic
hexagonal point sets (133 to 1400 pins, small random motion), to show whether
they grow quadratically. The fits are a least-squares line (ms per pin) and the exponent of
a log-log fit, ``time ~ pins ** k``.
"""
from __future__ import annotations

import math
import os
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from host.bench.sim import single_thread

__all__ = ["fit_growth", "hex_points", "time_matching", "bench_scaling", "format_scaling",
           "SIM_RINGS", "MATCH_SIZES"]

#: hexagonal rings of the simulated layouts: 1 + 3 n (n + 1) = 127, 217, 331, 469, 721 pins
SIM_RINGS = (6, 8, 10, 12, 15)
#: pin counts of the matching-alone timing
MATCH_SIZES = (133, 331, 700, 1400)


def fit_growth(pins, ms) -> dict:
    """Least-squares line ``ms = slope * pins + intercept`` and the exponent ``k`` of
    ``ms ~ pins ** k`` (log-log fit). Needs two distinct pin counts and positive
    times; otherwise every figure is NaN and ``ok`` is False."""
    x = np.asarray(pins, np.float64)
    y = np.asarray(ms, np.float64)
    ok = (x.size == y.size and x.size >= 2 and np.unique(x).size >= 2
          and bool(np.all(np.isfinite(y))) and bool(np.all(y > 0)) and bool(np.all(x > 0)))
    if not ok:
        nan = float("nan")
        return {"slope_ms_per_pin": nan, "intercept_ms": nan, "exponent": nan, "ok": False}
    slope, icpt = np.polyfit(x, y, 1)
    k, _ = np.polyfit(np.log(x), np.log(y), 1)
    return {"slope_ms_per_pin": float(slope), "intercept_ms": float(icpt),
            "exponent": float(k), "ok": True}


def hex_points(n: int, pitch_px: float = 10.0) -> np.ndarray:
    """The ``n`` points (n, 2) px of a hexagonal lattice nearest its centre."""
    rings = 1
    while 1 + 3 * rings * (rings + 1) < n:
        rings += 1
    q, r = np.meshgrid(np.arange(-rings, rings + 1), np.arange(-rings, rings + 1))
    q, r = q.ravel(), r.ravel()
    keep = np.abs(q + r) <= rings
    q, r = q[keep], r[keep]
    pts = np.stack([pitch_px * (q + r / 2.0), pitch_px * r * math.sqrt(3) / 2.0], axis=1)
    order = np.argsort(np.hypot(*pts.T), kind="stable")
    return pts[order[:n]] + 4 * rings * pitch_px


def _stats(ms: list[float]) -> dict:
    a = np.asarray(ms, np.float64)
    return {"median_ms": float(np.median(a)), "p99_ms": float(np.percentile(a, 99)),
            "n": int(a.size)}


def time_matching(sizes=MATCH_SIZES, frames: int = 60, pitch_px: float = 10.0,
                  motion_px: float = 0.5, seed: int = 0, reacquire_repeats: int = 3) -> dict:
    """Per-call median / p99 ms of ``match_pins`` (gate 0.4 pitch) and of the
    tracker's steady-state ``update`` on hexagonal sets of ``sizes`` pins that
    drift and jitter by about ``motion_px`` a frame (3 % of pins missing); and
    ``reacquire_repeats`` times the tracker's coarse re-acquisition
    (``track_with_neighbours`` with ``FULL_SEARCH_SCHEDULE``) after a jump of 1.2
    pitch, with the fraction of pins it puts back on their own pin
    (``reacquire_right``). ``reacquire_repeats=0`` leaves it out."""
    from device.pi.vision.matching import match_pins
    from device.pi.vision.neighbours import layout_neighbours, track_with_neighbours
    from device.pi.vision.tracking import FULL_SEARCH_SCHEDULE, Tracker

    rng = np.random.default_rng(seed)
    gate = 0.4 * pitch_px
    out = {}
    for n in sizes:
        ref = hex_points(int(n), pitch_px)
        drift = np.cumsum(rng.normal(0, motion_px, (frames, 1, 2)), axis=0)
        curs = []
        for f in range(frames):
            c = ref + drift[f] + rng.normal(0, motion_px / 2, ref.shape)
            keep = rng.random(len(c)) >= 0.03
            curs.append(c[keep][rng.permutation(int(keep.sum()))])
        for c in curs[:5]:                              # warm caches and scratch
            match_pins(ref, c, gate)
        mt, tt, right = [], [], []
        clock = time.thread_time                        # CPU time: no waits of a loaded machine
        for f, c in enumerate(curs):
            prev = ref + drift[f - 1] if f else ref
            t0 = clock()
            idx = match_pins(prev, c, gate)
            mt.append((clock() - t0) * 1e3)
            right.append(float((idx >= 0).mean()))
        tr = Tracker(max_dist_px=gate, pitch_px=pitch_px)
        tr.set_reference(ref)
        for c in curs[:5]:
            tr.update(c)
        for c in curs:
            t0 = clock()
            tr.update(c)
            tt.append((clock() - t0) * 1e3)
        out[int(n)] = {"match": _stats(mt), "tracker_update": _stats(tt),
                       "matched_fraction": float(np.mean(right))}
        if reacquire_repeats > 0:
            # a jump of 1.2 pitch (a snap back): the nearest-pin matching would take
            # the neighbour; the coarse search, from no prior, finds the pins again
            rj = np.random.default_rng([seed, int(n)])     # the matching's draws stay as they were
            jump = ref + np.array([1.2, 0.3]) * pitch_px + rj.normal(0, motion_px / 2, ref.shape)
            perm = rj.permutation(len(jump))
            neighbours = layout_neighbours(ref)
            start, steps, iters = FULL_SEARCH_SCHEDULE
            rt = []
            for _ in range(reacquire_repeats):
                t0 = clock()
                idx, _ = track_with_neighbours(ref, jump[perm], pitch_px, neighbours=neighbours,
                                               gate_frac=0.4, grow_rounds=4, anneal_start=start,
                                               anneal_steps=steps, sinkhorn_iters=iters)
                rt.append((clock() - t0) * 1e3)
            hit = idx >= 0
            out[int(n)]["reacquire"] = _stats(rt)
            out[int(n)]["reacquire_right"] = float(np.mean(hit & (perm[np.maximum(idx, 0)]
                                                                  == np.arange(len(ref)))))
    ns = sorted(out)
    keys = ("match", "tracker_update") + (("reacquire",) if reacquire_repeats > 0 else ())
    res = {"sizes": out, "pitch_px": pitch_px, "motion_px": motion_px,
           "match_fit": fit_growth(ns, [out[n]["match"]["median_ms"] for n in ns]),
           "tracker_fit": fit_growth(ns, [out[n]["tracker_update"]["median_ms"] for n in ns])}
    if reacquire_repeats > 0:
        res["reacquire_fit"] = fit_growth(ns, [out[n]["reacquire"]["median_ms"] for n in ns])
    if len(ns) >= 2:          # the local exponent between the two largest sets
        a, b = ns[-2], ns[-1]
        for key in keys:
            ya, yb = out[a][key]["median_ms"], out[b][key]["median_ms"]
            res[f"{key}_exponent_{a}_{b}"] = (math.log(yb / ya) / math.log(b / a)
                                              if ya > 0 and yb > 0 else float("nan"))
    return res


# -- the marker pipeline on each source ------------------------------------------------

def _time_stream(profile, frames, warm=(), repeats: int = 1) -> dict:
    """Per-frame wall time (``total``) and CPU time of this thread (``cpu``) of a
    MarkerStream over ``frames``, median and p99, with its detect and track stages
    (wall, the stream's own timings), after ``warm`` frames (not timed) that set the
    reference; ``pins`` is the median count the frames' detection found. The CPU
    time leaves out the waits of a loaded machine (another process holding the core)."""
    from device.pi.vision.pipeline import MarkerStream

    wall, cpu, detect, track, pins, ref = [], [], [], [], [], 0
    clock, cpu_clock = time.perf_counter, time.thread_time
    for _ in range(max(1, repeats)):
        stream = MarkerStream(profile)
        stream.fuse = False            # each stage timed apart (a fused frame times one call)
        for f in warm:
            stream.process(f)
        for f in frames:
            t0, c0 = clock(), cpu_clock()
            out = stream.process(f)
            cpu.append((cpu_clock() - c0) * 1e3)
            wall.append((clock() - t0) * 1e3)
            detect.append(out.timings_ms.get("detect", 0.0))
            track.append(out.timings_ms.get("track", 0.0))
            pins.append(len(out.pins))
        ref = 0 if stream.reference is None else len(stream.reference)
    return {"total": _stats(wall), "cpu": _stats(cpu), "detect": _stats(detect),
            "track": _stats(track), "pins": int(np.median(pins)) if pins else 0,
            "reference_pins": ref, "frames": len(frames)}


def _sim_source(rings: int, frames: int):
    """Binary frames of the drag-45 motion on the tactip331 image with ``rings``
    hexagonal rings (the first still ones to set the reference, then consecutive ones
    from the middle of the drag), and its pipeline profile."""
    from device.profile import hex_layout, load_pipeline_profile, load_profile
    from device.sim import Simulator, load_scene

    sens = load_profile("tactip331")
    pitch = 190.0 / rings                       # the outer ring stays 190 px out
    pin_d = sens.pin_diameter_px * pitch / 19.2
    pins = hex_layout(rings, pitch, sens.dome_centre_px)
    sens = replace(sens, pins_px=pins, pin_diameter_px=pin_d)
    scene = replace(load_scene("drag-45"), profile=sens, width=sens.width, height=sens.height)
    sim = Simulator(scene, seed=0)
    lo = max(6, (sim.n_frames - frames) // 2)        # consecutive frames mid-drag
    warm = [sim.render(i) for i in range(6)]         # still: they set the reference
    imgs = [sim.render(i) for i in range(lo, min(sim.n_frames, lo + frames))]
    area = math.pi * pin_d * pin_d / 4
    prof = load_pipeline_profile("tactip331")
    prof = replace(prof, name=f"sim-hex{rings}", pitch_px=pitch, n_pins=len(pins),
                   match_gate_px=0.4 * pitch,
                   vision=replace(prof.vision, min_area_px=max(1, int(0.3 * area)),
                                  max_area_px=max(2, int(3.0 * area))))
    return warm, imgs, prof


def bench_scaling(data=None, flat_profile=None, frames: int = 120, repeats: int = 1,
                  sim_rings=SIM_RINGS, match_sizes=MATCH_SIZES,
                  progress=lambda m: None) -> dict:
    """Per-frame cost of the marker pipeline against the pin count on every source
    present (``data``: the real-data folder holding roboskin/ and tactip_shear/;
    None: simulated frames only), and matching alone on synthetic point sets.
    One thread: OpenCV's and numpy's BLAS (whose matrix products go multi-threaded
    from about 700 pins, see :func:`time_matching`) are both limited to one."""
    from threadpoolctl import threadpool_info, threadpool_limits

    with threadpool_limits(limits=1):
        res = _bench_scaling(data, flat_profile, frames, repeats, sim_rings, match_sizes,
                             progress)
        res["blas_threads"] = max([i["num_threads"] for i in threadpool_info()
                                   if i.get("user_api") == "blas"] or [1])
    return res


def _bench_scaling(data, flat_profile, frames, repeats, sim_rings, match_sizes,
                   progress) -> dict:
    import cv2

    from host.data.video import video_frames

    single_thread()
    res = {"threads": 1, "sources": {}, "skipped": {},
           "load_avg_1min_start": round(os.getloadavg()[0], 2)}
    root = None if data is None else Path(data)
    if root is not None:
        for clip in ("smooth.avi", "concrete.avi"):
            p = root / "roboskin" / clip
            if not p.is_file():
                res["skipped"][f"roboskin {clip}"] = f"no {p}"
                continue
            progress(f"roboskin {clip}")
            imgs = video_frames(p, limit=frames)
            res["sources"][f"roboskin {clip}"] = _time_stream("roboskin", imgs, repeats=repeats)
        shear = root / "tactip_shear" / "images"
        first = shear / "image_1.png"
        if first.is_file():
            progress("tactip_shear")
            names = sorted(shear.glob("*.png"))[:frames]
            imgs = [cv2.imread(str(n), cv2.IMREAD_GRAYSCALE) for n in names]
            rest = cv2.imread(str(first), cv2.IMREAD_GRAYSCALE)
            res["sources"]["tactip_shear png"] = _time_stream("tactip331", imgs, warm=[rest] * 6,
                                                              repeats=repeats)
        else:
            res["skipped"]["tactip_shear png"] = f"no {first}"
        flat = root / "roboskin" / "flatSkin.avi"
        if flat_profile is None:
            res["skipped"]["roboskin flatSkin.avi"] = ("no --flat-profile (host calibrate "
                                                       f"{flat} --out FLAT.toml)")
        elif not flat.is_file():
            res["skipped"]["roboskin flatSkin.avi"] = f"no {flat}"
        else:
            progress("flatSkin")
            imgs = video_frames(flat, limit=frames)
            res["sources"]["roboskin flatSkin.avi"] = _time_stream(str(flat_profile), imgs,
                                                                   repeats=repeats)
    for rings in sim_rings:
        progress(f"simulated hex, {rings} rings")
        warm, imgs, prof = _sim_source(int(rings), frames)
        e = _time_stream(prof, imgs, warm=warm, repeats=repeats)
        e["layout_pins"] = prof.n_pins
        res["sources"][f"sim hex {prof.n_pins}"] = e
    progress("matching alone")
    res["matching"] = time_matching(match_sizes)
    src = res["sources"]
    sims = [k for k in src if k.startswith("sim ")]
    for key, names in (("all", list(src)), ("sim", sims)):
        pins = [src[k]["pins"] for k in names]
        res[f"fit_{key}"] = fit_growth(pins, [src[k]["cpu"]["median_ms"] for k in names])
        res[f"fit_{key}_wall"] = fit_growth(pins, [src[k]["total"]["median_ms"] for k in names])
    res["fit_sim_track"] = fit_growth([src[k]["pins"] for k in sims],
                                      [src[k]["track"]["median_ms"] for k in sims])
    res["load_avg_1min_end"] = round(os.getloadavg()[0], 2)
    return res


def format_scaling(res: dict) -> str:
    def fit(f):
        return (f"slope {f['slope_ms_per_pin'] * 1000:.2f} us/pin, "
                f"intercept {f['intercept_ms']:.3f} ms, log-log exponent {f['exponent']:.2f}")

    lines = [f"marker pipeline cost vs pins, 1 thread (load average "
             f"{res['load_avg_1min_start']} -> {res['load_avg_1min_end']}); ms per frame: "
             f"wall and CPU (this thread), detect and track stages wall",
             f"{'source':<24}{'pins':>6}{'frames':>7}{'median':>8}{'p99':>8}{'cpu med':>9}"
             f"{'cpu p99':>9}{'detect':>8}{'track':>8}{'trk p99':>9}"]
    for name, e in res["sources"].items():
        lines.append(f"{name:<24}{e['pins']:>6}{e['frames']:>7}{e['total']['median_ms']:>8.3f}"
                     f"{e['total']['p99_ms']:>8.3f}{e['cpu']['median_ms']:>9.3f}"
                     f"{e['cpu']['p99_ms']:>9.3f}{e['detect']['median_ms']:>8.3f}"
                     f"{e['track']['median_ms']:>8.3f}{e['track']['p99_ms']:>9.3f}")
    for name, why in res["skipped"].items():
        lines.append(f"{name:<24}skipped: {why}")
    lines.append(f"fit of CPU median, all sources: {fit(res['fit_all'])}")
    lines.append(f"fit of CPU median, simulated (same image, pins vary): {fit(res['fit_sim'])}")
    lines.append(f"fit of wall median, simulated: {fit(res['fit_sim_wall'])}")
    lines.append(f"fit of track stage (wall), simulated: {fit(res['fit_sim_track'])}")
    m = res["matching"]
    lines.append(f"matching alone, CPU ms per call (hex lattice, pitch {m['pitch_px']} px, "
                 f"motion {m['motion_px']} px/frame)")
    lines.append(f"  {'pins':>6}{'match_pins':>12}{'p99':>9}{'Tracker.update':>16}{'p99':>9}"
                 f"{'re-acquire':>12}{'right':>7}")
    for n, e in m["sizes"].items():
        re = (f"{e['reacquire']['median_ms']:>12.3f}{e['reacquire_right']:>7.3f}"
              if "reacquire" in e else "")
        lines.append(f"  {n:>6}{e['match']['median_ms']:>12.4f}{e['match']['p99_ms']:>9.4f}"
                     f"{e['tracker_update']['median_ms']:>16.4f}"
                     f"{e['tracker_update']['p99_ms']:>9.4f}{re}")
    lines.append(f"  match_pins: {fit(m['match_fit'])}")
    lines.append(f"  Tracker.update: {fit(m['tracker_fit'])}")
    if "reacquire_fit" in m:
        lines.append(f"  re-acquisition: {fit(m['reacquire_fit'])}")
    for k, v in m.items():
        if "_exponent_" in k:
            lines.append(f"  local exponent {k.replace('_exponent_', ' ')}: {v:.2f}")
    return "\n".join(lines)
