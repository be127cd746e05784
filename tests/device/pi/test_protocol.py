"""Wire protocol v1, CPython side (device/pi/protocol.py): CRC, COBS, framing, the
typed messages against the golden vectors, clamping, a decoder that never raises, and
docs/protocol.md quoting the vectors. The MicroPython side is in
tests/device/micropython/test_surface_link.py; ``host monitor`` in
tests/host/test_monitor.py."""
from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from device.pi import protocol as P
from tests import REPO_ROOT

ROOT = REPO_ROOT

VECTORS = json.loads((Path(__file__).with_name("protocol_vectors.json")).read_text())
ANY_FLOAT = st.floats(allow_nan=True, allow_infinity=True)
FAST = settings(max_examples=300, deadline=None)


def _num(v):
    return float(v) if isinstance(v, str) else v


def _given_msg(v):
    cls = P.MESSAGES[v["msg_type"]]
    kw = {}
    for k, val in v["given"].items():
        kw[k] = tuple(_num(x) for x in val) if isinstance(val, list) else _num(val)
    return cls(**kw)


# -- CRC and COBS ---------------------------------------------------------------------

def test_crc16_ccitt_false_check_value():
    assert P.crc16(b"123456789") == 0x29B1 == VECTORS["crc"]["value"]
    assert P.crc16(b"") == 0xFFFF


@pytest.mark.parametrize("raw,enc", [
    (b"\x00", b"\x01\x01"), (b"\x00\x00", b"\x01\x01\x01"),
    (b"\x11\x22\x00\x33", b"\x03\x11\x22\x02\x33"), (b"\x11\x22\x33\x44", b"\x05\x11\x22\x33\x44"),
    (bytes(range(1, 255)), b"\xff" + bytes(range(1, 255))),
    (bytes(range(1, 256)), b"\xff" + bytes(range(1, 255)) + b"\x02\xff")])
def test_cobs_known_encodings(raw, enc):
    assert P.cobs_encode(raw) == enc
    assert P.cobs_decode(enc) == raw


@FAST
@given(st.binary(max_size=600))
def test_cobs_roundtrip_and_no_zero_bytes(data):
    enc = P.cobs_encode(data)
    assert 0 not in enc
    assert len(enc) <= len(data) + len(data) // 254 + 1
    assert P.cobs_decode(enc) == data


def test_cobs_decode_names_the_bad_offset():
    with pytest.raises(ValueError, match="offset 0"):
        P.cobs_decode(b"\x05\x01")


# -- golden vectors --------------------------------------------------------------------

@pytest.mark.parametrize("v", VECTORS["messages"], ids=lambda v: v["name"])
def test_golden_vector_encode_and_decode(v):
    msg = _given_msg(v)
    assert msg.pack().hex() == v["payload_hex"]
    assert msg.encode(v["seq"], v["t_ms"]).hex() == v["wire_hex"]
    frames = P.FrameDecoder().feed(bytes.fromhex(v["wire_hex"]))
    assert [(f.msg_type, f.seq, f.t_ms, f.payload.hex()) for f in frames] == [
        (v["msg_type"], v["seq"], v["t_ms"], v["payload_hex"])]
    dec = P.decode_message(frames[0])
    for k, val in v["decoded"].items():
        got = getattr(dec, k)
        assert (list(got) if isinstance(got, tuple) else got) == val, k
    d = P.message_dict(dec)
    assert d["type"] == v["type"]
    json.dumps(d)


def test_golden_vectors_file_matches_the_generator():
    from tests.device.pi import make_protocol_vectors
    assert make_protocol_vectors.build() == VECTORS, \
        "run: .venv/bin/python tests/device/pi/make_protocol_vectors.py"


@pytest.mark.parametrize("v", VECTORS["streams"], ids=lambda v: v["name"])
def test_stream_vectors(v):
    d = P.FrameDecoder()
    wire = bytes.fromhex(v["wire_hex"])
    frames = []
    for i in range(0, len(wire), 5):        # split reads
        frames += d.feed(wire[i:i + 5])
    assert [(f.msg_type, f.seq, f.t_ms, f.payload.hex()) for f in frames] == [
        (e["msg_type"], e["seq"], e["t_ms"], e["payload_hex"]) for e in v["expect"]]
    assert {k: getattr(d, k) for k in v["counters"]} == v["counters"]


