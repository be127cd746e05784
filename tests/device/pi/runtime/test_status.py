"""The status file (device/pi/runtime/status.py): replaced whole, never half-written,
and rewritten by the runtime while it runs."""
from __future__ import annotations

import json

from device.pi.runtime.status import write_status_file
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

