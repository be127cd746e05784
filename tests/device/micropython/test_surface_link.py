"""The surface link consumer (device/micropython/tflink.py, surface_link.py,
gait_example.py) on REAL MicroPython (the WebAssembly port under Node) and on
CPython: the same scripts run on both and must give the same answers.

Covers: the golden vectors (decode, and the MCU's own GAIT/COMMAND encoder against
the Pi's bytes), the stream vectors' counters, 100k fuzzed streams per interpreter,
a long session with a link outage (stale -> safe default), no allocation per byte,
and the gait example's preset choice.
"""
from __future__ import annotations
from tests import REPO_ROOT

import contextlib
import io
import json
import random
import sys
import types
from pathlib import Path

from tests.mpyrun import MPY_LIB, cpython_path, requires_mpy, run_mpy

ROOT = REPO_ROOT
VECTORS = REPO_ROOT / "tests" / "device" / "pi" / "protocol_vectors.json"
sys.path.insert(0, str(ROOT))

from device.pi import protocol as P  # noqa: E402

FUZZ_STREAMS = 100_000


def run_cpython(src: str, args=()) -> str:
    """Run a MicroPython test script under CPython the way run.mjs runs it."""
    cpython_path()
    sys.modules["mpy_args"] = types.SimpleNamespace(ARGV=["script", *map(str, args)])
    out = io.StringIO()
    try:
        with contextlib.redirect_stdout(out):
            exec(compile(src, "<mpy-script>", "exec"), {"__name__": "__main__"})
    finally:
        del sys.modules["mpy_args"]
    return out.getvalue()


def run_both(src: str, args=(), puts=(), timeout=120):
    """stdout of ``src`` on MicroPython and on CPython (paths in args are the
    MicroPython paths of ``puts``; CPython gets the host paths)."""
    host_args = [dict((m, h) for h, m in puts).get(a, a) for a in map(str, args)]
    cp = run_cpython(src, host_args)
    res = run_mpy(src, libs=[MPY_LIB], puts=puts, args=args, timeout=timeout)
    assert res.returncode == 0, res.stderr[-3000:]
    return res.stdout, cp


# -- golden vectors -------------------------------------------------------------------

GOLDEN = r"""
import json, mpy_args, machine
from binascii import hexlify, unhexlify
import tflink, surface_link as SL

doc = json.load(open(mpy_args.ARGV[1]))
out = {"crc": tflink.crc16(b"123456789", 9), "messages": [], "encoded": {}, "streams": []}

def num(v):
    return float(v) if isinstance(v, str) else v

for v in doc["messages"]:
    u = machine.UART(0, 921600)
    link = SL.SurfaceLink(u, stale_ms=100, clock=lambda: 7)
    frames = []
    old = link.decoder.on_frame
    def grab(d, frames=frames, old=old):
        frames.append([d.msg_type, d.seq, d.t_ms, hexlify(bytes(d.payload)).decode()])
        old(d)
    link.decoder.on_frame = grab
    u.feed(unhexlify(v["wire_hex"]))
    n = link.poll()
    s = link.state()
    st = {"class_id": s.class_id, "probs_u8": list(s.probs_u8), "contact": s.contact,
          "slip": s.slip, "slip_conf_u8": s.slip_conf_u8, "texture_id": s.texture_id,
          "shear_dir_deg_x100": s.shear_dir_deg_x100, "shear_px_x100": s.shear_px_x100,
          "load_n_x100": s.load_n_x100, "pins": s.pins, "faults": s.faults,
          "valid": s.valid, "stale": s.stale, "age_ms": s.age_ms,
          "imu": list(link.imu), "imu_samples": link.imu_samples,
          "pi_uptime_s": link.pi_uptime_s, "pi_rate_fps_x10": link.pi_rate_fps_x10,
          "fault_bits": link.fault_bits, "fault_raised": link.fault_raised,
          "pins_lost": link.pins_lost, "unknown_type": link.unknown_type}
    out["messages"].append({"name": v["name"], "n": n, "frames": frames, "state": st})
    # the MCU's own encoder must give the Pi's bytes for what the MCU sends
    g = v["given"]
    if v["type"] in ("gait", "command"):
        t = v["t_ms"]
        tx = SL.SurfaceLink(u, clock=lambda t=t: t)
        tx.tx_seq = v["seq"]
        u.take()
        if v["type"] == "gait":
            tx.send_gait(g["phase"], num(g["load_n"]), [num(x) for x in g["vel_mm_s"]])
        else:
            tx.send_command(g["command"], g["arg"])
        out["encoded"][v["name"]] = hexlify(u.take()).decode()

for v in doc["streams"]:
    got = []
    d = tflink.Decoder(64, lambda d: got.append(
        [d.msg_type, d.seq, d.t_ms, hexlify(bytes(d.payload)).decode()]))
    w = unhexlify(v["wire_hex"])
    b = bytearray(w)
    # feed in uneven chunks: a frame split across reads must still decode
    i = 0
    k = 1
    while i < len(b):
        chunk = b[i:i + k]
        d.feed(chunk, len(chunk))
        i += k
        k = k % 7 + 1
    out["streams"].append({"name": v["name"], "frames": got, "counters": {
        "crc_errors": d.crc_errors, "too_long": d.too_long, "malformed": d.malformed,
        "newer_version": d.newer_version}})
print(json.dumps(out))
"""