def test_clamped_and_nonfinite_vectors_carry_fault_bits():
    by = {v["name"]: v for v in VECTORS["messages"]}
    assert by["surface_clamped"]["raw"]["faults"] & P.FAULT_CLAMPED
    assert by["surface_nonfinite"]["raw"]["faults"] & P.FAULT_NONFINITE
    assert by["gait_clamped"]["raw"]["flags"] == P.GAIT_FLAG_CLAMPED | P.GAIT_FLAG_NONFINITE
    assert not by["surface_hard"]["raw"]["faults"]


# -- sizes -----------------------------------------------------------------------------

SURFACES = st.builds(
    P.Surface, class_id=st.integers(-5, 300), probs=st.tuples(ANY_FLOAT, ANY_FLOAT, ANY_FLOAT,
                                                              ANY_FLOAT),
    contact=st.booleans(), slip=st.booleans(), slip_conf=ANY_FLOAT, shear_dir_deg=ANY_FLOAT,
    shear_px=ANY_FLOAT, load_n=ANY_FLOAT, pins=st.integers(-10, 10**6),
    faults=st.integers(-1, 1 << 20), texture_id=st.integers(-1, 300))


@FAST
@given(SURFACES, st.integers(0, 2**40), st.integers(0, 2**40))
def test_surface_is_at_most_32_bytes_on_the_wire_and_never_raises(s, seq, t_ms):
    wire = s.encode(seq, t_ms)
    assert len(wire) <= 32
    frames = P.FrameDecoder().feed(wire)
    assert len(frames) == 1 and frames[0].seq == seq & 0xFFFF
    assert frames[0].t_ms == t_ms & 0xFFFFFFFF
    d = P.decode_message(frames[0])
    for name in ("slip_conf", "shear_dir_deg", "shear_px", "load_n", *()):
        assert math.isfinite(getattr(d, name)), name
    assert all(0.0 <= p <= 1.0 for p in d.probs)
    assert 0 <= d.shear_dir_deg < 360


def test_every_message_fits_the_64_byte_frame():
    for cls in P.MESSAGES.values():
        assert len(P.cobs_decode(cls().encode(0, 0)[:-1])) <= P.MAX_FRAME
    assert len(P.Surface().encode(0, 0)) == 30


# -- roundtrip and clamping properties ----------------------------------------------------

FINITE = st.floats(-1e6, 1e6, allow_nan=False)


@FAST
@given(class_id=st.integers(0, 3), probs=st.lists(st.floats(0, 1), min_size=4, max_size=4),
       slip_conf=st.floats(0, 1), shear_dir_deg=FINITE, shear_px=FINITE, load_n=FINITE,
       pins=st.integers(0, 70000), contact=st.booleans(), slip=st.booleans())
def test_surface_roundtrip_equals_the_clamped_value(class_id, probs, slip_conf, shear_dir_deg,
                                                    shear_px, load_n, pins, contact, slip):
    s = P.Surface(class_id, tuple(probs), contact, slip, slip_conf, shear_dir_deg, shear_px,
                  load_n, pins, 0, 1)
    d = P.Surface.unpack(s.pack())
    assert (d.class_id, d.contact, d.slip, d.texture_id) == (class_id, contact, slip, 1)
    for a, b in zip(d.probs, probs):
        assert abs(a - b) <= 0.5 / 255 + 1e-12
    assert abs(d.slip_conf - slip_conf) <= 0.5 / 255 + 1e-12
    clamp = lambda x: min(max(x, 0.0), 655.35)  # noqa: E731
    assert abs(d.shear_px - clamp(shear_px)) <= 0.005 + 1e-9
    assert abs(d.load_n - clamp(load_n)) <= 0.005 + 1e-9
    err = abs(d.shear_dir_deg - shear_dir_deg % 360)
    assert min(err, 360 - err) <= 0.005 + 1e-6
    assert d.pins == min(pins, 65535)
    # beyond the field by more than half its step (0.01): what rounds to an end is that end
    beyond = lambda x: x * 100.0 < -0.5 or x * 100.0 > 65535.5  # noqa: E731
    out_of_range = beyond(shear_px) or beyond(load_n) or pins > 65535
    assert bool(d.faults & P.FAULT_CLAMPED) == out_of_range
    assert not d.faults & P.FAULT_NONFINITE


