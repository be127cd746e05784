"""device/pi/runtime/mcapfiles.py and McapLog's files: a restart never
truncates an earlier run's log (it takes the next free name and says so), the size
limit is bounded and a file overshoots it by at most one capped chunk, a full disk
leaves no empty files, a file cut inside its magic reads as empty, and a writer
stuck on its disk does not hold up the end of the run (issue 29, items 4, 6, 7, 8
and 14)."""
from __future__ import annotations

import errno
import hashlib
import json
import os
import signal
import subprocess
import sys
import threading
import time

import pytest

pytest.importorskip("mcap")

from mcap.reader import make_reader  # noqa: E402

from device.pi.__main__ import main  # noqa: E402
from device.pi.runtime import mcaplog  # noqa: E402
from device.pi.runtime.config import McapConfig  # noqa: E402
from device.pi.runtime.mcapfiles import read_log, recover  # noqa: E402
from device.pi.runtime.mcaplog import McapLog  # noqa: E402
from tests import REPO_ROOT
from tests.mcapread import frame_args, sim_run_command  # noqa: E402

MAGIC = b"\x89MCAP0\r\n"                          # the first 8 bytes of every MCAP file


def _run(tmp_path, *extra, frames=20, config=None):
    return sim_run_command(tmp_path, *extra, frames=frames, config=config)


def _frame_args(k=0, t_s=0.01):
    return frame_args(k, t_s, None)


def _bytes_on_disk(folder) -> int:
    return sum(p.stat().st_size for p in folder.glob("*.mcap"))


def _digest(p) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


# -- item 4: a restart never truncates a log ----------------------------------------

