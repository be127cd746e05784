"""Write tests/device/pi/protocol_vectors.json: the golden vectors of wire protocol v1.

    .venv/bin/python tests/device/pi/make_protocol_vectors.py [--check]

The JSON is committed as data: the Pi encoder, the MicroPython decoder and the
host monitor are all tested against it, and docs/protocol.md quotes it. --check
exits 1 if the file on disk differs from what this script would write.
"""
from __future__ import annotations
from tests import REPO_ROOT

import json
import struct
import sys
from pathlib import Path

ROOT = REPO_ROOT
sys.path.insert(0, str(ROOT))

from device.pi import protocol as P  # noqa: E402

OUT = Path(__file__).with_name("protocol_vectors.json")
NAN = float("nan")
INF = float("inf")

MESSAGES = [
    ("surface_hard", 1, 1000, P.Surface(1, (0.02, 0.9, 0.05, 0.03), True, False, 0.05, 45.0,
                                        3.21, 25.5, 331, 0, 2)),
    ("surface_slippery_slip", 2, 1033, P.Surface(3, (0.01, 0.1, 0.09, 0.8), True, True, 0.87,
                                                 270.5, 8.4, 40.2, 300, P.FAULT_PINS_LOST, 1)),
    ("surface_soft", 3, 1066, P.Surface(2, (0.0, 0.15, 0.8, 0.05), True, False, 0.0, 180.0,
                                        1.5, 12.0, 329, 0, 255)),
    ("surface_no_touch", 4, 1100, P.Surface(0, (0.97, 0.01, 0.01, 0.01), False, False, 0.0,
                                            0.0, 0.0, 0.0, 331, 0, 255)),
    ("surface_clamped", 5, 1133, P.Surface(1, (1.5, -0.2, 0.5, 0.0), True, False, 2.0, -90.0,
                                           1e6, -5.0, 70000, P.FAULT_NO_REFERENCE, 2)),
    ("surface_nonfinite", 6, 1166, P.Surface(3, (NAN, 0.5, 0.5, 0.0), True, True, INF, NAN,
                                             -INF, NAN, 12, P.FAULT_TOO_FEW_PINS, 255)),
    ("surface_seq_wrap", 0xFFFF, 0xFFFFFFFF, P.Surface(1, (0.0, 1.0, 0.0, 0.0), True, False,
                                                        0.0, 359.99, 655.35, 655.35, 65535,
                                                        0, 3)),
    ("imu_summary", 7, 1200, P.ImuSummary((12.0, -30.0, 998.0), (1.5, -0.3, 20.0), 1450.0, 33,
                                          0)),
    ("heartbeat", 8, 2000, P.Heartbeat(3600, 30.0, 2, 51, 0)),
    ("fault_camera_model", 9, 2033, P.Fault(P.FAULT_CAMERA | P.FAULT_MODEL, P.FAULT_CAMERA, 0)),
    ("fault_pins_lost", 10, 2066, P.Fault(P.FAULT_PINS_LOST | P.FAULT_TOO_FEW_PINS,
                                          P.FAULT_PINS_LOST, 42)),
    ("gait_stance", 11, 500, P.Gait(P.PHASE_STANCE, 45.5, (-250.0, 0.0, 0.0), 0)),
    ("gait_swing", 12, 520, P.Gait(P.PHASE_SWING, 0.0, (400.0, 10.0, 120.0), 0)),
    ("gait_clamped", 13, 540, P.Gait(P.PHASE_SWING, NAN, (1e6, -1e6, 5.0), 0)),
    ("command_rezero", 14, 600, P.Command(P.CMD_REZERO, 0)),
    ("command_set_rate", 15, 620, P.Command(P.CMD_SET_RATE, 60)),
    ("command_request_status", 16, 640, P.Command(P.CMD_REQUEST_STATUS, 0)),
]


def _clean(v):
    """JSON-safe: NaN/inf as strings, tuples as lists."""
    if isinstance(v, float) and v != v:
        return "nan"
    if isinstance(v, float) and v in (INF, -INF):
        return "inf" if v > 0 else "-inf"
    if isinstance(v, (tuple, list)):
        return [_clean(x) for x in v]
    return v


def raw_fields(msg_type: int, payload: bytes) -> dict:
    """The wire integers, named as device/micropython/surface_link.py names them."""
    if msg_type == P.MsgType.SURFACE:
        (cid, p0, p1, p2, p3, flags, conf, tex, d, mag, load, pins,
         faults) = struct.unpack("<BBBBBBBBHHHHH", payload)
        return {"class_id": cid, "probs_u8": [p0, p1, p2, p3], "contact": bool(flags & 1),
                "slip": bool(flags & 2), "slip_conf_u8": conf, "texture_id": tex,
                "shear_dir_deg_x100": d, "shear_px_x100": mag, "load_n_x100": load,
                "pins": pins, "faults": faults}
    if msg_type == P.MsgType.IMU_SUMMARY:
        *v, peak, n, faults = struct.unpack("<hhhhhhHBH", payload)
        return {"imu": v, "acc_peak_mg": peak, "imu_samples": n, "faults": faults}
    if msg_type == P.MsgType.HEARTBEAT:
        up, rate, dropped, temp, faults = struct.unpack("<IHHbH", payload)
        return {"pi_uptime_s": up, "pi_rate_fps_x10": rate, "frames_dropped": dropped,
                "temp_c": temp, "fault_bits": faults}
    if msg_type == P.MsgType.FAULT:
        f, r, lost = struct.unpack("<HHH", payload)
        return {"fault_bits": f, "fault_raised": r, "pins_lost": lost}
    if msg_type == P.MsgType.GAIT:
        phase, load, vx, vy, vz, flags = struct.unpack("<BHhhhB", payload)
        return {"phase": phase, "load_n_x10": load, "vel_mm_s": [vx, vy, vz], "flags": flags}
    if msg_type == P.MsgType.COMMAND:
        c, a = struct.unpack("<BH", payload)
        return {"command": c, "arg": a}
    return {}