@FAST
@given(st.sampled_from([float("nan"), float("inf"), -float("inf"), None, "x"]),
       st.sampled_from(["slip_conf", "shear_dir_deg", "shear_px", "load_n"]))
def test_nonfinite_becomes_zero_and_a_fault_bit(bad, name):
    s = P.Surface(1, (0.0, 1.0, 0.0, 0.0), True, False, 0.5, 10.0, 1.0, 2.0, 300, 0, 1)
    setattr(s, name, bad)
    d = P.Surface.unpack(s.pack())
    assert d.faults & P.FAULT_NONFINITE
    assert getattr(d, name) == 0.0


@FAST
@given(phase=st.integers(-3, 5), load_n=ANY_FLOAT, vel=st.tuples(ANY_FLOAT, ANY_FLOAT, ANY_FLOAT))
def test_gait_roundtrip_clamps_and_flags(phase, load_n, vel):
    g = P.Gait(phase, load_n, vel)
    d = P.decode_message(P.FrameDecoder().feed(g.encode(1, 2))[0])
    assert d.phase in (0, 1)
    assert 0.0 <= d.load_n <= 6553.5 and all(-32768 <= v <= 32767 for v in d.vel_mm_s)
    nonfinite = not all(math.isfinite(x) for x in (load_n, *vel))
    assert bool(d.flags & P.GAIT_FLAG_NONFINITE) == nonfinite
    if math.isfinite(load_n) and 0 <= load_n <= 6553.5:
        assert abs(d.load_n - load_n) <= 0.05 + 1e-9
    for a, b in zip(d.vel_mm_s, vel):
        if math.isfinite(b) and -32768 <= b <= 32767:
            assert abs(a - b) <= 0.5 + 1e-9


@FAST
@given(acc=st.tuples(FINITE, FINITE, FINITE), gyro=st.tuples(FINITE, FINITE, FINITE),
       samples=st.integers(0, 400))
def test_imu_summary_roundtrip(acc, gyro, samples):
    d = P.ImuSummary.unpack(P.ImuSummary(acc, gyro, 1000.0, samples, 0).pack())
    for a, b in zip(d.acc_mg, acc):
        assert abs(a - min(max(b, -32768), 32767)) <= 0.5 + 1e-9
    for a, b in zip(d.gyro_dps, gyro):
        assert abs(a - min(max(b, -3276.8), 3276.7)) <= 0.05 + 1e-9
    assert d.samples == min(samples, 255)


def test_command_heartbeat_fault_roundtrip():
    for msg in (P.Command(P.CMD_SET_RATE, 90), P.Heartbeat(12, 29.9, 3, -5, P.FAULT_IMU),
                P.Fault(P.FAULT_CAMERA, P.FAULT_CAMERA, 7)):
        d = P.decode_message(P.FrameDecoder().feed(msg.encode(3, 4))[0])
        assert d == msg


# -- the decoder never raises ------------------------------------------------------------

@settings(max_examples=500, deadline=None)
@given(st.lists(st.binary(max_size=90), max_size=8))
def test_decoder_never_raises_on_any_bytes(chunks):
    d = P.FrameDecoder(known_types=P.SURFACE_LINK_TYPES)
    for c in chunks:
        for f in d.feed(c):
            P.decode_message(f)
    good = P.Surface(class_id=2).encode(9, 9)
    assert [f.seq for f in d.feed(b"\x00" + good)] == [9]     # resync at the next zero


def test_unknown_types_and_newer_versions_are_skipped_and_counted():
    d = P.FrameDecoder(known_types=P.SURFACE_LINK_TYPES)
    body = P.HEADER.pack(2, P.MsgType.SURFACE, 1, 0) + P.Surface().pack()
    newer = P.cobs_encode(body + P.crc16(body).to_bytes(2, "little")) + b"\x00"
    frames = d.feed(P.encode_frame(0x0E, b"abc", 1, 0) + newer + P.Surface().encode(2, 0))
    assert [f.seq for f in frames] == [2]
    assert (d.unknown_type, d.newer_version, d.frames_ok) == (1, 1, 1)
    # without a type filter the framing layer passes it on; the message layer skips it
    raw = P.FrameDecoder().feed(P.encode_frame(0x0E, b"abc", 1, 0))
    assert P.decode_message(raw[0]) is None