def test_a_restart_with_the_same_path_keeps_the_last_runs_log(tmp_path):
    f = tmp_path / "run.mcap"
    r = subprocess.run(_run(tmp_path, "--mcap", f, frames=20), capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    first, size = _digest(f), _bytes_on_disk(tmp_path)
    st1 = json.loads(r.stdout)
    r = subprocess.run(_run(tmp_path, "--mcap", f, frames=20), capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    new = tmp_path / "run.1.mcap"
    assert _digest(f) == first                     # the first run's bytes, untouched
    assert _bytes_on_disk(tmp_path) > size         # never shrinks
    st = json.loads(r.stdout)
    assert st["mcap_files"] == [str(new)] and st["mcap_file"] == str(new)
    assert st1["mcap_file"] == str(f)              # the status names the file in use
    said = [x for x in r.stderr.splitlines() if "run.1.mcap" in x]
    assert len(said) == 1 and str(f) in said[0]    # one line names both
    msgs, complete = read_log(new)
    assert complete and sum(m["topic"] == "/tacfoot/decision" for m in msgs) == 20


def test_a_log_is_never_truncated_the_next_free_name_is_taken(tmp_path, caplog):
    caplog.set_level("INFO", logger="device.pi.runtime.mcaplog")
    cfg = McapConfig(image_every=1, image_width=32)
    f = tmp_path / "run.mcap"
    stale = {f: b"a crashed run", tmp_path / "run-0003.mcap": b"its third file",
             tmp_path / "run.1-0001.mcap": b"a later run's roll file"}
    for p, data in stale.items():
        p.write_bytes(data)
    log = McapLog(f, cfg, clock=lambda: 0.0, keep_existing=True)
    log.frame(*_frame_args(0))
    log.close()
    assert log.files == [str(tmp_path / "run.2.mcap")] and log.path == f
    assert "run.2.mcap" in caplog.text              # said in one line (INFO)
    for p, data in stale.items():                  # every earlier byte is still there
        assert p.read_bytes() == data
    # a roll file only (the first file removed by hand): the name is still taken
    g = tmp_path / "leg.mcap"
    (tmp_path / "leg-0001.mcap").write_bytes(b"x")
    log = McapLog(g, cfg, clock=lambda: 0.0, keep_existing=True)
    log.close()
    assert log.files == [str(tmp_path / "leg.1.mcap")] and not g.exists()
    assert "leg.1.mcap" in caplog.text
    # a free name is used as given, without a word
    caplog.clear()
    h = tmp_path / "new.mcap"
    log = McapLog(h, cfg, clock=lambda: 0.0, keep_existing=True)
    log.close()
    assert log.files == [str(h)] and caplog.text == ""


def test_a_roll_over_never_truncates_a_file_that_appeared_meanwhile(tmp_path):
    f = tmp_path / "r.mcap"
    log = McapLog(f, McapConfig(image_every=1, image_width=32, chunk_kb=1), max_mb=1,
                  clock=lambda: 0.0, keep_existing=True)
    (tmp_path / "r-0001.mcap").write_bytes(b"someone else's")
    log.max_bytes = 1                              # roll at the next message
    log.frame(*_frame_args(0))
    log.close()
    assert (tmp_path / "r-0001.mcap").read_bytes() == b"someone else's"
    assert str(tmp_path / "r-0001.mcap") not in log.files
    assert log.files[1] == str(tmp_path / "r-0002.mcap")


# -- item 6: the size limit is bounded; a file overshoots it by at most a chunk --------

@pytest.mark.parametrize("value", ["inf", "-inf", "nan", "1e-9", "0", "-1", "0.5", "1e12"])
def test_mcap_max_mb_out_of_bounds_is_one_line_and_exit_2(tmp_path, capsys, value):
    rc = main(["run", "--camera", "sim://press-hard", "--imu", "none", "--serial", "loop://",
               "--frames", "2", "--mcap", str(tmp_path / "r.mcap"), f"--mcap-max-mb={value}"])
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1, err
    assert "--mcap-max-mb" in err and f"got {float(value):g}" in err
    assert "Traceback" not in err
    assert not (tmp_path / "r.mcap").exists()


def test_a_file_overshoots_its_limit_by_at_most_a_capped_chunk(tmp_path):
    """The chunk is at most a quarter of the limit: with the default 1 MiB chunk and
    a 1 MB limit, no file ends more than a quarter past it (plus its summary)."""
    import base64
    log = McapLog(tmp_path / "big.mcap", McapConfig(chunk_kb=1024), max_mb=1.0,
                  clock=lambda: 0.0)
    rng = __import__("random").Random(4)
    for k in range(60):                            # ~3.6 MB of barely compressible text
        blob = base64.b64encode(rng.randbytes(45_000)).decode()
        log.write("/tacfoot/decision", k * 1000, {"frame": k, "blob": blob})
    log.close()
    limit = 1024 * 1024
    for p in log.files[:-1]:                       # a chunk of 256 kB, a message of 61 kB
        size = os.path.getsize(p)
        assert limit <= size <= limit + limit // 4 + 64_000 + 64 * 1024, (p, size)
    assert len(log.files) >= 3 and log.messages_lost == 0
    got = [m["data"]["frame"] for p in log.files for m in read_log(p)[0]]
    assert got == list(range(60))


# -- item 7: a full disk leaves no empty files ------------------------------------------

def test_a_full_disk_leaves_no_empty_file_per_retry(tmp_path, caplog, monkeypatch):
    caplog.set_level("WARNING", logger="device.pi.runtime.mcaplog")
    now, full = [0.0], [False]
    real = mcaplog._CountingFile.write

    def write(self, data):
        if full[0]:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, data)
    monkeypatch.setattr(mcaplog._CountingFile, "write", write)
    log = McapLog(tmp_path / "w.mcap", McapConfig(image_every=1, image_width=32, chunk_kb=1),
                  clock=lambda: now[0])
    log.frame(*_frame_args(0))
    log.write("/tacfoot/decision", 0, {"frame": 0, "pad": "x" * 4000})   # a chunk lands
    full[0] = True                                 # the disk fills
    for k in range(1, 9):                          # a retry a second, for 8 s
        now[0] = float(k) * (mcaplog.RETRY_S + 0.01)
        log.frame(*_frame_args(k))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["w.mcap"]
    assert log.files == [str(tmp_path / "w.mcap")]
    assert caplog.text.count("--mcap") == 1        # said once, not a line a retry
    full[0] = False                                # space again: the next name
    now[0] += 10.0
    log.frame(*_frame_args(20))
    log.close()
    assert log.files == [str(tmp_path / "w.mcap"), str(tmp_path / "w-0001.mcap")]
    msgs, complete = read_log(tmp_path / "w-0001.mcap")
    assert complete and {m["data"].get("frame", 20) for m in msgs} == {20}
    assert log.status()["mcap_file"] == str(tmp_path / "w-0001.mcap")


def test_a_file_whose_header_cannot_be_written_is_removed(tmp_path, monkeypatch):
    def write(self, data):
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.setattr(mcaplog._CountingFile, "write", write)
    with pytest.raises(mcaplog.McapLogError, match="No space left"):
        McapLog(tmp_path / "h.mcap", McapConfig())
    assert list(tmp_path.iterdir()) == []


# -- item 8: a file cut inside its magic ------------------------------------------------

@pytest.mark.parametrize("cut", range(0, 9))
def test_a_file_cut_inside_its_magic_reads_as_empty(tmp_path, cut):
    src = tmp_path / "cut.mcap"
    src.write_bytes(MAGIC[:cut])
    assert read_log(src) == ([], False)
    dst = tmp_path / "fixed.mcap"
    assert recover(src, dst) == 0
    with open(dst, "rb") as fh:                    # a well-formed empty log
        assert list(make_reader(fh).iter_messages()) == []


def test_a_file_that_is_not_mcap_is_one_error_naming_it(tmp_path):
    src = tmp_path / "notes.mcap"
    src.write_bytes(b"hello, world")
    with pytest.raises(mcaplog.McapLogError) as e:
        read_log(src)
    assert str(src) in str(e.value) and "\n" not in str(e.value)
    with pytest.raises(mcaplog.McapLogError):
        recover(src, tmp_path / "x.mcap")


# -- item 14: a writer stuck on its disk ------------------------------------------------

def test_close_gives_up_on_a_stuck_writer_and_counts_what_is_lost(tmp_path, monkeypatch):
    """The disk stops taking bytes once the run is on: close() waits at most
    CLOSE_STALL_S without progress (not CLOSE_WAIT_S), and every message is either
    written (in a chunk on disk) or counted lost."""
    stall, released = threading.Event(), threading.Event()
    real = mcaplog._CountingFile.write

    def write(self, data):
        if threading.current_thread().name == "mcap-writer" and not released.is_set():
            stall.set()
            released.wait(60)
        return real(self, data)
    monkeypatch.setattr(mcaplog._CountingFile, "write", write)
    monkeypatch.setattr(mcaplog, "CLOSE_WAIT_S", 60.0)
    log = McapLog(tmp_path / "s.mcap", McapConfig(image_every=1, image_width=32, chunk_kb=1),
                  clock=lambda: 0.0, background=True)
    n = 40
    for k in range(n):
        log.frame(*_frame_args(k, t_s=0.01 * (k + 1)))
    assert stall.wait(30)
    t0 = time.monotonic()
    try:
        log.close()
        took = time.monotonic() - t0
    finally:
        released.set()
    assert took < 30.0                             # not CLOSE_WAIT_S
    total = n * 6                                  # image, pins and four a frame
    assert log.messages_written == 0               # no message reached the disk
    assert log.messages_lost == total
    assert log.status()["mcap_messages_lost"] == total


STALL = """
import sys, threading
import device.pi.runtime.mcaplog as m
real = m._CountingFile.write
def write(self, data):
    if threading.current_thread().name == "mcap-writer":    # the disk stalls
        open(sys.argv[1], "w").close()
        threading.Event().wait()
    return real(self, data)
m._CountingFile.write = write
from device.pi.__main__ import main
sys.exit(main(sys.argv[2:]))
"""


def test_sigterm_with_a_stalled_mcap_disk_exits_0_and_counts_the_loss(tmp_path):
    mark = tmp_path / "stalled"
    # the thread writer (the process writer's stall: test_mcapproc.py)
    cmd = _run(tmp_path, "--mcap", tmp_path / "run.mcap", frames=None,
               config="[mcap]\nchunk_kb = 4\nimage_every = 1\nwriter = \"thread\"\n")
    cmd[cmd.index("sim://walk")] = "sim://walk?realtime=1"
    cmd = [sys.executable, "-c", STALL, str(mark)] + cmd[3:]
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env)
    try:
        t_end = time.monotonic() + 60
        while not mark.exists() and time.monotonic() < t_end:
            assert proc.poll() is None, proc.communicate()[1]
            time.sleep(0.02)
        assert mark.exists()
        time.sleep(0.1)                            # frames queue behind the stalled disk
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    st = json.loads(out)
    assert st["mcap_messages_lost"] > 0 and st["mcap_messages_written"] == 0
