"""The surface link consumer (device/micropython/surface_link.py, over tflink.py) on
REAL MicroPython (the WebAssembly port under Node) and on CPython: the same scripts run
on both and must give the same answers.

Covers: the golden vectors (decode, and the MCU's own GAIT/COMMAND encoder against
the Pi's bytes), the stream vectors' counters, a long session with a link outage
(stale -> safe default), no allocation per byte, and the MCU's GAIT encoder against
the Pi's for any values. The framing fuzz is in test_tflink.py, the gait example in
test_gait_example.py.
"""
from __future__ import annotations

import json
import random
from pathlib import Path

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from device.pi import protocol as P
from tests import REPO_ROOT
from tests.mpyrun import MPY_LIB, cpython_path, requires_mpy, run_both, run_cpython, run_mpy

VECTORS = REPO_ROOT / "tests" / "device" / "pi" / "protocol_vectors.json"


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
    for msg_type, payload in ((P.MsgType.SURFACE, bytes(17)), (P.MsgType.IMU_SUMMARY, bytes(16)),
                              (P.MsgType.HEARTBEAT, bytes(10)), (P.MsgType.FAULT, fault[:5])):
        u.feed(P.encode_frame(msg_type, payload, 1, 0))
    assert link.poll() == 4
    assert (link.short_payload, link.unknown_type) == (4, 0)
    assert not link.state().valid and link.heartbeats == 0 and link.fault_bits == 0
    u.feed(P.encode_frame(P.MsgType.FAULT, fault, 2, 0))
    assert link.poll() == 1 and (link.fault_bits, link.pins_lost) == (P.FAULT_CAMERA, 3)
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


# -- properties: the MCU and the Pi agree on every input -----------------------------------

ANY = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-10**6, 10**6))


@settings(max_examples=300, deadline=None)
@given(phase=st.integers(-2, 3), load_n=ANY, vel=st.tuples(ANY, ANY, ANY),
       seq=st.integers(0, 65535), t_ms=st.integers(0, 2**30 - 1))
# a finite load whose scaled value overflows: clamped on both sides, not "non-finite"
@example(phase=0, load_n=1.797693134862316e+307, vel=(0.0, 0.0, 0.0), seq=0, t_ms=0)
@example(phase=1, load_n=1.0, vel=(-1e308, 1e308, float("nan")), seq=1, t_ms=5)
# within half a step of a field's end: that end, unflagged; beyond it: clamped
@example(phase=0, load_n=6553.54, vel=(32767.4, -32768.4, 0.0), seq=2, t_ms=6)
@example(phase=0, load_n=-0.04, vel=(32767.6, -32768.6, 0.0), seq=3, t_ms=7)
def test_mcu_gait_encoder_equals_the_pi_encoder_for_any_values(phase, load_n, vel, seq, t_ms):
    cpython_path()
    import machine
    import surface_link as SL
    u = machine.UART(0)
    link = SL.SurfaceLink(u, clock=lambda: t_ms)
    link.tx_seq = seq
    link.send_gait(phase, load_n, vel)
    assert u.take() == P.Gait(phase, load_n, vel).encode(seq, t_ms)


@pytest.mark.parametrize("vel", [(), (5.0,), (5.0, -6.0), (1.0, 2.0, 3.0, 4.0), 7.5, None])
def test_mcu_gait_encoder_flags_a_velocity_of_the_wrong_length_as_the_pi_does(vel):
    cpython_path()
    import machine
    import surface_link as SL
    u = machine.UART(0, 921600)
    link = SL.SurfaceLink(u, clock=lambda: 0)
    link.send_gait(SL.PHASE_STANCE, 10.0, vel)
    wire = u.take()
    assert wire == P.Gait(P.PHASE_STANCE, 10.0, vel).encode(0, 0)
    g = P.decode_message(P.FrameDecoder().feed(wire)[0])
    flagged = not isinstance(vel, (int, float)) and len(vel or ()) != 3
    assert bool(g.flags & P.GAIT_FLAG_NONFINITE) == flagged


