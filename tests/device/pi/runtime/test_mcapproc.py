"""device/pi/runtime/mcapproc.py: the MCAP log written by a child process. What the
loop hands over reaches the file whole and in order; a bad path is refused at
start-up in one line; a Ctrl-C to the group does not stop the writer; a writer that
dies or stalls is a count and one warning, never an exception into the loop, and
close() stays bounded; a runtime killed outright still leaves a complete file."""
from __future__ import annotations

import json
import logging
import os
import signal
import time

import pytest

pytest.importorskip("mcap")

from device.pi.runtime import mcapproc  # noqa: E402
from device.pi.runtime.config import McapConfig  # noqa: E402
from device.pi.runtime.mcaplog import McapLogError, read_log  # noqa: E402
from device.pi.runtime.mcapproc import McapProcess  # noqa: E402
from tests.mcapread import frame_args, kill_when_logged, read_mcap  # noqa: E402


def _log(tmp_path, **kw):
    return McapProcess(tmp_path / "run.mcap", McapConfig(image_every=2), clock=time.monotonic,
                       **kw)


def test_every_frame_reaches_the_file_in_order_and_the_counts_agree(tmp_path):
    m = _log(tmp_path, metadata={"version": "x"})
    for k in range(40):
        m.frame(*frame_args(k, 0.01 * k))
    m.close()
    st = m.status()
    chans, msgs = read_mcap(tmp_path / "run.mcap")
    assert [d["frame"] for _, d in msgs["/tacfoot/decision"]] == list(range(40))
    assert len(msgs["/tacfoot/image"]) == 20                  # every 2nd frame, as JPEG
    assert chans["/tacfoot/image"] == "foxglove.CompressedImage"
    assert st["mcap_writer"] == "process" and st["mcap_messages_lost"] == 0
    assert st["mcap_messages_written"] == sum(len(v) for v in msgs.values()) == 40 * 4 + 20 * 2
    assert st["mcap_files"] == [str(tmp_path / "run.mcap")]
    assert m._proc.poll() == 0                                # the child ended by itself


def test_the_writer_runs_below_the_loops_priority(tmp_path):
    m = _log(tmp_path)
    try:
        fields = open(f"/proc/{m._proc.pid}/stat").read().rsplit(")", 1)[1].split()
        assert int(fields[16]) == min(19, os.nice(0) + mcapproc.WRITER_NICE)   # its nice
    finally:
        m.close()


def test_a_bad_path_is_refused_at_start_in_one_line(tmp_path):
    with pytest.raises(McapLogError, match="does not exist") as e:
        McapProcess(tmp_path / "nowhere" / "run.mcap", McapConfig(), clock=time.monotonic)
    assert "\n" not in str(e.value)


def test_a_ctrl_c_to_the_group_does_not_stop_the_writer(tmp_path):
    m = _log(tmp_path)
    os.kill(m._proc.pid, signal.SIGINT)
    os.kill(m._proc.pid, signal.SIGTERM)
    for k in range(5):
        m.frame(*frame_args(k, 0.01 * k))
    m.close()
    assert m._proc.returncode == 0
    _, msgs = read_mcap(tmp_path / "run.mcap")
    assert len(msgs["/tacfoot/decision"]) == 5


def test_a_writer_that_dies_is_counted_and_warned_once(tmp_path, caplog):
    m = _log(tmp_path)
    for k in range(5):
        m.frame(*frame_args(k, 0.01 * k))
    m._proc.kill()
    m._proc.wait()
    with caplog.at_level(logging.WARNING, logger="device"):
        for k in range(5, 60):
            m.frame(*frame_args(k, 0.01 * k))       # never raises into the loop
            time.sleep(0.002)
        m.close()
    st = m.status()
    warned = [r for r in caplog.records if "writer process ended" in r.getMessage()]
    assert len(warned) == 1
    # frames 5.. never reached a file: each frame's 4 or 6 messages are counted lost
    assert st["mcap_messages_lost"] >= 55 * 4
    assert st["mcap_messages_written"] + st["mcap_messages_lost"] >= 60 * 4
    # "written" is what reached the file: the chunk the child was filling is lost
    msgs, _ = read_log(tmp_path / "run.mcap")
    assert st["mcap_messages_written"] == len(msgs)


def test_close_is_bounded_when_the_writer_stalls(tmp_path):
    m = _log(tmp_path)
    os.kill(m._proc.pid, signal.SIGSTOP)               # a writer stuck (a hung disk)
    try:
        for k in range(20):
            m.frame(*frame_args(k, 0.01 * k))
        m.close_by = time.monotonic() + 0.3
        t0 = time.monotonic()
        m.close()
        took = time.monotonic() - t0
    finally:
        try:
            os.kill(m._proc.pid, signal.SIGCONT)
        except ProcessLookupError:
            pass
    # within close_by, and so within the runtime's 0.8 s grace after SIGTERM
    assert took < 0.75
    assert m._proc.poll() is not None                  # stopped, not left behind
    assert m.status()["mcap_messages_lost"] >= 20 * 4


def test_a_killed_runtime_still_leaves_a_complete_file(tmp_path):
    f = tmp_path / "killed.mcap"
    kill_when_logged(tmp_path, f, 40_000)
    t_end = time.monotonic() + 30                      # the writer ends the file
    complete = False
    while time.monotonic() < t_end and not complete:
        time.sleep(0.1)
        msgs, complete = read_log(f)
    assert complete
    frames = [x["data"]["frame"] for x in msgs if x["topic"] == "/tacfoot/decision"]
    assert len(frames) >= 3 and frames == list(range(len(frames)))


def test_the_child_refuses_calls_it_does_not_know(tmp_path):
    """Only McapLog's writing methods are called in the child, by name."""
    m = _log(tmp_path)
    m._q.append((json.dumps, {"x": 1}, 1))             # not a writing method: ignored
    m.frame(*frame_args(0, 0.0))
    m.close()
    assert "dumps" not in mcapproc._CALLS
    _, msgs = read_mcap(tmp_path / "run.mcap")
    assert [d["frame"] for _, d in msgs["/tacfoot/decision"]] == [0]
