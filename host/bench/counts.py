"""Instructions per frame, counted with valgrind's callgrind (issue 30, items 1 and 8).

A count of instructions does not move with the load of the machine the way a wall
time does, so before/after comparisons of the frame path are counts. Each figure is
the difference of two whole-process counts, one run of ``n2`` frames and one of
``n1``, divided by ``n2 - n1``: start-up, imports, model loading and the frame
loading cancel, and what remains is the cost of a frame in the steady state.

What is counted, on a real clip decoded to gray frames (``cv2.COLOR_BGR2GRAY`` of
each decoded frame: what a V4L2 camera's luma plane gives the leg) and written once
as a folder of PGM files (cached under ``out/bench/frames/<clip>/``):

* ``runtime``: the leg runtime end to end, ``python -m device.pi run --camera
  FOLDER --imu file://GYRO.npy --serial loop:// --frames N --config LEG.toml
  --json`` with the shipped models, unpaced (a file source is not paced unless
  given ``?realtime=1``), the config a copy of ``device/leg.toml`` with
  ``stall_periods = 100`` so the slowed run raises no camera fault. The runtime
  reads each frame from its PGM file, so a frame's count includes that read;
* ``runtime_pty``: the same with ``--serial`` a pty this harness drains: a packet
  is one ``write()``, as on the leg's UART, where ``loop://`` queues every byte
  through Python and loops the leg's own packets back to its reader;
* ``pipeline``: ``MarkerStream('roboskin').process`` on each gray frame, the frames
  loaded into memory first (:mod:`host.bench.count_drivers`);
* the pipeline's stages, by the difference of cumulative variants (detection;
  detection and tracking; ...; the rest is ``process``' own bookkeeping: the
  plausibility check, the timers, the result), and beside them the split of the
  pipeline's own stage timers measured under callgrind (a share of time, not a
  count, but it needs nothing but the stream's public output);
* ``peer``: SimpleBlobDetector and a nearest-neighbour match
  (:class:`host.bench.sim.BaselineBlobTracker`), on the same in-memory frames.

Everything runs through public entry points (the runtime's command line, the
stream's ``process``), so the counts follow whatever the frame path does. A stage
variant that can no longer be built from the stream's stage objects is reported
as not counted, with its error, and the timer split still stands.

Pi 4 column: ``ms = instructions / PI4_INSTR_PER_S * 1000`` (see
:data:`PI4_INSTR_PER_S`), beside the 8.33 ms a frame has at 120 fps.

    python -m host.bench.counts --real-data DIR [--clips lego_train.avi,...]
        [--n1 20 --n2 220] [--jobs 2] [--json]
"""
from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from device.errors import InputError, TacfootError

__all__ = ["N1", "N2", "PI4_INSTR_PER_S", "FRAME_BUDGET_MS", "DEFAULT_CLIPS",
           "parse_callgrind", "per_frame", "pi4_ms", "write_pgm", "frame_folder",
           "callgrind_cmd", "runtime_argv", "driver_argv", "stall_config", "imu_for",
           "count_clip", "bench_counts", "format_counts"]

N1, N2 = 20, 220
DEFAULT_CLIPS = ("lego_train.avi",)
KNOWN_CLIPS = ("lego_train.avi", "concrete.avi", "smooth.avi")
#: instructions per second assumed for one Raspberry Pi 4 core: a Cortex-A72 at
#: 1.5 GHz retiring about 1.0-1.3 instructions per clock on this kind of code
#: (interpreter dispatch, numpy and OpenCV loops over small arrays, branchy C), so
#: 1.5e9-2.0e9 instructions/s; the middle, 1.75e9, is used. An estimate, not a
#: measurement on a Pi: ``perf stat -e instructions,cycles`` there gives the real IPC.
PI4_INSTR_PER_S = 1.75e9
PI4_INSTR_PER_S_RANGE = (1.5e9, 2.0e9)
PI4_ASSUMPTION = ("Cortex-A72 at 1.5 GHz, IPC about 1.0-1.3 on this code: 1.5-2.0e9 "
                  "instructions/s, taken as 1.75e9; ms per frame = instructions / 1.75e9 "
                  "* 1000")
FRAME_FPS = 120.0
FRAME_BUDGET_MS = 1000.0 / FRAME_FPS
STALL_PERIODS = 100
CACHE = Path("out/bench/frames")
#: what is counted, in the table's order; the stages sit under the pipeline
TARGETS = ("runtime", "runtime_pty", "pipeline", "peer")
STAGE_NAMES = {"detect": "detection", "track": "tracking", "grid": "contact grid",
               "features": "features", "rest": "rest of process()"}