# -- what the link reports before any message, and its counters ---------------------------

COUNTERS = r"""
import json, machine, tflink
import surface_link as SL

now = [0]
u = machine.UART(0, 921600)
link = SL.SurfaceLink(u, clock=lambda: now[0])
enc = tflink.Encoder()

def state_dict():
    s = link.state()
    return {"valid": s.valid, "stale": s.stale, "age_ms": s.age_ms, "rx_ms": s.rx_ms,
            "seq": s.seq, "t_ms": s.t_ms, "class_id": s.class_id, "probs_u8": list(s.probs_u8),
            "contact": s.contact, "slip": s.slip, "slip_conf_u8": s.slip_conf_u8,
            "texture_id": s.texture_id, "shear_dir_deg_x100": s.shear_dir_deg_x100,
            "shear_px_x100": s.shear_px_x100, "load_n_x100": s.load_n_x100, "pins": s.pins,
            "faults": s.faults}

def link_dict():
    return {"fault_bits": link.fault_bits, "fault_raised": link.fault_raised,
            "pins_lost": link.pins_lost, "heartbeat_rx_ms": link.heartbeat_rx_ms,
            "heartbeats": link.heartbeats, "pi_uptime_s": link.pi_uptime_s,
            "pi_rate_fps_x10": link.pi_rate_fps_x10, "imu": list(link.imu),
            "imu_samples": link.imu_samples, "tx_seq": link.tx_seq,
            "unknown_type": link.unknown_type, "short_payload": link.short_payload,
            "drops": link.drops, "rates_refused": link.rates_refused,
            "frames_ok": link.frames_ok, "crc_errors": link.crc_errors,
            "too_long": link.too_long, "malformed": link.malformed,
            "newer_version": link.newer_version}

def send(msg_type, seq, payload):
    w = bytes(enc.frame(msg_type, seq, 5, payload, len(payload)))
    u.feed(w)
    return link.poll()

out = {"fresh_state": state_dict(), "fresh_link": link_dict(), "steps": []}

def step(name, msg_type, seq, payload):
    n = send(msg_type, seq, payload)
    out["steps"].append([name, n, link.drops, link.unknown_type, link.heartbeats,
                         link.heartbeat_rx_ms])

hb = bytearray(11)
hb[4] = 0xE8
hb[5] = 0x03                                   # 100.0 fps
now[0] = 1234
step("heartbeat", SL.MSG_HEARTBEAT, 0, hb)
now[0] = 2000
step("unknown", 0x0E, 1, bytearray(2))
step("unknown again", 0x0E, 2, bytearray(2))
step("999 missed", SL.MSG_SURFACE, 1002, bytearray(18))
step("1000 missed: a restart", SL.MSG_SURFACE, 2003, bytearray(18))
step("far jump: a restart", SL.MSG_SURFACE, 65535, bytearray(18))
step("wraps to 0: none missed", SL.MSG_SURFACE, 0, bytearray(18))
now[0] = 2500
step("1 missed", SL.MSG_HEARTBEAT, 2, hb)
out["end_link"] = link_dict()
# CMD_SET_RATE: sent within RATE_MIN_FPS..RATE_MAX_FPS, else refused and counted
from binascii import hexlify
u.take()
out["rates"] = []
for a in (1, 1000, 0, 1001, 70000, -1, "x", None, 2.5):
    seq = link.tx_seq
    n = link.send_command(SL.CMD_SET_RATE, a)
    out["rates"].append([str(a), seq, n, hexlify(u.take()).decode(), link.rates_refused])
print(json.dumps(out))
"""


