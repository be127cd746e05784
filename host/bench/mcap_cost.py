"""What the MCAP log and a live Foxglove viewer cost the leg runtime, on a real clip
(issue 22; run by ``make bench``)::

    python -m host.bench.mcap_cost --real-data DIR [--runs 5] [--out FILE.md] [--json]

It runs the real command, unpaced, in a child process with one compute thread
(as ``host bench runtime`` does)::

    python -m device.pi run --camera file://DIR/roboskin/concrete.avi
        --imu file://DIR/roboskin/concrete_gyro.npy --serial loop:// --frames 600 --json

three ways: as it is (``none``), with ``--mcap FILE`` (``mcap``), and with
``--foxglove 127.0.0.1:0`` and a WebSocket client in this process subscribed to every
channel and reading all it is sent (``viewer``). The three are interleaved, their
order rotated each round, ``--runs`` rounds. Each run gives its throughput (frames per
second of the loop, the status's ``throughput_fps``), its loop CPU per frame (p50,
p99: the loop thread's ``thread_time``, which a busy machine inflates less than wall
time), the log's own CPU per frame (``mcap_loop_cpu_s``: on the loop's thread, the
copying and queueing; ``mcap_sender_cpu_s``: the thread that makes the JPEG and hands
batches to the writer process; ``mcap_writer_cpu_s``: the writer's encoding,
compression and writing, in its own process, :mod:`device.pi.runtime.mcapproc`, or
in a thread with ``[mcap] writer = "thread"``), the child's whole CPU time and the
load average before and after.

The cost of a variant is one minus the median over rounds of its throughput over
the same round's ``none`` throughput: the goal is at most 10 % for ``mcap`` and for
``viewer`` (issue 32). On a machine busy with other work the throughput wanders by
more than these goals from run to run, so the table also gives the CPU figure: the
log's CPU per frame in the loop's process (loop thread and sender; and the writer
when it is a thread) as a share of the loop's. The Pi 4 column divides the throughput by
:data:`~host.bench.costs.PI4_FACTOR`, as the other tables do.
"""
from __future__ import annotations

import argparse
import asyncio
import json
import os
import re
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

import numpy as np

from host.bench.costs import PI4_FACTOR
from device.errors import TacfootError

#: the most each variant may cost of the runtime's throughput
GOALS = {"mcap": 0.10, "viewer": 0.10}
VARIANTS = ("none", "mcap", "viewer")
CLIP, GYRO = "roboskin/concrete.avi", "roboskin/concrete_gyro.npy"


class BenchError(TacfootError):
    """The benchmark cannot run (no clip, a child that failed); names the cause."""


def command(clip: str, gyro: str, frames: int) -> list[str]:
    """The runtime's command on a clip, unpaced, with its JSON status."""
    return [sys.executable, "-m", "device.pi", "run", "--camera", f"file://{clip}",
            "--imu", f"file://{gyro}", "--serial", "loop://", "--frames", str(frames),
            "--json"]


class Viewer:
    """A Foxglove WebSocket client on its own thread: subscribes to every channel
    advertised and reads all it is sent; counts the messages and the decisions."""

    def __init__(self, url: str):
        self.url = url
        self.messages = self.decisions = 0
        self.error: str | None = None
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        try:
            asyncio.run(self._client())
        except Exception as exc:               # the runtime ended: the socket closed
            if not self.messages:
                self.error = f"{type(exc).__name__}: {exc}"

    async def _client(self) -> None:
        import websockets
        async with websockets.connect(self.url, subprotocols=["foxglove.sdk.v1"],
                                      max_size=None) as ws:
            decision_sub = set()
            async for msg in ws:
                if isinstance(msg, str):
                    d = json.loads(msg)
                    if d.get("op") == "advertise":
                        subs = [{"id": c["id"], "channelId": c["id"]} for c in d["channels"]]
                        decision_sub |= {c["id"] for c in d["channels"]
                                         if c["topic"] == "/tacfoot/decision"}
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
                elif msg and msg[0] == 1:          # messageData: op, subscription id, ...
                    self.messages += 1
                    if int.from_bytes(msg[1:5], "little") in decision_sub:
                        self.decisions += 1