def _check_golden(out: dict):
    doc = json.loads(VECTORS.read_text())
    assert out["crc"] == 0x29B1
    by_name = {m["name"]: m for m in out["messages"]}
    for v in doc["messages"]:
        got = by_name[v["name"]]
        assert got["n"] == 1, v["name"]
        assert got["frames"] == [[v["msg_type"], v["seq"], v["t_ms"], v["payload_hex"]]]
        st, raw = got["state"], v["raw"]
        if v["type"] == "surface":
            for k, val in raw.items():
                assert st[k] == val, (v["name"], k, st[k], val)
            assert st["valid"] and not st["stale"] and st["age_ms"] == 0
        elif v["type"] == "imu_summary":
            assert st["imu"] == raw["imu"] and st["imu_samples"] == raw["imu_samples"]
        elif v["type"] == "heartbeat":
            for k in ("pi_uptime_s", "pi_rate_fps_x10", "fault_bits"):
                assert st[k] == raw[k], (v["name"], k)
        elif v["type"] == "fault":
            for k in ("fault_bits", "fault_raised", "pins_lost"):
                assert st[k] == raw[k], (v["name"], k)
        if v["type"] != "surface":
            assert not st["valid"] and st["stale"], "only SURFACE makes a state"
        if v["type"] in ("gait", "command"):
            assert out["encoded"][v["name"]] == v["wire_hex"], v["name"]
    assert len(out["encoded"]) == sum(v["type"] in ("gait", "command") for v in doc["messages"])
    sb = {s["name"]: s for s in out["streams"]}
    for v in doc["streams"]:
        exp = [[e["msg_type"], e["seq"], e["t_ms"], e["payload_hex"]] for e in v["expect"]]
        assert sb[v["name"]]["frames"] == exp, v["name"]
        assert sb[v["name"]]["counters"] == v["counters"], v["name"]


@requires_mpy
def test_golden_vectors_decode_and_encode_identically_on_micropython_and_cpython():
    mp, cp = run_both(GOLDEN, args=["/vectors.json"], puts=[(str(VECTORS), "/vectors.json")])
    mp_out, cp_out = json.loads(mp), json.loads(cp)
    _check_golden(mp_out)
    _check_golden(cp_out)
    assert mp_out == cp_out


def test_golden_vectors_on_cpython_alone():
    """The same checks without Node, so a machine without it still tests the logic."""
    _check_golden(json.loads(run_cpython(GOLDEN, [str(VECTORS)])))


def test_unknown_type_is_counted_by_the_link_not_fatal():
    cpython_path()
    import machine
    import surface_link as SL
    u = machine.UART(0, 921600)
    link = SL.SurfaceLink(u, clock=lambda: 0)
    hard = json.loads(VECTORS.read_text())["messages"][0]
    u.feed(P.encode_frame(0x0E, b"\x01\x02", 1, 0) + bytes.fromhex(hard["wire_hex"]))
    assert link.poll() == 2
    assert link.unknown_type == 1
    assert link.state().class_id == hard["raw"]["class_id"]