def _check_counters(out: dict):
    assert out["fresh_state"] == {
        "valid": False, "stale": True, "age_ms": -1, "rx_ms": 0, "seq": 0, "t_ms": 0,
        "class_id": 255, "probs_u8": [0, 0, 0, 0], "contact": False, "slip": False,
        "slip_conf_u8": 0, "texture_id": 255, "shear_dir_deg_x100": 0, "shear_px_x100": 0,
        "load_n_x100": 0, "pins": 0, "faults": 0}
    assert out["fresh_link"] == {
        "fault_bits": 0, "fault_raised": 0, "pins_lost": 0, "heartbeat_rx_ms": 0,
        "heartbeats": 0, "pi_uptime_s": 0, "pi_rate_fps_x10": 0, "imu": [0] * 6,
        "imu_samples": 0, "tx_seq": 0, "unknown_type": 0, "short_payload": 0, "drops": 0,
        "rates_refused": 0, "frames_ok": 0, "crc_errors": 0, "too_long": 0, "malformed": 0, "newer_version": 0}
    # == does not tell 0 from False or None from a missing value: the flags are booleans
    for k in ("valid", "stale", "contact", "slip"):
        assert type(out["fresh_state"][k]) is bool, k
    for k, v in out["fresh_link"].items():
        assert type(v) is (list if k == "imu" else int), k
    # [name, frames decoded, drops, unknown_type, heartbeats, heartbeat_rx_ms]
    assert out["steps"] == [
        ["heartbeat", 1, 0, 0, 1, 1234],
        ["unknown", 1, 0, 1, 1, 1234],
        ["unknown again", 1, 0, 2, 1, 1234],
        ["999 missed", 1, 999, 2, 1, 1234],                 # a gap below 1000 is counted
        ["1000 missed: a restart", 1, 999, 2, 1, 1234],     # 1000 and more: the Pi restarted
        ["far jump: a restart", 1, 999, 2, 1, 1234],
        ["wraps to 0: none missed", 1, 999, 2, 1, 1234],    # 65535 -> 0 is the next number
        ["1 missed", 1, 1000, 2, 2, 2500],
    ]
    assert out["end_link"]["pi_rate_fps_x10"] == 1000 and out["end_link"]["frames_ok"] == 8
    # [arg, tx_seq before, send_command's return, bytes written, rates_refused]
    sent = {"1": 1, "1000": 1000, "2.5": 2}                # 2.5 goes out as 2, as the Pi packs it
    refused = 0
    seq = 0
    for arg, seq_before, n, wire, n_refused in out["rates"]:
        assert seq_before == seq, arg
        if arg in sent:
            w = P.Command(P.CMD_SET_RATE, sent[arg]).encode(seq, 2500)
            assert (n, wire) == (len(w), w.hex()), arg
            seq += 1
        else:
            refused += 1
            assert (n, wire) == (0, ""), arg                  # nothing written, no sequence number
        assert n_refused == refused, arg
    assert refused == 6


@requires_mpy
def test_initial_values_and_counters_identically_on_micropython_and_cpython():
    mp, cp = run_both(COUNTERS)
    mp_out, cp_out = json.loads(mp), json.loads(cp)
    _check_counters(mp_out)
    _check_counters(cp_out)
    assert mp_out == cp_out


def test_initial_values_and_counters_on_cpython_alone():
    """Before any message every field holds its documented start value; a gap of
    fewer than 1000 sequence numbers counts as drops, 1000 or more as a restart of
    the Pi; each unknown message type counts once; a HEARTBEAT stamps its arrival; a
    rate command goes out for 1..1000 fps and is refused and counted otherwise."""
    _check_counters(json.loads(run_cpython(COUNTERS)))


# -- CMD_REQUEST_STATUS: rate-limited by the MCU's own clock (issue 29) ---------------

STATUS_LIMIT = r"""
import json, machine
from binascii import hexlify
import surface_link as SL

now = [0]
u = machine.UART(0, 921600)
link = SL.SurfaceLink(u, clock=lambda: now[0])
u.take()
out = {"min_ms": SL.STATUS_MIN_MS, "default": link.status_min_ms, "steps": []}
# (ticks_ms, command): requests around the 50 ms bound, a re-zero and a rate in
# between (never limited), and the 2**30 wrap of ticks_ms
WRAP = 0x3FFFFFFF
for t, c in ((0, 3), (0, 3), (10, 3), (49, 3), (49, 1), (50, 3), (51, 3), (99, 3), (100, 3),
             (100, 2), (1000, 3), (WRAP - 20, 3), ((WRAP - 20 + 40) & WRAP, 3),
             ((WRAP - 20 + 70) & WRAP, 3)):
    now[0] = t
    n = link.send_command(c, 60 if c == 2 else 0)
    out["steps"].append([t, c, n > 0, link.status_refused])
out["wire"] = hexlify(u.take()).decode()
quiet = SL.SurfaceLink(u, clock=lambda: now[0], status_min_ms=0)   # no limit
now[0] = 5
out["unlimited"] = [quiet.send_command(SL.CMD_REQUEST_STATUS) > 0 for _ in range(3)]
print(json.dumps(out))
"""


