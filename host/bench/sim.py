"""Benchmarks (``host bench ...``). Single-threaded, medians with p99."""
from __future__ import annotations

import os
import time

import numpy as np

from host.analysis.recall import recall_precision
from host.data.video import video_frames

# issue 25's goals for the marker pipeline on real frames, one core: the median frame,
# and the ratio to SimpleBlobDetector with a vectorised nearest neighbour
PIPELINE_MEDIAN_MS = 0.4
PIPELINE_SPEEDUP = 8.0


def single_thread():
    import cv2
    cv2.setNumThreads(1)


def timing_stats(seconds: list[float] | np.ndarray) -> dict:
    a = np.asarray(seconds, dtype=np.float64) * 1000.0
    return {"median_ms": float(np.median(a)), "p99_ms": float(np.percentile(a, 99)),
            "mean_ms": float(a.mean()), "n": int(a.size)}


def _time_render(sim, repeats: int) -> dict:
    out = np.empty((sim.height, sim.width), np.uint8)
    for i in range(min(sim.n_frames, 20)):         # warm caches
        sim.render(i, out)
    times = []
    clock = time.perf_counter
    for _ in range(repeats):
        for i in range(sim.n_frames):
            t0 = clock()
            sim.render(i, out)
            times.append(clock() - t0)
    st = timing_stats(times)
    st["fps"] = 1000.0 / st["mean_ms"]
    return st