def test_a_short_payload_is_counted_and_changes_nothing():
    cpython_path()
    import machine
    import surface_link as SL
    u = machine.UART(0, 921600)
    link = SL.SurfaceLink(u, clock=lambda: 0)
    fault = P.Fault(faults=P.FAULT_CAMERA, raised=P.FAULT_CAMERA, pins_lost=3).pack()
    for msg_type, payload in ((P.MSG_SURFACE, bytes(17)), (P.MSG_IMU_SUMMARY, bytes(16)),
                              (P.MSG_HEARTBEAT, bytes(10)), (P.MSG_FAULT, fault[:5])):
        u.feed(P.encode_frame(msg_type, payload, 1, 0))
    assert link.poll() == 4
    assert (link.short_payload, link.unknown_type) == (4, 0)
    assert not link.state().valid and link.heartbeats == 0 and link.fault_bits == 0
    u.feed(P.encode_frame(P.MSG_FAULT, fault, 2, 0))
    assert link.poll() == 1 and (link.fault_bits, link.pins_lost) == (P.FAULT_CAMERA, 3)


# -- fuzzing ------------------------------------------------------------------------

FUZZ = r"""
import json, mpy_args
import tflink

N = int(mpy_args.ARGV[1])
seed = int(mpy_args.ARGV[2])

# xorshift32: the same streams on MicroPython and CPython
_s = [seed & 0xFFFFFFFF or 1]
def rnd(n):
    x = _s[0]
    x ^= (x << 13) & 0xFFFFFFFF
    x ^= x >> 17
    x ^= (x << 5) & 0xFFFFFFFF
    _s[0] = x
    return x % n

enc = tflink.Encoder()
# pools of random bytes; streams take slices at random offsets (cheap on MicroPython)
POOL = 4096
noise = bytearray(POOL + 64)          # zeros frequent: line noise
nonzero = bytearray(POOL + 64)        # no zeros: garbage that hides the next delimiter
for j in range(POOL + 64):
    noise[j] = 0 if rnd(8) == 0 else rnd(256)
    nonzero[j] = rnd(255) + 1
frames = []          # the good frames of the current stream: (type, seq, t_ms, payload)
got = []

def on_frame(d):
    got.append((d.msg_type, d.seq, d.t_ms, bytes(d.payload)))

dec = tflink.Decoder(64, on_frame)
try:                   # CPython: the Pi's decoder must agree frame for frame
    from device.pi.protocol import FrameDecoder
    pi = FrameDecoder(64)
except ImportError:    # MicroPython
    pi = None

def good():
    n = rnd(13)
    o = rnd(POOL)
    pay = noise[o:o + n]
    t = rnd(0x40) + 1
    x = rnd(0x40000000)
    s = x & 0xFFFF
    ms = x * 4 + rnd(4)
    frames.append((t, s, ms, bytes(pay)))
    return bytearray(enc.frame(t, s, ms, pay, n))

stats = {"streams": 0, "bytes": 0, "accepted": 0, "corrupt_accepted": 0,
         "missed_resync": 0, "exceptions": 0, "kinds": [0, 0, 0, 0]}
for i in range(N):
    kind = rnd(4)
    stats["kinds"][kind] += 1
    del frames[:]
    del got[:]
    must = None
    if kind == 0:          # garbage with no delimiter, then A, B: B must decode
        o = rnd(POOL)
        g = nonzero[o:o + rnd(16) + 1]
        a = good()
        b = good()
        stream = g + a + b
        must = frames[1]
    elif kind == 1:        # A with 1-3 flipped bits (not its delimiter), then B: B must decode
        a = good()
        for j in range(rnd(3) + 1):
            k = rnd(len(a) - 1)
            a[k] ^= 1 << rnd(8)
        stream = a + good()
        must = frames[1]
    elif kind == 2:        # A with a byte dropped, inserted or a slice repeated, then B
        a = good()
        k = rnd(len(a) - 1)
        op = rnd(3)
        if op == 0:
            a = a[:k] + a[k + 1:]
        elif op == 1:
            a = a[:k] + bytearray([rnd(256)]) + a[k:]
        else:
            a = a[:k] + a[rnd(len(a)):]
        stream = a + good()
        must = frames[1]
    else:                  # line noise (zeros frequent), then a delimiter, then A
        o = rnd(POOL)
        g = noise[o:o + rnd(32) + 1]
        stream = g + bytearray(1) + good()
        must = frames[0]
    stats["streams"] += 1
    stats["bytes"] += len(stream)
    try:
        # two uneven reads, as a UART delivers them
        cut = rnd(len(stream) + 1)
        dec.feed(stream[:cut], cut)
        rest = stream[cut:]
        dec.feed(rest, len(rest))
    except Exception as e:
        stats["exceptions"] += 1
        dec.reset()
        continue
    if pi is not None:
        pf = [(f.msg_type, f.seq, f.t_ms, f.payload) for f in pi.feed(stream)]
        if pf != got:
            stats["pi_disagrees"] = stats.get("pi_disagrees", 0) + 1
    for f in got:
        stats["accepted"] += 1
        if f not in frames:
            stats["corrupt_accepted"] += 1
    if must not in got:
        stats["missed_resync"] += 1
for k in ("frames_ok", "crc_errors", "too_long", "malformed", "newer_version"):
    stats[k] = getattr(dec, k)
if pi is not None:
    stats["pi_counters"] = dict((k, getattr(pi, k)) for k in (
        "frames_ok", "crc_errors", "too_long", "malformed", "newer_version"))
print(json.dumps(stats))
"""