def run_once(variant: str, clip: str, gyro: str, frames: int, folder: Path) -> dict:
    """One run of the runtime as ``variant``; its status plus the figures above."""
    cmd = command(clip, gyro, frames)
    if variant == "mcap":
        cmd += ["--mcap", str(folder / "cost.mcap")]
    elif variant == "viewer":
        cmd += ["--foxglove", "127.0.0.1:0"]
    elif variant != "none":
        raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    load0 = os.getloadavg()[0]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env)
    viewer = None
    err = b""
    if variant == "viewer":
        line = proc.stderr.readline()
        while line and b"ws://" not in line:
            err += line
            line = proc.stderr.readline()
        m = re.search(rb"ws://([\d.]+):(\d+)", line)
        if m:
            viewer = Viewer(f"ws://{m[1].decode()}:{m[2].decode()}")
    out, rest = proc.communicate(timeout=600)
    err += rest
    if proc.returncode != 0:
        raise BenchError(f"{' '.join(cmd)} failed ({proc.returncode}): "
                         f"{err.decode(errors='replace').strip()[-500:]}")
    st = json.loads(out.decode().strip().splitlines()[-1])
    n = max(1, int(st["frames"]))
    res = {"variant": variant, "frames": st["frames"], "throughput_fps": st["throughput_fps"],
           "cpu_ms_per_frame_p50": st["cpu_ms_per_frame_p50"],
           "cpu_ms_per_frame_p99": st["cpu_ms_per_frame_p99"],
           "log_loop_cpu_ms_per_frame": 1e3 * st.get("mcap_loop_cpu_s", 0.0) / n,
           "log_sender_cpu_ms_per_frame": 1e3 * st.get("mcap_sender_cpu_s", 0.0) / n,
           "log_writer_cpu_ms_per_frame": 1e3 * st.get("mcap_writer_cpu_s", 0.0) / n,
           "mcap_writer": st.get("mcap_writer", "thread"),
           "mcap_dropped": st.get("mcap_dropped", 0),
           "mcap_messages_lost": st.get("mcap_messages_lost", 0),
           "load_avg_1min": [round(load0, 2), round(os.getloadavg()[0], 2)]}
    if viewer is not None:
        viewer.thread.join(10)
        if viewer.error:
            raise BenchError(f"the WebSocket client failed: {viewer.error}")
        res.update(viewer_messages=viewer.messages, viewer_frames=viewer.decisions)
    return res


def bench(real_data, runs: int = 5, frames: int = 600, variants=VARIANTS) -> dict:
    """``runs`` rounds of the variants, interleaved; the per-variant summary."""
    import resource
    root = Path(real_data)
    clip, gyro = root / CLIP, root / GYRO
    for p in (clip, gyro):
        if not p.is_file():
            raise BenchError(f"no such recording: {p} (give --real-data, the folder "
                             f"holding roboskin/)")
    if runs < 1:
        raise BenchError(f"--runs must be >= 1, got {runs}")
    if "viewer" in variants:
        try:
            import foxglove  # noqa: F401
            import websockets  # noqa: F401
        except ImportError as exc:
            variants = tuple(v for v in variants if v != "viewer")
            skipped = f"viewer: skipped ({exc.name} not installed; pip install .[viz] websockets)"
        else:
            skipped = None
    else:
        skipped = None
    rows: dict[str, list[dict]] = {v: [] for v in variants}
    with tempfile.TemporaryDirectory(prefix="tacfoot-mcap-cost-") as tmp:
        for r in range(runs):
            order = variants[r % len(variants):] + variants[:r % len(variants)]
            for v in order:
                c0 = resource.getrusage(resource.RUSAGE_CHILDREN)
                res = run_once(v, str(clip), str(gyro), frames, Path(tmp))
                c1 = resource.getrusage(resource.RUSAGE_CHILDREN)
                res["process_cpu_s"] = round(c1.ru_utime + c1.ru_stime
                                             - c0.ru_utime - c0.ru_stime, 3)
                res["round"] = r
                rows[v].append(res)
    out = {"command": " ".join(command(str(clip), str(gyro), frames)), "runs": runs,
           "pi4_factor": PI4_FACTOR, "cpu_count": os.cpu_count(),
           "load_avg": [round(x, 2) for x in os.getloadavg()], "skipped": skipped,
           "variants": {v: summarise(v, rows[v], rows["none"]) for v in variants},
           "raw": rows}
    return out