def test_short_payload_is_not_a_message_but_longer_is_accepted():
    short = P.FrameDecoder().feed(P.encode_frame(P.MsgType.SURFACE, b"\x01" * 5, 1, 0))[0]
    assert P.decode_message(short) is None
    longer = P.FrameDecoder().feed(P.encode_frame(P.MsgType.COMMAND, b"\x01\x02\x00\xff", 1, 0))[0]
    assert P.decode_message(longer) == P.Command(1, 2)


def test_sequence_gaps_count_drops_and_big_jumps_count_restarts():
    d = P.FrameDecoder()
    wire = b"".join(P.Surface().encode(s, 0) for s in (65534, 65535, 2, 3, 40000))
    assert len(d.feed(wire)) == 5
    assert (d.drops, d.restarts) == (2, 1)      # 0 and 1 missing across the wrap


def test_over_long_frames_are_dropped_and_counted():
    d = P.FrameDecoder()
    frames = d.feed(P.cobs_encode(bytes(range(1, 200))) + b"\x00" + P.Surface().encode(5, 0))
    assert [f.seq for f in frames] == [5] and d.too_long == 1


def test_encode_frame_errors_name_the_field():
    with pytest.raises(ValueError, match="msg_type"):
        P.encode_frame(300, b"", 0, 0)
    with pytest.raises(ValueError, match="payload of 60 bytes"):
        P.encode_frame(1, bytes(60), 0, 0)


def test_protocol_fault_bits_are_the_one_table():
    from device.pi import faults
    for bit, name in faults.FAULT_NAMES.items():
        assert P.FAULT_NAMES[bit] == name
    assert P.fault_names(P.FAULT_CAMERA | P.FAULT_NO_DOME) == ["no_dome", "camera"]


def test_docs_quote_every_golden_vector_and_the_table_sizes():
    doc = (ROOT / "docs" / "protocol.md").read_text()
    for v in VECTORS["messages"]:
        assert v["wire_hex"] in doc, v["name"]
    for t, cls in P.MESSAGES.items():
        n = cls.layout.size
        assert f"| 0x{t:02X} | " in doc
        assert f"| {n} | {n + 12} |" in doc, (hex(t), n)


# -- boundaries the mutation tester found untested (issue 24) ------------------------------

@pytest.mark.parametrize("class_id, name", [(0, "no-touch"), (3, "slippery"), (4, "unknown"),
                                            (P.CLASS_UNKNOWN, "unknown"), (-1, "unknown")])
def test_class_name_of_every_class_and_of_unknown(class_id, name):
    assert P.Surface(class_id=class_id).class_name == name
    assert P.message_dict(P.Surface(class_id=class_id))["class_name"] == name


@pytest.mark.parametrize("probs", [(0.5, 0.25), (0.5, 0.25, 0.1, 0.1, 0.9), 0.5, None, "abcd"])
def test_a_wrong_length_sequence_is_padded_with_zero_and_flagged(probs):
    s = P.Surface.unpack(P.Surface(class_id=1, probs=probs).pack())
    assert s.faults == P.FAULT_NONFINITE
    if isinstance(probs, tuple):
        want = (list(probs) + [0.0] * 4)[:4]
        assert [round(p * 255) for p in s.probs] == [round(p * 255) for p in want]
    # a gait velocity given as one number is the x velocity, unflagged
    g = P.Gait.unpack(P.Gait(vel_mm_s=-12.0).pack())
    assert g.vel_mm_s == (-12.0, 0.0, 0.0) and g.flags == 0
    g = P.Gait.unpack(P.Gait(vel_mm_s=(1.0, 2.0)).pack())
    assert g.vel_mm_s == (1.0, 2.0, 0.0) and g.flags == P.GAIT_FLAG_NONFINITE


def test_a_frame_of_exactly_64_bytes_is_legal_and_65_is_too_long():
    payload = bytes(range(1, P.MAX_FRAME - P.MIN_FRAME + 1))        # 54 bytes
    wire = P.encode_frame(0x20, payload, 7, 8)
    d = P.FrameDecoder()
    assert [(f.msg_type, f.seq, f.t_ms, f.payload) for f in d.feed(wire)] == [(0x20, 7, 8, payload)]
    assert d.too_long == 0 and d.frames_ok == 1
    with pytest.raises(ValueError, match="65-byte"):
        P.encode_frame(0x20, payload + b"\x01", 7, 8)
    body = P.HEADER.pack(1, 0x20, 8, 8) + payload + b"\x01"
    d.feed(P.cobs_encode(body + P.crc16(body).to_bytes(2, "little")) + b"\x00")
    assert (d.too_long, d.frames_ok) == (1, 1)
    # a smaller limit counts a frame one byte over it as too long, one at it as good
    small = P.FrameDecoder(max_frame=12)
    assert len(small.feed(P.encode_frame(1, b"ab", 1, 0) + P.encode_frame(1, b"abc", 2, 0))) == 1
    assert small.too_long == 1