_LINE = re.compile(r"^(summary|totals):\s*(\d+)", re.M)


class CountError(TacfootError, RuntimeError):
    """A counted run failed or its output held no total; the message says which."""


# -- arithmetic and parsing ------------------------------------------------------------

def parse_callgrind(path) -> int:
    """The instruction count (the first event, Ir) of a callgrind output file: its
    ``summary:`` line, or its ``totals:`` line when it has no summary."""
    text = Path(path).read_text(errors="replace")
    found = {m.group(1): int(m.group(2)) for m in _LINE.finditer(text)}
    for key in ("summary", "totals"):
        if key in found:
            return found[key]
    raise CountError(f"{path}: no 'summary:' or 'totals:' line (not a callgrind output file?)")


def per_frame(count_n1: int, count_n2: int, n1: int, n2: int) -> float:
    """Instructions per frame: ``(count_n2 - count_n1) / (n2 - n1)``."""
    if n2 <= n1:
        raise ValueError(f"n2 must be larger than n1, got n1={n1}, n2={n2}")
    return (count_n2 - count_n1) / (n2 - n1)


def pi4_ms(instructions: float, instr_per_s: float = PI4_INSTR_PER_S) -> float:
    """Estimated ms per frame on one Pi 4 core (:data:`PI4_INSTR_PER_S`)."""
    return instructions / instr_per_s * 1e3


# -- frames ------------------------------------------------------------------------------

def write_pgm(path, gray) -> None:
    """``gray`` (2-D uint8) as a binary PGM (P5, maxval 255)."""
    import numpy as np
    a = np.ascontiguousarray(gray)
    if a.ndim != 2 or a.dtype != np.uint8:
        raise ValueError(f"write_pgm: a 2-D uint8 image is needed, got shape {a.shape} "
                         f"dtype {a.dtype}")
    h, w = a.shape
    Path(path).write_bytes(f"P5\n{w} {h}\n255\n".encode() + a.tobytes())


def frame_folder(clip, n: int, cache=CACHE) -> Path:
    """A folder of the first ``n`` frames of the video ``clip`` as gray PGM files
    (``frame_00000.pgm``, ...), written once under ``cache/<clip stem>/`` and reused
    while its ``frames.json`` names the same clip (size and mtime) and enough frames."""
    import cv2
    clip = Path(clip)
    st = clip.stat()
    key = {"clip": str(clip.resolve()), "size": st.st_size, "mtime_ns": st.st_mtime_ns,
           "gray": "cv2.COLOR_BGR2GRAY"}
    folder = Path(cache) / clip.stem
    meta = folder / "frames.json"
    try:
        old = json.loads(meta.read_text())
        if {k: old.get(k) for k in key} == key and old.get("frames", 0) >= n:
            return folder
    except (OSError, ValueError):
        pass
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    cap = cv2.VideoCapture(str(clip))
    i = 0
    try:
        while i < n:
            ok, frame = cap.read()
            if not ok:
                break
            gray = frame if frame.ndim == 2 else cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
            write_pgm(folder / f"frame_{i:05d}.pgm", gray)
            i += 1
    finally:
        cap.release()
    if i < n:
        raise CountError(f"{clip}: {i} frames decoded, {n} needed")
    meta.write_text(json.dumps(dict(key, frames=i)))
    return folder


def imu_for(clip) -> str:
    """The IMU source of a roboskin clip: its gyro file beside it
    (``concrete.avi`` -> ``concrete_gyro.npy``, ``lego_train.avi`` ->
    ``lego_gyro_train.npy``), or ``none``."""
    clip = Path(clip)
    stem = clip.stem
    names = [f"{stem}_gyro.npy"]
    if stem.endswith("_train"):
        names.append(f"{stem[:-len('_train')]}_gyro_train.npy")
    for name in names:
        if (clip.parent / name).is_file():
            return f"file://{clip.parent / name}"
    return "none"


def stall_config(folder, stall_periods: float = STALL_PERIODS) -> Path:
    """A copy of ``device/leg.toml`` with ``[camera] stall_periods`` set (a run
    slowed 50x by valgrind would otherwise raise the camera fault), in ``folder``."""
    from device.pi.runtime.config import DEFAULT_CONFIG
    text = Path(DEFAULT_CONFIG).read_text()
    new, n = re.subn(r"(?m)^(\s*stall_periods\s*=\s*)[^#\n]*?(\s*(#.*)?)$",
                     lambda m: f"{m.group(1)}{stall_periods:g}{m.group(2)}", text, count=1)
    if n != 1:
        raise CountError(f"{DEFAULT_CONFIG}: no stall_periods key to set")
    path = Path(folder) / "leg-counts.toml"
    path.write_text(new)
    return path