def bench_sim(scene_name: str = "minimal", repeats: int = 20) -> dict:
    """Frames per second of the minimal scene at 320x240 and 640x480, and the
    added per-frame cost of each effect at 640x480."""
    from dataclasses import replace

    from device.sim import EFFECTS, Simulator, load_scene

    single_thread()
    base = load_scene(scene_name)
    result = {"scene": scene_name, "threads": 1, "sizes": {}, "effects": {}}
    for w, h in ((320, 240), (640, 480)):
        sim = Simulator(replace(base, width=w, height=h), seed=0)
        result["sizes"][f"{w}x{h}"] = _time_render(sim, repeats)
    ref = result["sizes"]["640x480"]
    for name in EFFECTS:
        sim = Simulator(replace(base.with_effects(name), width=640, height=480), seed=0)
        st = _time_render(sim, max(3, repeats // 2))
        st["added_ms"] = st["median_ms"] - ref["median_ms"]
        result["effects"][name] = st
    result["goals"] = {
        "320x240_fps>=3000": result["sizes"]["320x240"]["fps"] >= 3000,
        "640x480_fps>=1000": result["sizes"]["640x480"]["fps"] >= 1000,
    }
    return result


def format_sim(res: dict) -> str:
    lines = [f"simulator, scene {res['scene']}, 1 thread",
             f"{'case':<22}{'fps':>9}{'median ms':>11}{'p99 ms':>9}{'added ms':>10}"]
    for size, st in res["sizes"].items():
        lines.append(f"{'minimal ' + size:<22}{st['fps']:>9.0f}{st['median_ms']:>11.4f}"
                     f"{st['p99_ms']:>9.4f}{'':>10}")
    for name, st in res["effects"].items():
        lines.append(f"{'+' + name + ' 640x480':<22}{st['fps']:>9.0f}{st['median_ms']:>11.4f}"
                     f"{st['p99_ms']:>9.4f}{st['added_ms']:>10.4f}")
    lines.append("goals: " + ", ".join(f"{k} {'met' if v else 'MISSED'}"
                                       for k, v in res["goals"].items()))
    return "\n".join(lines)


# -- the marker pipeline ------------------------------------------------------------

def _sim_frames_truth(scene: str = "drag-45", effects=("glare", "camera_noise"), seed: int = 0):
    from device.sim import Simulator, load_scene
    sim = Simulator(load_scene(scene).with_effects(*effects), seed=seed)
    frames = [sim.render(i) for i in range(sim.n_frames)]
    return frames, sim.truth


def nearest_pins(ref: np.ndarray, pins: np.ndarray) -> np.ndarray:
    """For each row of ``ref`` (m, 2) the row of ``pins`` (n, 2) nearest to it, or -1
    when there are no pins: one vectorised (m, n) squared-distance matrix and a row
    argmin, as common TacTip toolkits match. Like the brute-force loop it replaces,
    no gate and not one to one (two reference pins may take the same pin); the
    squared distances are computed in the inputs' dtype, in the loop's order
    (``dx**2 + dy**2``), and ties go to the first pin, so the pairs are the loop's."""
    if len(pins) == 0:
        return np.full(len(ref), -1, np.int64)
    dx = np.subtract.outer(ref[:, 0], pins[:, 0])
    dy = np.subtract.outer(ref[:, 1], pins[:, 1])
    dx *= dx
    dy *= dy
    dx += dy
    return dx.argmin(axis=1).astype(np.int64, copy=False)


class BaselineBlobTracker:
    """What common TacTip toolkits do: OpenCV SimpleBlobDetector on the frame,
    then nearest-neighbour matching to the reference pins with a vectorised
    distance matrix (:func:`nearest_pins`)."""

    def __init__(self, min_area: float = 10, max_area: float = 100):
        import cv2
        p = cv2.SimpleBlobDetector_Params()
        p.filterByColor = True
        p.blobColor = 255
        p.filterByArea = True
        p.minArea = float(min_area)
        p.maxArea = float(max_area)
        p.filterByCircularity = False
        p.filterByConvexity = False
        p.filterByInertia = False
        p.minThreshold = 120
        p.maxThreshold = 240
        p.thresholdStep = 10
        self.det = cv2.SimpleBlobDetector_create(p)
        self.ref = None

    def detect(self, gray):
        kps = self.det.detect(gray)
        return np.array([k.pt for k in kps], np.float32).reshape(-1, 2)

    def match(self, pins: np.ndarray) -> np.ndarray:
        """Row of ``pins`` each reference pin is matched to (-1: none)."""
        return nearest_pins(self.ref, pins)

    def process(self, gray):
        pins = self.detect(gray)
        if self.ref is None:
            self.ref = pins
        idx = self.match(pins)
        vec = np.zeros_like(self.ref)
        hit = idx >= 0
        vec[hit] = pins[idx[hit]] - self.ref[hit]
        return pins, vec


def bench_pipeline(recordings=(), repeats: int = 3, profile: str = "roboskin",
                   limit: int = 300) -> dict:
    """Per-stage and total median / p99 ms per frame of the marker pipeline with the
    sensor ``profile`` (video decoding excluded), on the first ``limit`` frames of
    each of ``recordings`` (:class:`host.bench.specs.Recording`, from the caller's
    data spec) and on simulated frames, against the SimpleBlobDetector +
    vectorised nearest-neighbour baseline, plus steady-state allocation."""
    from host.bench.specs import recording_frames

    import gc
    import tracemalloc

    import cv2

    from device.pi.vision.pipeline import STAGES, MarkerStream
    from device.pi.vision.extract import to_gray

    single_thread()
    sets = {}
    for rec in recordings:
        frames = recording_frames(rec, limit)
        if frames:
            sets[f"real {rec.name}"] = (frames, None)
    sim_frames, truth = _sim_frames_truth()
    sets["sim drag-45"] = (sim_frames, truth)
    res = {"profile": profile, "threads": 1, "sets": {},
           "load_avg_1min_start": round(os.getloadavg()[0], 2)}
    for name, (frames, tr) in sets.items():
        stage_t = {k: [] for k in STAGES + ("total",)}
        for _ in range(repeats):
            stream = MarkerStream(profile)
            for f in frames:
                out = stream.process(f)
                for k in stage_t:
                    stage_t[k].append(out.timings_ms.get(k, 0.0))
        st = {k: {"median_ms": float(np.median(v)), "p99_ms": float(np.percentile(v, 99))}
              for k, v in stage_t.items()}
        # baseline on the same frames (gray conversion excluded for both)
        grays = [to_gray(f) for f in frames]
        base = BaselineBlobTracker()
        bt = []
        for g in grays:
            t0 = time.perf_counter()
            base.process(g)
            bt.append((time.perf_counter() - t0) * 1e3)
        entry = {"stages": st, "frames": len(frames),
                 "baseline": {"median_ms": float(np.median(bt)),
                              "p99_ms": float(np.percentile(bt, 99))}}
        entry["speedup_vs_baseline"] = entry["baseline"]["median_ms"] / max(
            st["total"]["median_ms"], 1e-9)
        if tr is not None:
            stream = MarkerStream(profile)
            ours, theirs = [], []
            for i, g in enumerate(grays):
                vis = tr["pins_px"][i][tr["visible"][i]]
                ours.append(recall_precision(stream.process(g).pins, vis))
                theirs.append(recall_precision(base.detect(g), vis))
            entry["recall"] = float(np.mean([r for r, _ in ours]))
            entry["precision"] = float(np.mean([p for _, p in ours]))
            entry["baseline_recall"] = float(np.mean([r for r, _ in theirs]))
            entry["baseline_precision"] = float(np.mean([p for _, p in theirs]))
        res["sets"][name] = entry
    # steady state: no allocation growth over many frames
    stream = MarkerStream(profile)
    frames = sets[next(iter(sets))][0]
    for f in frames[:50]:
        stream.process(f)
    gc.collect()
    tracemalloc.start()
    for f in frames[:50]:
        stream.process(f)
    gc.collect()
    first, _ = tracemalloc.get_traced_memory()
    for _ in range(4):
        for f in frames:
            stream.process(f)
    gc.collect()
    last, _ = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    res["load_avg_1min_end"] = round(os.getloadavg()[0], 2)
    res["steady_state_growth_bytes"] = int(last - first)
    res["steady_state_frames"] = 4 * len(frames)
    res["goals"] = {
        f"total_median<={PIPELINE_MEDIAN_MS:g}ms": all(
            e["stages"]["total"]["median_ms"] <= PIPELINE_MEDIAN_MS for e in res["sets"].values()),
        f"speedup>={PIPELINE_SPEEDUP:g}x": all(e["speedup_vs_baseline"] >= PIPELINE_SPEEDUP
                                              for e in res["sets"].values()),
        "recall>=baseline": all(e.get("recall", 1) >= e.get("baseline_recall", 0)
                                for e in res["sets"].values()),
        "no_growth": res["steady_state_growth_bytes"] < 64 * 1024,
    }
    return res


def format_pipeline(res: dict) -> str:
    lines = [f"marker pipeline, profile {res['profile']}, 1 thread (decoding excluded)"]
    for name, e in res["sets"].items():
        lines.append(f"{name} ({e['frames']} frames)")
        lines.append(f"  {'stage':<10}{'median ms':>11}{'p99 ms':>9}")
        for k, v in e["stages"].items():
            lines.append(f"  {k:<10}{v['median_ms']:>11.4f}{v['p99_ms']:>9.4f}")
        b = e["baseline"]
        lines.append(f"  baseline SimpleBlobDetector + vectorised NN: median "
                     f"{b['median_ms']:.3f} ms, p99 {b['p99_ms']:.3f} ms; ours is "
                     f"{e['speedup_vs_baseline']:.1f}x faster")
        if "recall" in e:
            lines.append(f"  pin recall {e['recall']:.4f} precision {e['precision']:.4f}; "
                         f"baseline recall {e['baseline_recall']:.4f} precision "
                         f"{e['baseline_precision']:.4f}")
    lines.append(f"steady-state allocation growth over {res['steady_state_frames']} frames: "
                 f"{res['steady_state_growth_bytes']} bytes")
    lines.append("goals: " + ", ".join(f"{k} {'met' if v else 'MISSED'}"
                                       for k, v in res["goals"].items()))
    return "\n".join(lines)