@settings(max_examples=50, deadline=None)
@given(st.binary(max_size=80), st.integers(0, 0xFFFF))
def test_crc16_of_a_list_of_ints_equals_the_crc_of_the_bytes(data, start):
    assert P.crc16(list(data), start) == P.crc16(data, start)
    assert P.crc16(iter(data), start) == P.crc16(bytes(data), start)


def test_crc16_table_path_check_value():
    assert P.crc16(list(b"123456789")) == 0x29B1
    assert P.crc16([0x00]) == 0xE1F0 and P.crc16([0xFF]) == 0xFF00


# (message, field, largest value on the wire, the decoded attribute, how it reads back)
_SATURATING = [
    (P.Surface, "shear_px", 655.35, "shear_px"),
    (P.Surface, "load_n", 655.35, "load_n"),
    (P.Surface, "pins", 0xFFFF, "pins"),
    (P.ImuSummary, "acc_peak_mg", 0xFFFF, "acc_peak_mg"),
    (P.ImuSummary, "samples", 255, "samples"),
    (P.Heartbeat, "rate_fps", 6553.5, "rate_fps"),
    (P.Heartbeat, "frames_dropped", 0xFFFF, "frames_dropped"),
    (P.Heartbeat, "uptime_s", 0xFFFFFFFF, "uptime_s"),
    (P.Heartbeat, "temp_c", 127, "temp_c"),
    (P.Fault, "pins_lost", 0xFFFF, "pins_lost"),
    (P.Fault, "raised", 0xFFFF, "raised"),
]


@pytest.mark.parametrize("cls, field, top, attr", _SATURATING)
def test_each_field_saturates_at_its_largest_wire_value_and_flags(cls, field, top, attr):
    exact = cls.unpack(cls(**{field: top}).pack())
    assert getattr(exact, attr) == pytest.approx(top)
    assert not exact.faults
    step = 1 if isinstance(top, int) else 0.1
    over = cls.unpack(cls(**{field: top + step}).pack())
    assert getattr(over, attr) == pytest.approx(top)
    assert over.faults == P.FAULT_CLAMPED


def test_faults_and_signed_fields_saturate_at_both_ends():
    f = P.Fault.unpack(P.Fault(faults=0x1FFFF).pack())
    assert f.faults == 0xFFFF
    f = P.Fault.unpack(P.Fault(faults=0xFFFF).pack())
    assert f.faults == 0xFFFF
    h = P.Heartbeat.unpack(P.Heartbeat(temp_c=-500, faults=P.FAULT_IMU).pack())
    assert h.temp_c == -128 and h.faults == P.FAULT_IMU | P.FAULT_CLAMPED
    s = P.Surface.unpack(P.Surface(faults=1 << 20).pack())
    assert s.faults == 0xFFFF
    i = P.ImuSummary.unpack(P.ImuSummary(acc_mg=(40000, -40000, 32767),
                                         gyro_dps=(3276.7, -3276.8, 5000)).pack())
    assert i.acc_mg == (32767, -32768, 32767) and i.gyro_dps == (3276.7, -3276.8, 3276.7)
    assert i.faults == P.FAULT_CLAMPED
    g = P.Gait.unpack(P.Gait(load_n=6553.5, vel_mm_s=(32767, -32768, 0)).pack())
    assert g.load_n == 6553.5 and g.flags == 0
    g = P.Gait.unpack(P.Gait(load_n=7000.0, phase=5).pack())
    assert g.load_n == 6553.5 and g.phase == 1 and g.flags == P.GAIT_FLAG_CLAMPED
    c = P.Command.unpack(P.Command(P.CMD_SET_RATE, 70000).pack())
    assert c.arg == 0xFFFF and P.Command.unpack(P.Command(P.CMD_SET_RATE, 0xFFFF).pack()).arg == 0xFFFF


