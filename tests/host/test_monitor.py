"""``host monitor`` (host/monitor.py): surface-link packets decoded from a captured
file, loop://, a pty and a socket, its text and JSON output, bad input, Ctrl-C, and
--bench."""
from __future__ import annotations

import json
from pathlib import Path

from device.pi import protocol as P


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

