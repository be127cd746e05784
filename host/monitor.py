"""``host monitor``: decode surface-link packets live (or from a capture) and show
the rate, the latest state, drops and CRC errors.

Sources: any pyserial URL or port (``/dev/ttyUSB0``, a pty path, ``loop://``,
``socket://host:port``) or a file of captured bytes (read to its end). On a TTY
one status line refreshes in place; ``--json`` writes one JSON line per decoded
message and a summary line at the end.
"""
from __future__ import annotations

import json
import sys
import time
from collections import deque
from pathlib import Path

from device.checks import serial_url
from device.pi import protocol as P
from device.sim.mpy.runner import MPY_LIB, cpython_path, mpy_unavailable, run_mpy
from device.errors import TacfootError


class LinkMonitor:
    """Decoder + statistics. ``feed(bytes)`` returns the decoded (frame, message)
    pairs; :meth:`snapshot` is the JSON-ready state."""

    def __init__(self, window: int = 50, max_frame: int = P.MAX_FRAME):
        self.decoder = P.FrameDecoder(max_frame, known_types=P.SURFACE_LINK_TYPES)
        self.counts = {cls.name: 0 for cls in P.MESSAGES.values()}
        self.latest: dict[str, dict] = {}
        self.short_payload = 0
        self._surface_t = deque(maxlen=max(2, int(window)))
        self._host_t = deque(maxlen=max(2, int(window)))

    def feed(self, data: bytes, host_s: float | None = None) -> list:
        out = []
        for f in self.decoder.feed(data):
            msg = P.decode_message(f)
            if msg is None:
                self.short_payload += 1
                continue
            name = msg.name
            self.counts[name] += 1
            d = P.message_dict(msg)
            d.update(seq=f.seq, t_ms=f.t_ms)
            self.latest[name] = d
            if f.msg_type == P.MsgType.SURFACE:
                self._surface_t.append(f.t_ms)
            if host_s is not None:
                self._host_t.append(host_s)
            out.append((f, d))
        return out

    @property
    def rate_hz(self) -> float | None:
        """SURFACE messages per second by the sender's clock (works on captures)."""
        t = self._surface_t
        if len(t) < 2:
            return None
        span_ms = (t[-1] - t[0]) & 0xFFFFFFFF
        return (len(t) - 1) * 1000.0 / span_ms if span_ms else None

    @property
    def host_rate_hz(self) -> float | None:
        """Good messages per second by this computer's clock (live sources)."""
        t = self._host_t
        if len(t) < 2 or t[-1] <= t[0]:
            return None
        return (len(t) - 1) / (t[-1] - t[0])

    def snapshot(self) -> dict:
        c = self.decoder.counters
        return {"rate_hz": _round(self.rate_hz), "host_rate_hz": _round(self.host_rate_hz),
                "messages": dict(self.counts), "frames_ok": c["frames_ok"],
                "drops": c["drops"], "crc_errors": c["crc_errors"], "too_long": c["too_long"],
                "malformed": c["malformed"], "newer_version": c["newer_version"],
                "unknown_type": c["unknown_type"], "short_payload": self.short_payload,
                "restarts": c["restarts"], "bytes": c["bytes_in"], "latest": self.latest}

    def status_line(self) -> str:
        s = self.latest.get("surface")
        rate = self.rate_hz
        parts = [f"surface {rate:6.1f} Hz" if rate else "surface    -- Hz"]
        if s:
            p = max(s["probs"]) if s["probs"] else 0.0
            touch = "contact" if s["contact"] else "no-contact"
            parts.append(f"{s['class_name']} p={p:.2f} {touch}"
                         f" slip={'YES' if s['slip'] else 'no'}({s['slip_conf']:.2f})"
                         f" shear {s['shear_px']:.2f}px@{s['shear_dir_deg']:.1f}deg"
                         f" load {s['load_n']:.2f}N pins {s['pins']}")
            if s["faults"]:
                parts.append("faults " + ",".join(s["faults_names"]))
        c = self.decoder.counters
        parts.append(f"ok {c['frames_ok']} drops {c['drops']} crc {c['crc_errors']} "
                     f"long {c['too_long']} bad {c['malformed']} newer {c['newer_version']} "
                     f"unknown {c['unknown_type']}")
        return " | ".join(parts)


def _round(v):
    return None if v is None else round(v, 3)


class MonitorError(TacfootError):
    """The source cannot be opened (one clear line for the CLI)."""


class _FileSource:
    is_file = True

    def __init__(self, path: Path):
        self.f = open(path, "rb")

    def read(self) -> bytes:
        return self.f.read(4096)

    def close(self):
        self.f.close()