def test_message_dict_holds_every_field_and_the_names_of_type_class_command_and_faults():
    """The JSON dict of a message: its type's name, every field (tuples as lists), the
    class and command names, and the fault bits also by name."""
    s = P.Surface(class_id=1, probs=(0.1, 0.7, 0.2, 0.0), contact=True, slip=False,
                  slip_conf=0.25, shear_dir_deg=90.0, shear_px=1.5, load_n=3.0, pins=133,
                  faults=P.FAULT_CLAMPED, texture_id=2)
    assert P.message_dict(s) == {
        "type": "surface", "class_id": 1, "probs": [0.1, 0.7, 0.2, 0.0], "contact": True,
        "slip": False, "slip_conf": 0.25, "shear_dir_deg": 90.0, "shear_px": 1.5,
        "load_n": 3.0, "pins": 133, "faults": P.FAULT_CLAMPED, "texture_id": 2,
        "class_name": "hard", "faults_names": ["clamped"]}
    f = P.Fault(faults=P.FAULT_CLAMPED | P.FAULT_CAMERA, raised=P.FAULT_CAMERA, pins_lost=3)
    assert P.message_dict(f) == {
        "type": "fault", "faults": P.FAULT_CLAMPED | P.FAULT_CAMERA, "raised": P.FAULT_CAMERA,
        "pins_lost": 3, "faults_names": ["camera", "clamped"], "raised_names": ["camera"]}
    assert P.message_dict(P.Command(P.CMD_SET_RATE, 90)) == {
        "type": "command", "command": P.CMD_SET_RATE, "arg": 90, "command_name": "set_rate"}
    assert P.message_dict(P.Command(9))["command_name"] == "unknown"
    assert P.message_dict(P.Gait(P.PHASE_SWING, 2.5, (1.0, -2.0, 0.0), 0)) == {
        "type": "gait", "phase": P.PHASE_SWING, "load_n": 2.5, "vel_mm_s": [1.0, -2.0, 0.0],
        "flags": 0}
    assert P.message_dict(P.ImuSummary(samples=3))["type"] == "imu_summary"


# -- one class per message type (issue 31) -----------------------------------------------

SIZES = {0x01: 18, 0x02: 17, 0x03: 11, 0x04: 6, 0x10: 10, 0x11: 3}


def test_every_message_type_has_one_class_in_the_one_table():
    assert set(P.MESSAGES) == set(P.MsgType) == set(SIZES) == P.SURFACE_LINK_TYPES
    for t, cls in P.MESSAGES.items():
        assert (cls.msg_type, cls.name, cls.layout.size) == (t, t.name.lower(), SIZES[t])
        assert cls.encode is P.Message.encode and cls.decode.__func__ is P.Message.decode.__func__
        assert "msg_type" not in P.message_dict(cls())     # a class attribute, not a field


def test_a_second_class_for_a_type_or_a_type_without_an_enum_member_is_refused():
    again = type("Again", (P.Message,), {})
    with pytest.raises(ValueError, match="SURFACE \\(0x01\\) already has class Surface, not Again"):
        P.message(P.MsgType.SURFACE, "<B")(again)
    assert P.MESSAGES[P.MsgType.SURFACE] is P.Surface and not hasattr(again, "layout")
    with pytest.raises(ValueError, match="126"):
        P.message(0x7E, "<B")


@pytest.mark.parametrize("cls", list(P.MESSAGES.values()), ids=lambda c: c.name)
def test_decode_needs_the_whole_layout_and_ignores_trailing_bytes(cls):
    payload = cls(faults=P.FAULT_IMU).pack() if "faults" in cls.__dataclass_fields__ \
        else cls().pack()
    assert cls.decode(payload[:-1]) is None and cls.decode(b"") is None
    assert cls.decode(payload) == cls.decode(payload + b"\xff\x01") == cls.unpack(payload)
    raw = P.FrameDecoder().feed(P.encode_frame(cls.msg_type, payload[:-1], 1, 0))[0]
    assert P.decode_message(raw) is None


@pytest.mark.parametrize("command, arg, want", [
    (P.CMD_REZERO, 0, (P.CMD_REZERO, 0)), (255, 0xFFFF, (255, 0xFFFF)),
    (0, 0, (0, 0)), (-1, -1, (0, 0)), (256, 1 << 20, (255, 0xFFFF)),
    ("x", None, (0, 0)), (float("nan"), float("inf"), (0, 0))])