def _check_status_limit(out: dict):
    assert out["min_ms"] == out["default"] == 50
    sent = [(t, c) for t, c, ok, _ in out["steps"] if ok]
    refused = [(t, c) for t, c, ok, _ in out["steps"] if not ok]
    wrap = 0x3FFFFFFF
    assert refused == [(0, 3), (10, 3), (49, 3), (51, 3), (99, 3), ((wrap - 20 + 40) & wrap, 3)]
    assert out["steps"][-1][3] == len(refused)
    # what went out is what the Pi reads: the commands sent, in order, nothing else
    dec = P.FrameDecoder()
    got = [P.decode_message(r) for r in dec.feed(bytes.fromhex(out["wire"]))]
    assert [(m.command, m.arg) for m in got] == [(c, 60 if c == 2 else 0) for _, c in sent]
    assert dec.crc_errors == dec.malformed == 0
    assert out["unlimited"] == [True] * 3


@requires_mpy
def test_mcu_sends_a_status_request_at_most_every_50_ms_on_micropython_and_cpython():
    """send_command(CMD_REQUEST_STATUS) goes out at most once per status_min_ms (50)
    by the link's own clock, across the ticks_ms wrap; the others return 0, write
    nothing and count in status_refused; re-zero and rate commands are never held
    back (before: every request was sent, 6,000 a second starved the leg)."""
    mp, cp = run_both(STATUS_LIMIT)
    assert json.loads(mp) == json.loads(cp)
    _check_status_limit(json.loads(mp))


def test_mcu_sends_a_status_request_at_most_every_50_ms_on_cpython_alone():
    _check_status_limit(json.loads(run_cpython(STATUS_LIMIT)))


GAIT_EDGES = r"""
import json, machine
from binascii import hexlify
import surface_link as SL

u = machine.UART(0, 921600)
link = SL.SurfaceLink(u, clock=lambda: 9)
out = []
for load, vel in ((6553.54, (32767.4, -32768.4, 0.0)), (-0.04, (0.0, 0.0, 0.0)),
                  (6553.56, (0.0, 0.0, 0.0)), (-0.06, (32767.6, -32768.6, 0.49))):
    u.take()
    link.send_gait(SL.PHASE_STANCE, load, vel)
    out.append(hexlify(u.take()).decode())
print(json.dumps(out))
"""


@requires_mpy
def test_mcu_and_pi_agree_on_values_within_half_a_step_of_a_fields_end():
    """A value that rounds to its field's end is that end with no clamped flag, one
    beyond is clamped, on real MicroPython as on the Pi (issue 29, item 13)."""
    mp, cp = run_both(GAIT_EDGES)
    assert json.loads(mp) == json.loads(cp)
    cases = [(6553.54, (32767.4, -32768.4, 0.0), 0), (-0.04, (0.0, 0.0, 0.0), 0),
             (6553.56, (0.0, 0.0, 0.0), P.GAIT_FLAG_CLAMPED),
             (-0.06, (32767.6, -32768.6, 0.49), P.GAIT_FLAG_CLAMPED)]
    for i, (wire, (load, vel, flags)) in enumerate(zip(json.loads(mp), cases)):
        assert wire == P.Gait(P.PHASE_STANCE, load, vel).encode(i, 9).hex()
        (raw,) = P.FrameDecoder().feed(bytes.fromhex(wire))
        assert P.decode_message(raw).flags == flags
