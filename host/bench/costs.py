"""What one decision costs: the vision pipeline per frame, measured on real frames,
plus the window encoding and the model; the machine the times were taken on; and
the estimated Raspberry Pi 4 figures.

Every time here is taken on one thread (``cv2.setNumThreads(1)``, ONNX Runtime
``intra_op_num_threads=1``), with nothing else of the report running beside it.
"""
from __future__ import annotations

import os
import platform
import time
from pathlib import Path

import numpy as np

from device.pi.vision.encoder import FrameEncoder
from host.data.video import video_frames
from host.learn import evaluate

__all__ = ["PI4_FACTOR", "PI4_SOURCE", "machine", "machine_line", "read_frames",
           "frame_times", "vision_cost", "model_cost", "decision_cost", "percentiles"]

#: a Raspberry Pi 4 core (Cortex-A72, 1.5 GHz) takes about this many times as long
#: as one core of the machine the report runs on; see :data:`PI4_SOURCE`
PI4_FACTOR = 4.0
PI4_SOURCE = (
    "an estimate, not a measurement on a Pi: the clock ratio (1.5 GHz Cortex-A72 vs "
    "about 2.6 GHz here) times the A72's lower work per clock (about 2x), in line with "
    "public single-core benchmark scores of the Pi 4 against recent x86 server cores "
    "(about a quarter); docs/BENCHMARKS.md uses the same 3-4x for the vision pipeline")


def percentiles(ms) -> dict:
    """Median, p99 and count of a list of times in ms (None when empty), unrounded:
    :func:`host.learn.evaluate.percentiles` without the mean."""
    return evaluate.percentiles(ms, mean=False, digits=None)


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown CPU"


def machine() -> dict:
    """The CPU model, core count and load averages (1, 5, 15 min) now."""
    try:
        load = [round(x, 2) for x in os.getloadavg()]
    except OSError:
        load = None
    return {"cpu": cpu_model(), "cores": os.cpu_count() or 1, "load": load,
            "python": platform.python_version(), "system": platform.system()}


def machine_line(m: dict) -> str:
    """One line naming the machine the times were taken on."""
    load = ("n/a" if not m.get("load") else ", ".join(f"{x:.2f}" for x in m["load"]))
    return (f"Times taken on: {m['cpu']}, {m['cores']} cores, load average {load} "
            f"(1, 5, 15 min), {m['system']}, Python {m['python']}; one thread per "
            f"measurement.")


def read_frames(clip, limit: int | None = None) -> list[np.ndarray]:
    """The frames of a video file (up to ``limit``); ValueError when there are none."""
    frames = video_frames(clip, limit)
    if not frames:
        raise ValueError(f"{clip}: no frames could be read")
    return frames


def frame_times(frames, profile: str = "roboskin", crop_px: int | None = None,
                warmup: int = 10) -> tuple[list[float], list[float]]:
    """Per-frame (wall-clock, thread CPU) times in ms of :class:`FrameEncoder` (the
    marker pipeline and the layout mapping, plus the binary dome crop when
    ``crop_px``), one thread, on ``frames`` in order (the tracker follows them as on
    the leg), after ``warmup`` frames through a separate encoder."""
    import cv2

    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        enc = FrameEncoder(profile, crop_px=crop_px)
        for img in frames[:warmup]:
            enc.encode(img)
        enc = FrameEncoder(profile, crop_px=crop_px)
        wall, cpu = [], []
        for img in frames:
            w0, c0 = time.perf_counter(), time.thread_time()
            enc.encode(img)
            cpu.append((time.thread_time() - c0) * 1e3)
            wall.append((time.perf_counter() - w0) * 1e3)
    finally:
        cv2.setNumThreads(threads)
    return wall, cpu


def vision_cost(frame_sets, profile: str = "roboskin", crop_px: int | None = None) -> dict:
    """{"wall": p50/p99, "cpu": p50/p99} in ms of :func:`frame_times` over several
    recordings (a fresh encoder for each)."""
    wall, cpu = [], []
    for frames in frame_sets:
        w, c = frame_times(frames, profile, crop_px)
        wall += w
        cpu += c
    return {"wall": percentiles(wall), "cpu": percentiles(cpu)}


def model_cost(model_dir, ws, warmup: int = 20) -> dict:
    """Per decision of the float model in ``model_dir`` on the windows ``ws``: the
    window encoding the Pi runs (:func:`device.pi.models.window.encode`) and the
    model (ONNX Runtime, one thread), {"wall", "cpu"} p50/p99 in ms, its input
    layout and its file size."""
    from device.pi.models.window import encode

    pred, spec, kind = evaluate.load_variant(model_dir, "float")
    layout = spec.input_layout
    uses_imu = spec.uses_imu
    call = pred.predict_one if kind == "regressor" else pred.predict

    def decide(i):
        parts = {"vectors": ws.vectors[i], "grids": None if ws.grids is None else ws.grids[i],
                 "frames": None if ws.frames is None else ws.frames[i],
                 "imu": ws.imu[i] if uses_imu else None}
        x = encode(layout, **parts)
        return call(x)

    for i in range(min(warmup, len(ws))):
        decide(i)
    wall, cpu = [], []
    for i in range(len(ws)):
        w0, c0 = time.perf_counter(), time.thread_time()
        decide(i)
        cpu.append((time.thread_time() - c0) * 1e3)
        wall.append((time.perf_counter() - w0) * 1e3)
    folder = Path(model_dir)
    return {"wall": percentiles(wall), "cpu": percentiles(cpu), "input_layout": layout,
            "size_bytes": int((folder / spec.onnx).stat().st_size) if spec.onnx else 0}


def decision_cost(vision: dict, model: dict, factor: float = PI4_FACTOR) -> dict:
    """One decision: the vision pipeline on the newest frame, then the window
    encoding and the model, for each clock ("wall", "cpu"). p50 is the sum of the
    medians; p99 the sum of the p99s (an upper bound: the two rarely peak on one
    frame). ``pi4`` scales the CPU times by ``factor``."""
    out = {}
    for clock in ("wall", "cpu"):
        out[clock] = {q: vision[clock][q] + model[clock][q] for q in ("p50", "p99")}
    out["pi4"] = {q: factor * out["cpu"][q] for q in ("p50", "p99")}
    return out
