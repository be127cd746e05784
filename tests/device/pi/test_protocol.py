"""Wire protocol v1, CPython side (device/pi/protocol.py): CRC, COBS, framing, the
typed messages against the golden vectors, clamping, and a decoder that never
raises; then ``host monitor`` (captured file, loop://, a pty) and its --bench.
The MicroPython side is in test_mpy_link.py."""
from __future__ import annotations
from tests import REPO_ROOT

import json
import math
import sys
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

ROOT = REPO_ROOT
sys.path.insert(0, str(ROOT))

from device.pi import protocol as P  # noqa: E402

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
    out_of_range = shear_px < 0 or shear_px > 655.35 or load_n < 0 or load_n > 655.35 \
        or pins > 65535
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
    body = P.HEADER.pack(2, P.MSG_SURFACE, 1, 0) + P.Surface().pack()
    newer = P.cobs_encode(body + P.crc16(body).to_bytes(2, "little")) + b"\x00"
    frames = d.feed(P.encode_frame(0x0E, b"abc", 1, 0) + newer + P.Surface().encode(2, 0))
    assert [f.seq for f in frames] == [2]
    assert (d.unknown_type, d.newer_version, d.frames_ok) == (1, 1, 1)
    # without a type filter the framing layer passes it on; the message layer skips it
    raw = P.FrameDecoder().feed(P.encode_frame(0x0E, b"abc", 1, 0))
    assert P.decode_message(raw[0]) is None


def test_short_payload_is_not_a_message_but_longer_is_accepted():
    short = P.FrameDecoder().feed(P.encode_frame(P.MSG_SURFACE, b"\x01" * 5, 1, 0))[0]
    assert P.decode_message(short) is None
    longer = P.FrameDecoder().feed(P.encode_frame(P.MSG_COMMAND, b"\x01\x02\x00\xff", 1, 0))[0]
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


# -- host monitor ---------------------------------------------------------------------

def _capture(tmp_path, corrupt: bool = True) -> tuple[Path, list]:
    """100 SURFACE/s for 1 s (seq 0..99), one frame corrupted, one lost."""
    wire, sent = b"", []
    for i in range(100):
        s = P.Surface(i % 4, (0.1, 0.2, 0.3, 0.4), True, False, 0.0, i, i / 10, 5.0, 300, 0, 1)
        w = s.encode(i, 1000 + 10 * i)
        if i == 40 and corrupt:
            body = bytearray(P.cobs_decode(w[:-1]))
            body[10] ^= 0x10
            w = P.cobs_encode(body) + b"\x00"
        elif i == 70:
            continue                      # lost on the way
        else:
            sent.append((i, P.Surface.unpack(s.pack())))
        wire += w
    path = tmp_path / "capture.bin"
    path.write_bytes(b"\x17\x99" + wire)   # starts mid-frame, as a capture does
    return path, sent


def test_monitor_cli_on_a_captured_file_json(tmp_path, capsys):
    from host.cli import main
    path, sent = _capture(tmp_path)
    assert main(["monitor", str(path), "--json"]) == 0
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    msgs, summary = lines[:-1], lines[-1]
    assert summary["kind"] == "summary" and summary["stopped_by"] == "eof"
    # the first frame is swallowed by the partial bytes before it (resync at its end)
    expect = sent[1:]
    assert [(m["seq"], m["class_id"], m["shear_px"]) for m in msgs] == [
        (i, s.class_id, s.shear_px) for i, s in expect]
    assert summary["crc_errors"] == 1 and summary["drops"] == 2   # seq 40 and 70
    assert summary["messages"]["surface"] == len(expect)
    # received rate over the last 50 SURFACE (seq 49..99 without 70): 49 in 500 ms
    assert summary["rate_hz"] == round(49 * 1000 / 500, 3)
    assert summary["latest"]["surface"]["seq"] == 99


def test_monitor_text_output_tty_and_pipe(tmp_path):
    import io

    from host.monitor import run_monitor
    path, _ = _capture(tmp_path)
    buf = io.StringIO()
    snap = run_monitor(str(path), tty=True, out=buf)
    text = buf.getvalue()
    assert text.startswith("\r\x1b[2K") and text.endswith("\n")
    assert " 98.0 Hz" in text and "crc 1" in text and "drops 2" in text
    assert snap["latest"]["surface"]["class_name"] == P.SURFACE_CLASSES[99 % 4]
    buf = io.StringIO()
    run_monitor(str(path), tty=False, out=buf)      # a pipe: one final line for a file
    assert buf.getvalue().count("\n") == 1 and "\r" not in buf.getvalue()


def test_monitor_on_loop_url_stops_at_count():
    import io

    import serial

    from host.monitor import run_monitor
    port = serial.serial_for_url("loop://", timeout=0.05)
    frames = [P.Surface(2).encode(i, 10 * i) for i in range(10)]
    port.write(b"".join(frames) + P.Heartbeat(1, 30.0).encode(10, 100))
    buf = io.StringIO()
    snap = run_monitor(port, as_json=True, count=4, out=buf)
    lines = [json.loads(x) for x in buf.getvalue().splitlines()]
    assert [m["seq"] for m in lines[:-1]] == [0, 1, 2, 3]
    assert snap["stopped_by"] == "count" and lines[-1]["messages_total"] == 4