def test_a_command_packs_its_fields_saturated_and_a_bad_value_as_zero(command, arg, want):
    """COMMAND's command is one byte and its argument two: values outside them
    saturate, a value that is not a number is sent as 0; the payload is 3 bytes."""
    p = P.Command(command, arg).pack()
    assert len(p) == 3
    c = P.Command.unpack(p)
    assert (c.command, c.arg) == want


def test_cobs_decode_says_which_zero_byte_it_met():
    """A zero where a block code belongs and a zero inside a block are told apart, with
    the offset of the block."""
    with pytest.raises(ValueError, match=r"^cobs: zero byte at offset 2$"):
        P.cobs_decode(b"\x02\x07\x00")
    with pytest.raises(ValueError, match=r"^cobs: zero byte inside the block at offset 0$"):
        P.cobs_decode(b"\x03\x00\x01")


def test_the_decoder_counts_every_good_and_every_bad_frame():
    """The counters add up: two good frames are 2, two frames with a bad CRC are 2."""
    d = P.FrameDecoder()
    good = P.Surface().encode(1, 0) + P.Surface().encode(2, 0)
    body = bytearray(P.HEADER.pack(P.VERSION, P.MsgType.SURFACE, 3, 0) + P.Surface().pack())
    bad = P.cobs_encode(bytes(body) + ((P.crc16(bytes(body)) ^ 1).to_bytes(2, "little"))) + b"\x00"
    assert len(d.feed(good + bad + bad)) == 2
    assert (d.frames_ok, d.crc_errors) == (2, 2)


def test_a_sequence_gap_of_exactly_max_gap_is_drops_and_one_more_is_a_restart():
    d = P.FrameDecoder(max_gap=5)
    wire = b"".join(P.Surface().encode(s, 0) for s in (0, 6, 13))   # gaps of 5, then 6
    assert len(d.feed(wire)) == 3
    assert (d.drops, d.restarts) == (5, 1)


def test_non_numbers_in_id_fields_are_sent_as_unknown_and_an_array_is_a_sequence():
    """A class or texture id that is not a number goes out as 'unknown' (255), not
    as class 0 (no-touch) or texture 0, flagged; probabilities given as a numpy
    array (the runtime's) are sent like a tuple, without a fault."""
    import numpy as np
    s = P.Surface.unpack(P.Surface(class_id="x", texture_id=None).pack())
    assert (s.class_id, s.texture_id) == (P.CLASS_UNKNOWN, P.TEXTURE_NONE)
    assert s.faults & P.FAULT_NONFINITE
    a = P.Surface.unpack(P.Surface(class_id=1, probs=np.array([0.0, 1.0, 0.0, 0.0])).pack())
    assert a.probs == (0.0, 1.0, 0.0, 0.0) and a.faults == 0


@pytest.mark.parametrize("field, value, sent, clamped", [
    ("probs", (1.0000000000000002, 0.0, 0.0, 0.0), 1.0, False),   # float rounding of 1.0
    ("probs", (1.0019, 0.0, 0.0, 0.0), 1.0, False),                # 255.48: rounds to 255
    ("probs", (1.0021, 0.0, 0.0, 0.0), 1.0, True),                 # 255.54: beyond
    ("slip_conf", 1.0 + 1e-12, 1.0, False),
    ("slip_conf", -0.0019, 0.0, False),                            # -0.48 of a step
    ("slip_conf", -0.0021, 0.0, True),
    ("load_n", 655.354, 655.35, False),
    ("load_n", 655.356, 655.35, True),
    ("load_n", -0.004, 0.0, False),
    ("load_n", -0.006, 0.0, True),
    ("shear_px", 655.3549, 655.35, False),
])
def test_a_value_within_half_a_step_of_a_fields_end_is_that_end_not_clamped(field, value,
                                                                            sent, clamped):
    """`clamped` means a value beyond what the field can carry, not one that rounds to
    its end: a probability of 1.0000000000000002 (float rounding) is 255 unflagged
    (before: flagged, because the test came before the rounding)."""
    s = P.Surface.unpack(P.Surface(**{field: value}).pack())
    got = getattr(s, field)
    got = got[0] if field == "probs" else got
    assert got == pytest.approx(sent, abs=1e-9)
    assert bool(s.faults & P.FAULT_CLAMPED) is clamped
