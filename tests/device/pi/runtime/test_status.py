"""The status file (device/pi/runtime/status.py): replaced whole, never half-written."""
from __future__ import annotations

import json

from device.pi.runtime.status import write_status_file


def test_status_file_is_replaced_whole(tmp_path):
    path = tmp_path / "status.json"
    assert write_status_file(path, {"frames": 1})
    assert write_status_file(str(path), {"frames": 2, "fault_names": ["camera"]})
    assert json.loads(path.read_text()) == {"frames": 2, "fault_names": ["camera"]}
    assert [p.name for p in tmp_path.iterdir()] == ["status.json"]      # no temporary left


def test_an_unwritable_place_is_reported_not_raised(tmp_path):
    assert write_status_file(tmp_path / "missing" / "status.json", {"frames": 1}) is False