# -- commands ------------------------------------------------------------------------------

def callgrind_cmd(out_file, argv) -> list[str]:
    """``argv`` under callgrind, its output file ``out_file``."""
    return ["valgrind", "--tool=callgrind", f"--callgrind-out-file={out_file}", *map(str, argv)]


def runtime_argv(frames_dir, imu: str, n: int, config, python=sys.executable,
                 serial: str = "loop://") -> list[str]:
    """The leg runtime end to end on the PGM folder, unpaced, ``n`` frames."""
    return [python, "-m", "device.pi", "run", "--camera", str(frames_dir), "--imu", imu,
            "--serial", serial, "--frames", str(n), "--config", str(config), "--json"]


def driver_argv(kind: str, frames_dir, n: int, timings=None, python=sys.executable) -> list[str]:
    """One of :mod:`host.bench.count_drivers`' programs on ``n`` frames."""
    argv = [python, "-m", "host.bench.count_drivers", kind, str(frames_dir), str(n)]
    return argv + (["--timings", str(timings)] if timings else [])


def _env() -> dict:
    return dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1",
                MKL_NUM_THREADS="1", PYTHONHASHSEED="0")


def _shown(argv) -> str:
    """A command as a user would type it (``python`` for this interpreter)."""
    return " ".join("python" if a == sys.executable else a for a in map(str, argv))


PTY = "PTY"      # in a runtime argv: the slave of a pty this harness drains


def _on_pty(cmd: list, timeout: float):
    """Run ``cmd`` with :data:`PTY` replaced by a pty's slave, whose master a thread
    of this process reads and drops (what a UART's far end does); a pty is written
    with one ``write()`` a packet, as /dev/serial0 is, where pyserial's ``loop://``
    queues every byte through Python."""
    import pty
    import threading
    import tty
    master, slave = pty.openpty()
    tty.setraw(slave)

    def drain():
        try:
            while os.read(master, 65536):
                pass
        except OSError:
            pass
    threading.Thread(target=drain, daemon=True).start()
    try:
        cmd = [os.ttyname(slave) if a == PTY else a for a in cmd]
        return subprocess.run(cmd, capture_output=True, text=True, env=_env(), timeout=timeout)
    finally:
        os.close(slave)
        os.close(master)


def run_counted(argv, out_file, timeout: float = 3600) -> dict:
    """Run ``argv`` under callgrind; its instruction count, seconds, and the stdout."""
    cmd = callgrind_cmd(out_file, argv)
    t0 = time.monotonic()
    r = (_on_pty(cmd, timeout) if PTY in cmd else
         subprocess.run(cmd, capture_output=True, text=True, env=_env(), timeout=timeout))
    secs = time.monotonic() - t0
    if r.returncode != 0:
        tail = [ln for ln in r.stderr.strip().splitlines() if ln.strip() and
                not ln.startswith("==")][-1:] or [f"exit {r.returncode}"]
        raise CountError(f"{_shown(argv)}: failed under callgrind ({r.returncode}): {tail[0]}")
    return {"instructions": parse_callgrind(out_file), "seconds": round(secs, 1),
            "stdout": r.stdout}


# -- one clip ----------------------------------------------------------------------------

def _jobs(clip: Path, frames_dir: Path, config: Path, n1: int, n2: int, work: Path):
    """(name, n, argv, extra) of every counted run of one clip."""
    imu = imu_for(clip)
    jobs = []
    for n in (n1, n2):
        jobs.append(("runtime", n, runtime_argv(frames_dir, imu, n, config), None))
        jobs.append(("runtime_pty", n, runtime_argv(frames_dir, imu, n, config, serial=PTY),
                     None))
        timings = work / f"timings-{n}.json"
        jobs.append(("pipeline", n, driver_argv("pipeline", frames_dir, n, timings), timings))
        jobs.append(("peer", n, driver_argv("peer", frames_dir, n), None))
        from host.bench.count_drivers import STAGE_VARIANTS
        for kind in STAGE_VARIANTS:
            jobs.append((f"stage:{kind}", n, driver_argv(kind, frames_dir, n), None))
    return jobs