def _check_fuzz(stats: dict, n: int):
    assert stats["streams"] == n
    assert stats["exceptions"] == 0
    assert stats["corrupt_accepted"] == 0, stats
    assert stats["missed_resync"] == 0, stats
    # every kind ran, and the decoder saw (and counted) each kind of damage
    assert min(stats["kinds"]) > n // 5
    assert stats["crc_errors"] > n // 20 and stats["malformed"] > n // 20
    assert stats["accepted"] >= n


@requires_mpy
def test_fuzz_100k_streams_on_micropython():
    res = run_mpy(FUZZ, libs=[MPY_LIB], args=[FUZZ_STREAMS, 12345], timeout=120)
    assert res.returncode == 0, res.stderr[-3000:]
    _check_fuzz(json.loads(res.stdout), FUZZ_STREAMS)


def test_fuzz_100k_streams_on_cpython_same_streams():
    """The same 100k streams as on MicroPython (same PRNG and seed)."""
    stats = json.loads(run_cpython(FUZZ, [FUZZ_STREAMS, 12345]))
    _check_fuzz(stats, FUZZ_STREAMS)
    # the Pi's decoder (device/pi/protocol.py) saw the same streams: same frames
    # accepted, same damage counted
    assert stats.get("pi_disagrees", 0) == 0
    assert stats["pi_counters"] == {k: stats[k] for k in stats["pi_counters"]}


# -- a long session ----------------------------------------------------------------

TICK_MS = 10
OUTAGE = (60_000, 60_500)       # the Pi sends nothing in [start, end)
STALE_MS = 150


