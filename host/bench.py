"""Benchmarks (``host bench ...``). Single-threaded, medians with p99."""
from __future__ import annotations

import time

import numpy as np


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