def _frame_v(version: int, msg_type: int, payload: bytes, seq: int, t_ms: int) -> bytes:
    body = struct.pack("<BBHI", version, msg_type, seq, t_ms) + payload
    body += struct.pack("<H", P.crc16(body))
    return P.cobs_encode(body) + b"\x00"


def _expect(msg_type, seq, t_ms, payload):
    return {"msg_type": msg_type, "seq": seq, "t_ms": t_ms, "payload_hex": payload.hex()}


def streams() -> list[dict]:
    good = P.Surface(1, (0.0, 1.0, 0.0, 0.0), True, False, 0.0, 90.0, 2.0, 10.0, 331, 0, 255)
    gp = good.pack()
    f1, f2 = good.encode(100, 5000), good.encode(101, 5033)
    body = bytearray(P.cobs_decode(f1[:-1]))
    body[12] ^= 0x04                      # one bit of the payload: the CRC must catch it
    bad = P.cobs_encode(body) + b"\x00"
    long_body = bytes(range(1, 71))       # 70 decoded bytes, no zeros: over the 64 limit
    out = [
        {"name": "garbage_then_frames",
         "note": "garbage without a delimiter swallows the first frame; the next is decoded",
         "wire_hex": (b"\x13\x37\xab\xcd\x05" + f1 + f2).hex(),
         "expect": [_expect(1, 101, 5033, gp)],
         "counters": {"crc_errors": 1, "too_long": 0, "malformed": 0, "newer_version": 0}},
        {"name": "corrupt_crc", "note": "one flipped payload bit, then a good frame",
         "wire_hex": (bytes(bad) + f2).hex(), "expect": [_expect(1, 101, 5033, gp)],
         "counters": {"crc_errors": 1, "too_long": 0, "malformed": 0, "newer_version": 0}},
        {"name": "newer_version", "note": "a version-2 frame is skipped and counted",
         "wire_hex": (_frame_v(2, 1, gp + b"\x00\x01", 100, 5000) + f2).hex(),
         "expect": [_expect(1, 101, 5033, gp)],
         "counters": {"crc_errors": 0, "too_long": 0, "malformed": 0, "newer_version": 1}},
        {"name": "unknown_type",
         "note": "type 0x0E is framed correctly: the framing layer delivers it, the "
                 "message layer skips and counts it",
         "wire_hex": (P.encode_frame(0x0E, b"\x01\x02\x03", 100, 5000) + f2).hex(),
         "expect": [_expect(0x0E, 100, 5000, b"\x01\x02\x03"), _expect(1, 101, 5033, gp)],
         "counters": {"crc_errors": 0, "too_long": 0, "malformed": 0, "newer_version": 0}},
        {"name": "too_long", "note": "70 decoded bytes: dropped at 64 and counted",
         "wire_hex": (P.cobs_encode(long_body) + b"\x00" + f2).hex(),
         "expect": [_expect(1, 101, 5033, gp)],
         "counters": {"crc_errors": 0, "too_long": 1, "malformed": 0, "newer_version": 0}},
        {"name": "truncated", "note": "half a frame, then a delimiter, then a good frame",
         "wire_hex": (f1[:14] + b"\x00" + f2).hex(), "expect": [_expect(1, 101, 5033, gp)],
         "counters": {"crc_errors": 0, "too_long": 0, "malformed": 1, "newer_version": 0}},
        {"name": "empty_delimiters", "note": "runs of 0x00 are idle line, not errors",
         "wire_hex": (b"\x00\x00\x00" + f1 + b"\x00\x00" + f2).hex(),
         "expect": [_expect(1, 100, 5000, gp), _expect(1, 101, 5033, gp)],
         "counters": {"crc_errors": 0, "too_long": 0, "malformed": 0, "newer_version": 0}},
    ]
    for v in out:                         # the counters are the Pi decoder's
        d = P.FrameDecoder()
        d.feed(bytes.fromhex(v["wire_hex"]))
        got = {k: getattr(d, k) for k in v["counters"]}
        if got != v["counters"]:
            raise SystemExit(f"stream {v['name']}: expected counters {v['counters']}, "
                             f"the Pi decoder counts {got}")
    return out


def build() -> dict:
    msgs = []
    for name, seq, t_ms, msg in MESSAGES:
        payload = msg.pack()
        wire = msg.encode(seq, t_ms)
        decoded = P.decode_message(P.FrameDecoder().feed(wire)[0])
        msgs.append({
            "name": name, "type": msg.name, "msg_type": int(msg.msg_type),
            "seq": seq, "t_ms": t_ms,
            "given": {k: _clean(v) for k, v in msg.__dict__.items()},
            "payload_hex": payload.hex(), "wire_hex": wire.hex(), "wire_len": len(wire),
            "decoded": {k: _clean(v) for k, v in decoded.__dict__.items()},
            "raw": raw_fields(msg.msg_type, payload)})
    return {"protocol_version": P.VERSION,
            "crc": {"name": "CRC-16/CCITT-FALSE", "input": "313233343536373839",
                    "value": P.crc16(b"123456789")},
            "messages": msgs, "streams": streams()}


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    text = json.dumps(build(), indent=1) + "\n"
    if "--check" in argv:
        same = OUT.is_file() and OUT.read_text() == text
        print(f"{OUT}: {'up to date' if same else 'DIFFERS from the generator'}")
        return 0 if same else 1
    OUT.write_text(text)
    print(f"wrote {OUT}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