def make_session(path: Path, seconds: int = 120, seed: int = 7) -> dict:
    """A session at 100 SURFACE/s with 1 Hz heartbeats, a fault, a link outage and
    line noise on every 997th SURFACE. Written as per-tick chunks: u16 length +
    bytes. Returns what a perfect consumer must report."""
    rng = random.Random(seed)
    seq = 0
    chunks = []
    sent = corrupted = 0
    last = None
    classes = [1, 2, 3, 1]
    for t in range(0, seconds * 1000, TICK_MS):
        wire = b""
        if not OUTAGE[0] <= t < OUTAGE[1]:
            cid = classes[(t // 7000) % 4]
            probs = [0.05] * 4
            probs[cid] = 0.85
            s = P.Surface(cid, probs, True, cid == 3, 0.6 if cid == 3 else 0.0,
                          (t / 100) % 360, 1.0 + (t % 1000) / 100, 20 + (t % 500) / 50,
                          331 - (t % 3), 0, 255)
            w = s.encode(seq, t)
            seq = (seq + 1) & 0xFFFF
            sent += 1
            if sent % 997 == 0:
                k = len(w) // 2      # noise inside the frame, no zeros: the frame is lost
                w = w[:k] + bytes(rng.randrange(1, 256) for _ in range(5)) + w[k:]
                corrupted += 1
            else:
                last = (seq - 1) & 0xFFFF, t, s
            wire += w
            if t % 1000 == 0:
                wire += P.Heartbeat(t // 1000, 100.0, 0, 50, 0).encode(seq, t)
                seq = (seq + 1) & 0xFFFF
            if t == 30_000:
                wire += P.Fault(P.FAULT_PINS_LOST, P.FAULT_PINS_LOST, 9).encode(seq, t)
                seq = (seq + 1) & 0xFFFF
        chunks.append(len(wire).to_bytes(2, "little") + wire)
    path.write_bytes(b"".join(chunks))
    lseq, lt, ls = last
    raw = P.Surface.unpack(ls.pack())
    return {"ticks": len(chunks), "surfaces_ok": sent - corrupted, "drops": corrupted,
            "heartbeats": seconds - (1 if OUTAGE[0] % 1000 == 0 else 0),
            "stale_ticks": (OUTAGE[1] - OUTAGE[0] - STALE_MS) // TICK_MS,
            "last_seq": lseq, "last_t_ms": lt, "last_class": raw.class_id,
            "last_pins": raw.pins}


SESSION = r"""
import json, gc, mpy_args, machine
import surface_link as SL

now = [0]
u = machine.UART(0, 921600, rxbuf=512)
link = SL.SurfaceLink(u, stale_ms=int(mpy_args.ARGV[2]), clock=lambda: now[0])
f = open(mpy_args.ARGV[1], "rb")
hdr = bytearray(2)
stale_ticks = 0
surfaces = 0
last_seq = -1
ticks = 0
max_age = 0
while True:
    if f.readinto(hdr) != 2:
        break
    n = hdr[0] | (hdr[1] << 8)
    if n:
        u.feed(f.read(n))
    link.poll()
    s = link.state()
    if s.stale:
        stale_ticks += 1
    elif s.age_ms > max_age:
        max_age = s.age_ms
    if s.valid and s.seq != last_seq:
        surfaces += 1
        last_seq = s.seq
    ticks += 1
    now[0] += 10
gc.collect()
print(json.dumps({"ticks": ticks, "surfaces": surfaces, "stale_ticks": stale_ticks,
    "frames_ok": link.frames_ok, "crc_errors": link.crc_errors, "malformed": link.malformed,
    "too_long": link.too_long, "drops": link.drops, "heartbeats": link.heartbeats,
    "fault_raised": link.fault_raised, "pins_lost": link.pins_lost,
    "last_seq": s.seq, "last_t_ms": s.t_ms, "last_class": s.class_id, "last_pins": s.pins,
    "max_fresh_age_ms": max_age, "overrun": u.overrun}))
"""


def _check_session(out: dict, exp: dict):
    assert out["ticks"] == exp["ticks"]
    assert out["surfaces"] == exp["surfaces_ok"]
    assert out["drops"] == exp["drops"]
    assert out["crc_errors"] + out["malformed"] == exp["drops"]
    assert out["frames_ok"] == exp["surfaces_ok"] + exp["heartbeats"] + 1
    assert out["heartbeats"] == exp["heartbeats"]
    assert out["stale_ticks"] == exp["stale_ticks"]
    assert out["max_fresh_age_ms"] <= STALE_MS
    assert (out["last_seq"], out["last_t_ms"], out["last_class"], out["last_pins"]) == (
        exp["last_seq"], exp["last_t_ms"], exp["last_class"], exp["last_pins"])
    assert out["fault_raised"] == P.FAULT_PINS_LOST and out["pins_lost"] == 9
    assert out["overrun"] == 0 and out["too_long"] == 0


@requires_mpy
def test_long_session_two_minutes_with_outage_and_noise(tmp_path):
    path = tmp_path / "session.bin"
    exp = make_session(path)
    mp, cp = run_both(SESSION, args=["/session.bin", STALE_MS], puts=[(str(path), "/session.bin")])
    mp_out, cp_out = json.loads(mp), json.loads(cp)
    _check_session(mp_out, exp)
    _check_session(cp_out, exp)
    assert mp_out == cp_out


ALLOC = r"""
import gc, json, tflink, machine, surface_link
enc = tflink.Encoder()
p = bytearray(range(1, 19))
w = bytes(enc.frame(1, 5, 1000, p, 18))
frames = bytearray(w * 50)
garbage = bytearray(b"\x55\x02\x13" * 700 + b"\x00")
d = tflink.Decoder()
d.feed(frames, len(frames))            # warm up
gc.collect()
gc.disable()
a0 = gc.mem_alloc()
d.feed(garbage, len(garbage))
a1 = gc.mem_alloc()
d.feed(frames, len(frames))
a2 = gc.mem_alloc()
# the whole consumer: decode + SURFACE parse into the state object
link = surface_link.SurfaceLink(machine.UART(0), clock=lambda: 0)
s = bytes(enc.frame(1, 6, 1000, bytearray(18), 18))
sframes = bytearray(s * 50)
link.feed(sframes, len(sframes))
a3 = gc.mem_alloc()
link.feed(sframes, len(sframes))
link.state()
a4 = gc.mem_alloc()
gc.enable()
print(json.dumps({"garbage_bytes": len(garbage), "alloc_garbage": a1 - a0,
                  "frames": 50, "frame_bytes": len(frames), "alloc_frames": a2 - a1,
                  "alloc_link_frames": a4 - a3, "link_ok": link.frames_ok,
                  "ok": d.frames_ok}))
"""


@requires_mpy
def test_decoder_allocates_nothing_per_byte_on_micropython():
    res = run_mpy(ALLOC, libs=[MPY_LIB], check=True)
    out = json.loads(res.stdout)
    assert out["ok"] == 100
    assert out["alloc_garbage"] == 0, out          # 2100 bytes of noise: no allocation at all
    # per valid frame only the payload memoryview (a few words), not per byte
    assert out["alloc_frames"] <= 32 * out["frames"], out
    assert out["link_ok"] == 100
    assert out["alloc_link_frames"] <= 32 * out["frames"], out


# -- the gait example -----------------------------------------------------------------

GAIT = r"""
import json, mpy_args, machine
from binascii import hexlify, unhexlify
import surface_link as SL
import gait_example as G

now = [0]
u = machine.UART(0, 921600, rxbuf=512)
link = SL.SurfaceLink(u, stale_ms=150, clock=lambda: now[0])
loop = G.GaitLoop(link, context_ms=20, clock=lambda: now[0])
plan = json.loads(mpy_args.ARGV[1])     # [[until_ms, wire_hex or ""], ...]
presets = []
tx = []
k = 0
while now[0] < plan[-1][0]:
    while plan[k][0] <= now[0]:
        k += 1
    if plan[k][1] and now[0] % 20 == 0:
        u.feed(unhexlify(plan[k][1]))
    presets.append(loop.step())
    tx.append(hexlify(u.take()).decode())
    now[0] += 10
print(json.dumps({"presets": presets, "tx": "".join(tx), "switches": loop.switches}))
"""


def _gait_plan():
    vec = {v["name"]: v["wire_hex"] for v in json.loads(VECTORS.read_text())["messages"]}
    # the same SURFACE bytes repeated are fine for the consumer (age is local)
    return [[2000, vec["surface_hard"]], [4000, vec["surface_slippery_slip"]],
            [6000, vec["surface_soft"]], [7000, ""], [8000, vec["surface_hard"]]]


def _check_gait(out: dict):
    pre = out["presets"]
    at = lambda ms: pre[ms // 10]  # noqa: E731
    assert at(0) == "safe"                       # start safe; switch at the step's end
    assert at(G_PERIOD["safe"]) == "hard"
    assert at(1990) == "hard"
    # a change of surface is taken at the next step boundary (<= one period)
    assert at(2000 + G_PERIOD["hard"]) == "slippery"
    assert at(3990) == "slippery"
    assert at(4000 + G_PERIOD["slippery"]) == "soft"
    # the link goes quiet at 6000: safe within stale_ms (+ one tick)
    first_safe = next(i for i in range(600, len(pre)) if pre[i] == "safe") * 10
    assert 6000 + 150 - 20 < first_safe <= 6000 + 150 + 20
    assert at(6990) == "safe"
    assert at(7000 + G_PERIOD["safe"]) == "hard"
    # GAIT context went back every 20 ms, and decodes with the Pi's decoder
    msgs = [P.decode_message(f) for f in P.FrameDecoder().feed(bytes.fromhex(out["tx"]))]
    assert len(msgs) == len(pre) // 2 and all(isinstance(m, P.Gait) for m in msgs)
    stance = [m for m in msgs if m.phase == P.PHASE_STANCE]
    swing = [m for m in msgs if m.phase == P.PHASE_SWING]
    assert stance and swing
    assert all(m.load_n == 45.0 and m.vel_mm_s[0] < 0 for m in stance)
    assert all(m.load_n == 0.0 and m.vel_mm_s[0] > 0 for m in swing)
    assert all(m.flags == 0 for m in msgs)
    # slippery steps are shorter and slower: smaller stance speed than on hard ground
    hard_v = min(m.vel_mm_s[0] for m in msgs[:90] if m.phase == P.PHASE_STANCE)
    wet_v = min(m.vel_mm_s[0] for m in msgs[110:190] if m.phase == P.PHASE_STANCE)
    assert abs(wet_v) < abs(hard_v)


def _gait_periods():
    cpython_path()
    import gait_example
    return {k: v[1] for k, v in gait_example.PRESETS.items()}


G_PERIOD = {}


@requires_mpy
def test_gait_example_picks_presets_and_sends_gait_context():
    G_PERIOD.update(_gait_periods())
    mp, cp = run_both(GAIT, args=[json.dumps(_gait_plan())])
    assert json.loads(mp) == json.loads(cp)
    _check_gait(json.loads(mp))


def test_gait_example_presets_match_the_issue():
    cpython_path()
    import gait_example as G
    hard, soft, wet, safe = (G.PRESETS[k] for k in ("hard", "soft", "slippery", "safe"))
    assert wet[0] < hard[0] and wet[1] > hard[1]        # wet: shorter, slower steps
    assert soft[2] > hard[2]                            # soft: higher clearance
    import surface_link as SL
    s = SL.SurfaceState()
    assert G.choose_preset(s, "hard") == "safe"         # never received -> safe
    s.valid, s.stale, s.class_id = True, False, SL.CLASS_SOFT
    s.probs_u8[SL.CLASS_SOFT] = 200
    assert G.choose_preset(s, "hard") == "soft"
    s.probs_u8[SL.CLASS_SOFT] = 100                     # not confident: keep
    assert G.choose_preset(s, "hard") == "hard"
    s.faults = SL.FAULT_CAMERA
    assert G.choose_preset(s, "hard") == "safe"


# -- properties: the MCU and the Pi agree on every input -----------------------------------

from hypothesis import example, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

ANY = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-10**6, 10**6))


@settings(max_examples=300, deadline=None)
@given(phase=st.integers(-2, 3), load_n=ANY, vel=st.tuples(ANY, ANY, ANY),
       seq=st.integers(0, 65535), t_ms=st.integers(0, 2**30 - 1))
# a finite load whose scaled value overflows: clamped on both sides, not "non-finite"
@example(phase=0, load_n=1.797693134862316e+307, vel=(0.0, 0.0, 0.0), seq=0, t_ms=0)
@example(phase=1, load_n=1.0, vel=(-1e308, 1e308, float("nan")), seq=1, t_ms=5)
def test_mcu_gait_encoder_equals_the_pi_encoder_for_any_values(phase, load_n, vel, seq, t_ms):
    cpython_path()
    import machine
    import surface_link as SL
    u = machine.UART(0)
    link = SL.SurfaceLink(u, clock=lambda: t_ms)
    link.tx_seq = seq
    link.send_gait(phase, load_n, vel)
    assert u.take() == P.Gait(phase, load_n, vel).encode(seq, t_ms)


@settings(max_examples=300, deadline=None)
@given(st.lists(st.binary(max_size=80), max_size=6), st.integers(0, 3))
def test_mcu_decoder_and_pi_decoder_accept_the_same_frames(chunks, n_good):
    cpython_path()
    import tflink
    good = [P.Surface(i % 4).encode(i, i) for i in range(n_good)]
    stream = b"".join(c + g for c, g in zip(chunks, good + [b""] * len(chunks)))
    got = []
    d = tflink.Decoder(64, lambda d: got.append((d.msg_type, d.seq, d.t_ms,
                                                 bytes(d.payload))))
    d.feed(stream, len(stream))
    pi = P.FrameDecoder()
    assert got == [(f.msg_type, f.seq, f.t_ms, f.payload) for f in pi.feed(stream)]
    for k in ("crc_errors", "too_long", "malformed", "newer_version", "frames_ok"):
        assert getattr(d, k) == getattr(pi, k), k
