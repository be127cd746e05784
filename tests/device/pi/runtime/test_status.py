"""The status file (device/pi/runtime/status.py): replaced whole, never half-written,
and rewritten by the runtime while it runs."""
from __future__ import annotations

import errno
import io
import json

import pytest

from device.pi.runtime.status import JsonLog, write_status_file
from tests.device.pi.runtime.standins import make_runtime, run_for


def test_status_file_is_replaced_whole(tmp_path):
    path = tmp_path / "status.json"
    assert write_status_file(path, {"frames": 1})
    assert write_status_file(str(path), {"frames": 2, "fault_names": ["camera"]})
    assert json.loads(path.read_text()) == {"frames": 2, "fault_names": ["camera"]}
    assert [p.name for p in tmp_path.iterdir()] == ["status.json"]      # no temporary left


def test_an_unwritable_place_is_reported_not_raised(tmp_path):
    assert write_status_file(tmp_path / "missing" / "status.json", {"frames": 1}) is False


def test_status_file_is_rewritten_atomically(tmp_path):
    path = tmp_path / "status.json"
    seen = []

    def hook(rt):
        if path.exists():
            seen.append(json.loads(path.read_text()))       # never a half-written file
    rt, cam, port = make_runtime(tmp_path, status_path=str(path))
    rt.cfg.status.interval_s = 0.05
    run_for(rt, frames=60, hook=hook)
    doc = json.loads(path.read_text())
    assert {"pid", "t_unix", "frames", "packets_sent", "packets_dropped", "faults",
            "fault_names"} <= set(doc)
    assert doc["frames"] == 60 and doc["packets_sent"] >= 60
    assert len({d["t_unix"] for d in seen}) >= 2



class _Flaky(io.RawIOBase):
    """A binary file that fails (ENOSPC), takes half a line, then recovers."""

    def __init__(self):
        self.data = bytearray()
        self.mode = "fail"

    def writable(self):
        return True

    def write(self, b):
        if self.mode == "fail":
            raise OSError(errno.ENOSPC, "No space left on device")
        if self.mode == "half":
            self.mode = "ok"
            self.data += bytes(b)[:len(b) // 2]
            return len(b) // 2
        self.data += bytes(b)
        return len(b)


def test_json_log_counts_lost_lines_warns_once_and_keeps_lines_whole(caplog):
    fh = _Flaky()
    log = JsonLog(fh, "d.jsonl")
    assert not log.write({"frame": 0}) and not log.write({"frame": 1})
    fh.mode = "half"
    assert not log.write({"frame": 2})
    assert log.write({"frame": 3}) and log.write({"frame": 4})
    assert log.lines_lost == 3 and log.lines_written == 2
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warned) == 1
    assert "warning: --json-log d.jsonl: cannot write (No space left on device)" in warned[0]
    half, *whole = fh.data.decode().splitlines()
    # the half line stands alone; every whole line is one JSON document
    assert [json.loads(x) for x in whole] == [{"frame": 3}, {"frame": 4}]
    with pytest.raises(ValueError):
        json.loads(half)


def test_runtime_status_counts_json_log_lines_lost(tmp_path):
    path = tmp_path / "status.json"
    fh = _Flaky()
    rt, cam, port = make_runtime(tmp_path, status_path=str(path), json_log=fh)
    run_for(rt, frames=5)
    assert json.loads(path.read_text())["json_log_lines_lost"] == 5