def count_clip(clip, n1: int = N1, n2: int = N2, jobs: int = 2, cache=CACHE,
               progress=None) -> dict:
    """Every count of one clip (see the module doc), ``jobs`` valgrind processes at a
    time."""
    say = progress or (lambda m: None)
    clip = Path(clip)
    frames_dir = frame_folder(clip, n2, cache)
    with tempfile.TemporaryDirectory(prefix="tacfoot-counts-") as tmp:
        work = Path(tmp)
        config = stall_config(work)
        todo = _jobs(clip, frames_dir, config, n1, n2, work)

        def one(i_job):
            i, (name, n, argv, extra) = i_job
            say(f"{clip.name}: {name}, {n} frames (callgrind)")
            try:
                r = run_counted(argv, work / f"callgrind.{i}.out")
            except (CountError, subprocess.TimeoutExpired) as exc:
                return name, n, argv, {"error": str(exc)}
            if extra is not None and Path(extra).is_file():
                r["timings"] = json.loads(Path(extra).read_text())
            return name, n, argv, r

        with ThreadPoolExecutor(max_workers=max(1, min(int(jobs), 2))) as pool:
            done = list(pool.map(one, enumerate(todo)))
    runs: dict = {}
    for name, n, argv, r in done:
        runs.setdefault(name, {})[n] = dict(r, command=_shown(argv))
    return summarise(clip, runs, n1, n2)


def _pair(runs: dict, name: str, n1: int, n2: int) -> dict:
    a, b = runs.get(name, {}).get(n1, {}), runs.get(name, {}).get(n2, {})
    err = a.get("error") or b.get("error")
    if err or "instructions" not in a or "instructions" not in b:
        return {"per_frame": None, "error": err or "not run"}
    pf = per_frame(a["instructions"], b["instructions"], n1, n2)
    return {"per_frame": pf, "count_n1": a["instructions"], "count_n2": b["instructions"],
            "seconds": [a["seconds"], b["seconds"]], "command_n2": b["command"],
            "pi4_ms": pi4_ms(pf)}


def summarise(clip: Path, runs: dict, n1: int, n2: int) -> dict:
    """Per-frame figures from the raw run counts ``runs[name][n]``."""
    from host.bench.count_drivers import STAGE_VARIANTS
    res = {"clip": clip.name, "n1": n1, "n2": n2,
           "figures": {t: _pair(runs, t, n1, n2) for t in TARGETS}}
    rt = runs.get("runtime", {}).get(n2, {})
    try:
        summary = json.loads(rt.get("stdout", "").strip().splitlines()[-1])
    except (ValueError, IndexError):
        summary = {}
    res["runtime_summary"] = {k: summary.get(k) for k in (
        "frames", "models", "models_fused", "faults", "fault_names", "fault_changes",
        "frames_dropped_behind", "frames_skipped", "tracker", "packets_sent", "packets_dropped") if k in summary}
    # the stages: differences of the cumulative variants, then what process() adds
    stages, prev = {}, 0.0
    cum = {k: _pair(runs, f"stage:{k}", n1, n2) for k in STAGE_VARIANTS}
    for k in STAGE_VARIANTS:
        pf = cum[k]["per_frame"]
        if pf is None or prev is None:
            stages[k] = {"per_frame": None, "error": cum[k].get("error") or "an earlier "
                                                                           "variant failed"}
            prev = None
            continue
        stages[k] = {"per_frame": pf - prev, "cumulative": pf}
        prev = pf
    total = res["figures"]["pipeline"]["per_frame"]
    stages["rest"] = ({"per_frame": total - prev} if total is not None and prev is not None
                      else {"per_frame": None, "error": "needs the pipeline and every variant"})
    res["stages"] = stages
    # the stage timers' split under callgrind (time shares between the two lengths)
    t1 = runs.get("pipeline", {}).get(n1, {}).get("timings", {}).get("timings_ms")
    t2 = runs.get("pipeline", {}).get(n2, {}).get("timings", {}).get("timings_ms")
    if t1 and t2:
        diff = {k: t2[k] - t1.get(k, 0.0) for k in t2 if k != "total"}
        whole = sum(diff.values())
        res["timer_split"] = {k: (v / whole if whole > 0 else None) for k, v in diff.items()}
    else:
        res["timer_split"] = None
    return res


# -- all clips -----------------------------------------------------------------------------

def valgrind_found() -> bool:
    return shutil.which("valgrind") is not None