def summarise(variant: str, rows: list[dict], base: list[dict]) -> dict:
    """Medians over the runs; the cost against the same round's ``none`` run."""
    def med(key):
        xs = [r[key] for r in rows if r.get(key) is not None]
        return None if not xs else float(np.median(xs))
    fps = med("throughput_fps")
    s = {"throughput_fps": fps, "pi4_throughput_fps": None if fps is None else fps / PI4_FACTOR,
         "cpu_ms_per_frame_p50": med("cpu_ms_per_frame_p50"),
         "cpu_ms_per_frame_p99": med("cpu_ms_per_frame_p99"),
         "log_loop_cpu_ms_per_frame": med("log_loop_cpu_ms_per_frame"),
         "log_sender_cpu_ms_per_frame": med("log_sender_cpu_ms_per_frame"),
         "log_writer_cpu_ms_per_frame": med("log_writer_cpu_ms_per_frame"),
         "writer": rows[0].get("mcap_writer") if rows else None,
         "process_cpu_s": med("process_cpu_s"),
         "load_avg_1min": [min(r["load_avg_1min"][0] for r in rows),
                           max(r["load_avg_1min"][1] for r in rows)],
         "dropped": int(sum(r.get("mcap_dropped") or 0 for r in rows))}
    if "viewer_frames" in (rows[0] if rows else {}):
        s["viewer_frames_share"] = float(np.median([r["viewer_frames"] / max(1, r["frames"])
                                                    for r in rows]))
    by_round = {r["round"]: r["throughput_fps"] for r in base}
    ratios = [r["throughput_fps"] / by_round[r["round"]] for r in rows
              if by_round.get(r["round"]) and r.get("throughput_fps")]
    s["cost"] = None if variant == "none" or not ratios else 1.0 - float(np.median(ratios))
    loop = s["cpu_ms_per_frame_p50"]
    log = (s["log_loop_cpu_ms_per_frame"] or 0.0) + (s["log_sender_cpu_ms_per_frame"] or 0.0)
    if s["writer"] != "process":         # a writer thread shares the loop's process
        log += s["log_writer_cpu_ms_per_frame"] or 0.0
    s["cpu_share"] = None if variant == "none" or not loop else log / loop
    goal = GOALS.get(variant)
    s["goal"] = goal
    s["met"] = None if goal is None or s["cost"] is None else bool(s["cost"] <= goal)
    return s


def _f(x, fmt="{:.2f}") -> str:
    return "n/a" if x is None else fmt.format(x)


def table(res: dict) -> str:
    """The markdown table docs/BENCHMARKS.md takes, with the command and machine."""
    lines = ["| run | throughput fps (median) | Pi 4 est. fps | loop CPU ms/frame p50 / p99 | "
             "log CPU ms/frame: loop thread + sender + writer | log CPU in the loop's "
             "process / loop CPU | throughput "
             "cost | goal | met | load avg (1 min) |",
             "|---|---:|---:|---:|---:|---:|---:|---|---|---|"]
    names = {"none": "no log", "mcap": "--mcap FILE",
             "viewer": "--foxglove + a client reading"}
    for v, s in res["variants"].items():
        goal = "" if s["goal"] is None else f"cost <= {s['goal']:.0%}"
        met = "" if s["met"] is None else ("met" if s["met"] else "missed")
        extra = (f" ({s['viewer_frames_share']:.0%} of frames seen)"
                 if "viewer_frames_share" in s else "")
        lines.append(
            f"| {names[v]}{extra} | {_f(s['throughput_fps'], '{:.1f}')} | "
            f"{_f(s['pi4_throughput_fps'], '{:.1f}')} | {_f(s['cpu_ms_per_frame_p50'])} / "
            f"{_f(s['cpu_ms_per_frame_p99'])} | "
            + ("" if v == "none" else f"{_f(s['log_loop_cpu_ms_per_frame'], '{:.3f}')} + "
               f"{_f(s['log_sender_cpu_ms_per_frame'], '{:.3f}')} + "
               f"{_f(s['log_writer_cpu_ms_per_frame'], '{:.3f}')} ({s['writer']})")
            + f" | {_f(s['cpu_share'], '{:.1%}')} | {_f(s['cost'], '{:+.1%}')} | {goal} | "
              f"{met} | {s['load_avg_1min'][0]:.2f}-{s['load_avg_1min'][1]:.2f} |")
    lines += ["", f"Command: `{res['command']}` (+ `--mcap FILE`, or `--foxglove "
                  f"127.0.0.1:0` with a WebSocket client subscribed to every channel); "
                  f"{res['runs']} interleaved rounds, one compute thread, "
                  f"{res['cpu_count']} cores, load average now "
                  f"{', '.join(f'{x:.2f}' for x in res['load_avg'])}. Throughput cost: one "
                  f"minus the median of each round's throughput over that round's no-log "
                  f"run. Pi 4: throughput / {res['pi4_factor']:g}."]
    if res.get("skipped"):
        lines.append(f"Not measured: {res['skipped']}.")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m host.bench.mcap_cost",
                                 description="the MCAP log's and a live viewer's cost to "
                                             "the runtime on a real clip")
    ap.add_argument("--real-data", required=True, help="the folder holding roboskin/")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--frames", type=int, default=600)
    ap.add_argument("--out", help="write the markdown table here too")
    ap.add_argument("--json", action="store_true", help="print the JSON result")
    args = ap.parse_args(argv)
    try:
        res = bench(args.real_data, args.runs, args.frames)
    except BenchError as exc:
        print(f"host.bench.mcap_cost: error: {exc}", file=sys.stderr)
        return 2
    text = table(res)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(text)
    print(json.dumps(res) if args.json else text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