class _SerialSource:
    is_file = False

    def __init__(self, port):
        self.port = port

    def read(self) -> bytes:
        # what is waiting, or else wait up to the port timeout (50 ms) for more
        n = getattr(self.port, "in_waiting", 0) or 0
        return self.port.read(min(n, 4096) if n > 1 else 256)

    def close(self):
        self.port.close()


def open_source(spec: str, baudrate: int = 921600):
    """A regular file is a capture; anything else goes to pyserial."""
    p = Path(spec)
    if p.is_file():
        return _FileSource(p)
    import serial
    serial_url(spec, error=MonitorError)
    try:
        port = serial.serial_for_url(spec, baudrate=baudrate, timeout=0.05)
    except (serial.SerialException, ValueError, OSError) as exc:
        raise MonitorError(f"cannot open {spec!r}: {exc}") from None
    return _SerialSource(port)


def run_monitor(source, as_json: bool = False, count: int | None = None,
                seconds: float | None = None, out=None, tty: bool | None = None,
                interval_s: float = 1.0, clock=time.monotonic) -> dict:
    """Read ``source`` (a spec string, an open pyserial port, or a source object)
    until EOF (files), ``count`` messages, ``seconds``, or Ctrl-C. Returns the
    final snapshot."""
    out = sys.stdout if out is None else out
    if isinstance(source, str):
        src = open_source(source)
    elif hasattr(source, "read") and hasattr(source, "is_file"):
        src = source
    else:
        src = _SerialSource(source)
    tty = out.isatty() if tty is None else tty
    mon = LinkMonitor()
    t0 = clock()
    last_draw = -1e9
    n_msgs = 0
    reason = "eof"
    try:
        while True:
            now = clock()
            if seconds is not None and now - t0 >= seconds:
                reason = "seconds"
                break
            data = src.read()
            if not data:
                if src.is_file:
                    break
                continue
            for f, d in mon.feed(data, None if src.is_file else now):
                n_msgs += 1
                if as_json:
                    out.write(json.dumps({"kind": "message", **d}) + "\n")
                if count is not None and n_msgs >= count:
                    break
            if count is not None and n_msgs >= count:
                reason = "count"
                break
            if not as_json and now - last_draw >= (0.1 if tty else interval_s) \
                    and not (src.is_file and not tty):
                _draw(out, mon.status_line(), tty)
                last_draw = now
    except KeyboardInterrupt:
        reason = "interrupted"
    finally:
        src.close()
    snap = mon.snapshot()
    snap["stopped_by"] = reason
    snap["messages_total"] = n_msgs
    if as_json:
        out.write(json.dumps({"kind": "summary", **snap}) + "\n")
    else:
        _draw(out, mon.status_line(), tty)
        if tty:
            out.write("\n")
    out.flush()
    return snap


def _draw(out, line: str, tty: bool):
    if tty:
        out.write("\r\x1b[2K" + line)
    else:
        out.write(line + "\n")
    out.flush()


# -- benchmark: host monitor --bench ---------------------------------------------------

_MPY_BENCH = """
import time, tflink, surface_link, machine
import mpy_args
w = bytes.fromhex(mpy_args.ARGV[1]) if hasattr(bytes, "fromhex") else None
n = int(mpy_args.ARGV[2])
u = machine.UART(0)
link = surface_link.SurfaceLink(u, clock=lambda: 0)
# ticks_us on the wasm port moves in whole ms: time batches of 500 packets
buf = bytearray(w * 500)
best = None
for r in range(max(1, n // 500)):
    t0 = time.ticks_us()
    link.feed(buf, len(buf))
    dt = time.ticks_diff(time.ticks_us(), t0)
    best = dt if best is None or dt < best else best
def ref_loop(n):
    x = 0
    for i in range(n):
        x = i * 3
    return x
ref = None
for r in range(3):
    t0 = time.ticks_us()
    ref_loop(200000)
    dt = time.ticks_diff(time.ticks_us(), t0)
    ref = dt if ref is None or dt < ref else ref
print(best / 500, ref / 200000, link.frames_ok)
"""


def _ref_loop(n):
    """The reference 'simple loop iteration' (the same code runs on MicroPython)."""
    x = 0
    for i in range(n):
        x = i * 3
    return x