def bench_counts(real_data, clips=DEFAULT_CLIPS, n1: int = N1, n2: int = N2, jobs: int = 2,
                 cache=CACHE, progress=None) -> dict:
    """The counts of each clip (a name in ``real_data/roboskin/`` or a path)."""
    if n1 < 1 or n2 <= n1:
        raise InputError(f"--n1/--n2: need 1 <= n1 < n2, got n1={n1}, n2={n2}")
    if not valgrind_found():
        raise CountError("valgrind not found (Debian: apt-get install valgrind)")
    paths = []
    for c in clips:
        p = Path(c)
        if not p.is_file():
            p = Path(real_data) / "roboskin" / c
        if not p.is_file():
            raise CountError(f"--clips: no such clip: {c} (looked in {Path(real_data) / 'roboskin'})")
        paths.append(p)
    from host.bench.costs import machine
    res = {"n1": n1, "n2": n2, "machine": machine(),
           "valgrind": subprocess.run(["valgrind", "--version"], capture_output=True,
                                      text=True).stdout.strip(),
           "pi4": {"instr_per_s": PI4_INSTR_PER_S, "range": list(PI4_INSTR_PER_S_RANGE),
                   "assumption": PI4_ASSUMPTION, "frame_budget_ms": FRAME_BUDGET_MS,
                   "fps": FRAME_FPS},
           "clips": [count_clip(p, n1, n2, jobs, cache, progress) for p in paths]}
    return res


def _m(v) -> str:
    return "n/a" if v is None else f"{v / 1e6:.2f}"


def format_counts(res: dict) -> str:
    """A text table: instructions per frame (millions) and the Pi 4 estimate."""
    lines = []
    for c in res["clips"]:
        lines.append(f"instructions per frame, {c['clip']}, callgrind, "
                     f"(count({c['n2']}) - count({c['n1']})) / {c['n2'] - c['n1']}")
        lines.append(f"  {'':<34}{'M instr':>9}{'Pi 4 ms':>9}  (budget at "
                     f"{FRAME_FPS:g} fps {FRAME_BUDGET_MS:.2f} ms)")
        rows = [("leg runtime end to end", c["figures"]["runtime"]),
                ("  the same, serial on a pty", c["figures"].get("runtime_pty",
                                                                 {"per_frame": None})),
                ("marker pipeline", c["figures"]["pipeline"])]
        rows += [(f"  {STAGE_NAMES[k]}", v) for k, v in c["stages"].items()]
        rows.append(("SimpleBlobDetector peer", c["figures"]["peer"]))
        for name, f in rows:
            pf = f["per_frame"]
            pi = "" if pf is None else f"{pi4_ms(pf):>9.2f}"
            err = f"  ({f['error']})" if pf is None and f.get("error") else ""
            lines.append(f"  {name:<34}{_m(pf):>9}{pi}{err}")
        if c.get("timer_split"):
            lines.append("  pipeline stage timers under callgrind: " + ", ".join(
                f"{k} {v:.0%}" for k, v in c["timer_split"].items() if v is not None))
    lines.append(f"Pi 4 estimate: {PI4_ASSUMPTION}")
    return "\n".join(lines)


def main(argv=None) -> int:
    import argparse
    ap = argparse.ArgumentParser(prog="python -m host.bench.counts",
                                 description="instructions per frame with callgrind")
    ap.add_argument("--real-data", default=os.environ.get("TACFOOT_REAL_DATA", "../shared/data"),
                    help="the real recordings folder (holds roboskin/)")
    ap.add_argument("--clips", default=",".join(DEFAULT_CLIPS),
                    help="comma-separated clips in REAL_DATA/roboskin/ or paths "
                         f"(e.g. {','.join(KNOWN_CLIPS)})")
    ap.add_argument("--n1", type=int, default=N1)
    ap.add_argument("--n2", type=int, default=N2)
    ap.add_argument("--jobs", type=int, default=2, help="valgrind processes at a time (1-2)")
    ap.add_argument("--out", help="also write the JSON result to this file")
    ap.add_argument("--json", action="store_true", help="print the JSON result")
    ap.add_argument("--skip-without-valgrind", action="store_true",
                    help="without valgrind, say so in one line and exit 0 (make bench)")
    a = ap.parse_args(argv)
    if not valgrind_found():
        msg = "instruction counts skipped: valgrind not found (Debian: apt-get install valgrind)"
        print(msg, file=sys.stderr)
        return 0 if a.skip_without_valgrind else 1
    try:
        res = bench_counts(a.real_data, [c for c in a.clips.split(",") if c], a.n1, a.n2,
                           a.jobs, progress=lambda m: print(f"counts: {m}", file=sys.stderr))
    except (CountError, ValueError) as exc:
        print(f"counts: {exc}", file=sys.stderr)
        return 1
    text = json.dumps(res, indent=1)
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(text)
    print(text if a.json else format_counts(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