def test_monitor_on_a_pty_and_seconds_limit(capsys):
    import os
    import threading
    import time
    import tty

    from host.cli import main
    master, slave = os.openpty()
    try:
        tty.setraw(slave)                 # no line discipline: bytes pass unchanged
        name = os.ttyname(slave)
        # pyserial flushes the input when it opens the port, so the far end keeps
        # sending (as the Pi does) until the monitor has what it asked for
        stop = threading.Event()

        def far_end():
            i = 0
            while not stop.is_set() and i < 2000:
                os.write(master, P.Surface(3, slip=True).encode(i, 33 * i))
                i += 1
                time.sleep(0.01)

        writer = threading.Thread(target=far_end)
        writer.start()
        try:
            assert main(["monitor", name, "--json", "--count", "5", "--seconds", "20"]) == 0
        finally:
            stop.set()
            writer.join()
        lines = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
        seqs = [m["seq"] for m in lines[:-1]]
        assert len(seqs) == 5 and seqs == list(range(seqs[0], seqs[0] + 5))
        assert lines[-1]["stopped_by"] == "count"
        assert all(m["slip"] and m["class_name"] == "slippery" for m in lines[:-1])
        t0 = time.monotonic()
        assert main(["monitor", name, "--json", "--seconds", "0.3"]) == 0   # nothing more
        assert 0.25 < time.monotonic() - t0 < 3
        last = json.loads(capsys.readouterr().out.splitlines()[-1])
        assert last["stopped_by"] == "seconds" and last["frames_ok"] == 0
    finally:
        os.close(master)
        os.close(slave)


def test_monitor_bad_input_is_one_line_and_exit_2(capsys):
    from host.cli import main
    assert main(["monitor", "/nonexistent/port"]) == 2
    err = capsys.readouterr().err
    assert "host monitor: error:" in err and "/nonexistent/port" in err
    assert main(["monitor", "loop://", "--count", "0"]) == 2
    assert "--count" in capsys.readouterr().err


def test_docs_quote_every_golden_vector_and_the_table_sizes():
    doc = (ROOT / "docs" / "protocol.md").read_text()
    for v in VECTORS["messages"]:
        assert v["wire_hex"] in doc, v["name"]
    for t, n in P.PAYLOAD_LEN.items():
        assert f"| 0x{t:02X} | " in doc
        assert f"| {n} | {n + 12} |" in doc, (hex(t), n)


def test_bench_reports_size_and_an_estimate_under_the_goal():
    from host.monitor import bench_link
    r = bench_link(repeats=300, mpy_packets=500)
    assert r["surface_wire_bytes"] == len(P.Surface().encode(0, 0)) <= 32
    assert r["cpython"]["decode"]["median_us"] > 0
    assert 0 < r["rp2040_estimate_us"]["at_2us_per_iteration"] < r["goal_us"]
    assert r["bytecodes_per_packet"] > 10 * r["surface_wire_bytes"]   # counted, not guessed


def test_monitor_on_a_socket_url():
    import io
    import socket
    import threading
    import time

    from host.monitor import run_monitor
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)
    stop = threading.Event()

    def serve():                          # a Pi streaming SURFACE at ~100 Hz
        conn, _ = srv.accept()
        i = 0
        try:                              # pyserial discards what is waiting at open
            while not stop.is_set() and i < 2000:
                conn.sendall(P.Surface(1).encode(i, 10 * i))
                i += 1
                time.sleep(0.01)
        except OSError:
            pass
        conn.close()

    th = threading.Thread(target=serve)
    th.start()
    try:
        buf = io.StringIO()
        snap = run_monitor(f"socket://127.0.0.1:{srv.getsockname()[1]}", as_json=True,
                           count=6, seconds=20, out=buf)
    finally:
        stop.set()
        th.join(timeout=5)
        srv.close()
    assert snap["stopped_by"] == "count"
    seqs = [json.loads(x)["seq"] for x in buf.getvalue().splitlines()[:-1]]
    assert len(seqs) == 6 and seqs == list(range(seqs[0], seqs[0] + 6))


def test_monitor_ctrl_c_on_a_port_ends_with_the_summary():
    import io

    from host.monitor import run_monitor

    class Port:                            # a live port; the user presses Ctrl-C
        is_file = False
        closed = False

        def __init__(self):
            self.chunks = [P.Surface(2).encode(0, 0), b"", P.Surface(2).encode(1, 33)]

        def read(self):
            if not self.chunks:
                raise KeyboardInterrupt
            return self.chunks.pop(0)

        def close(self):
            self.closed = True

    port = Port()
    buf = io.StringIO()
    snap = run_monitor(port, as_json=True, out=buf)
    assert snap["stopped_by"] == "interrupted" and snap["messages_total"] == 2
    assert port.closed
    assert json.loads(buf.getvalue().splitlines()[-1])["kind"] == "summary"