def _count_opcodes(wire: bytes) -> dict:
    """CPython bytecodes executed to decode one packet with the MicroPython code
    (tflink.Decoder.feed + SurfaceLink's SURFACE parse), counted with a tracer."""
    cpython_path()
    import surface_link

    class _U:
        def readinto(self, b):
            return None

    link = surface_link.SurfaceLink(_U(), clock=lambda: 0)
    link.feed(wire, len(wire))                     # warm up
    counts = {"ops": 0, "lines": 0}

    def tracer(frame, event, arg):
        frame.f_trace_opcodes = True
        if event == "opcode":
            counts["ops"] += 1
        elif event == "line":
            counts["lines"] += 1
        return tracer

    sys.settrace(tracer)
    try:
        link.feed(wire, len(wire))
    finally:
        sys.settrace(None)
    assert link.frames_ok == 2
    packet = counts["ops"]
    counts["ops"] = 0
    sys.settrace(tracer)
    try:
        _ref_loop(1000)
    finally:
        sys.settrace(None)
    return {"ops": packet, "ref_ops_per_iteration": round(counts["ops"] / 1000, 2)}


def bench_link(repeats: int = 20000, mpy_packets: int = 5000) -> dict:
    """SURFACE size, CPython encode/decode per packet, the MicroPython decoder on the
    WebAssembly port (if Node and the package are installed), and an RP2040-class
    estimate from the bytecode count."""
    import statistics

    s = P.Surface(1, (0.02, 0.9, 0.05, 0.03), True, False, 0.05, 45.0, 3.21, 25.5, 331, 0, 2)
    wire = s.encode(1, 1000)
    enc, dec = [], []
    d = P.FrameDecoder()
    clock = time.perf_counter_ns
    for i in range(repeats):
        t0 = clock()
        w = s.encode(i, i)
        t1 = clock()
        (f,) = d.feed(w)
        P.decode_message(f)
        t2 = clock()
        enc.append((t1 - t0) / 1000)
        dec.append((t2 - t1) / 1000)
    q = lambda v: {"median_us": round(statistics.median(v), 2),  # noqa: E731
                   "p99_us": round(sorted(v)[int(0.99 * (len(v) - 1))], 2)}
    ops = _count_opcodes(wire)
    res = {"surface_wire_bytes": len(wire), "surface_payload_bytes": len(s.pack()),
           "cpython": {"encode": q(enc), "decode": q(dec), "packets": repeats},
           "bytecodes_per_packet": ops["ops"],
           "bytecodes_per_ref_iteration": ops["ref_ops_per_iteration"]}
    iters = ops["ops"] / ops["ref_ops_per_iteration"]
    res.update(ref_iterations_per_packet=round(iters, 1),
               rp2040_estimate_us={"at_1us_per_iteration": round(iters),
                                   "at_2us_per_iteration": round(2 * iters)},
               goal_us=1000)
    if mpy_unavailable() is None:
        r = run_mpy(_MPY_BENCH, libs=[MPY_LIB], args=[wire.hex(), str(mpy_packets)], timeout=120)
        if r.returncode == 0:
            us, ref_us, ok = r.stdout.split()
            res["micropython_wasm_us_per_packet"] = float(us)
            res["micropython_wasm_us_per_ref_iteration"] = float(ref_us)
            # the same ratio measured rather than counted: packet time / iteration time
            res["wasm_ref_iterations_per_packet"] = round(float(us) / float(ref_us), 1)
        else:
            res["micropython_wasm_error"] = r.stderr.strip().splitlines()[-1:]
    return res


def format_bench(r: dict) -> str:
    lines = [f"SURFACE on the wire: {r['surface_wire_bytes']} bytes "
             f"(payload {r['surface_payload_bytes']}; limit 32)",
             f"CPython encode: median {r['cpython']['encode']['median_us']} us, "
             f"p99 {r['cpython']['encode']['p99_us']} us",
             f"CPython decode: median {r['cpython']['decode']['median_us']} us, "
             f"p99 {r['cpython']['decode']['p99_us']} us"]
    if "micropython_wasm_us_per_packet" in r:
        lines.append(f"MicroPython (wasm, Node) decode: {r['micropython_wasm_us_per_packet']} "
                     f"us per packet; reference loop iteration "
                     f"{r['micropython_wasm_us_per_ref_iteration']} us, so a packet costs "
                     f"{r['wasm_ref_iterations_per_packet']} iterations")
    e = r["rp2040_estimate_us"]
    lines.append(f"bytecodes per packet: {r['bytecodes_per_packet']} = "
                 f"{r['ref_iterations_per_packet']} reference loop iterations "
                 f"({r['bytecodes_per_ref_iteration']} bytecodes each) -> RP2040 at 1-2 us per "
                 f"iteration: {e['at_1us_per_iteration']}-{e['at_2us_per_iteration']} us "
                 f"(goal {r['goal_us']} us)")
    return "\n".join(lines)
