"""host/data/recordings.py: recording ids from files, simulated runs and datasets; the
windows carry them."""
from __future__ import annotations

import numpy as np

from host.data.load import load_spec
from host.data.recordings import file_recording, profile_ref, sim_recording, source_recording


def test_a_file_recording_is_named_by_its_content(tmp_path):
    a = tmp_path / "a.avi"
    a.write_bytes(b"clip bytes")
    (tmp_path / "sub").mkdir()
    b = tmp_path / "sub" / "a.avi"
    b.write_bytes(b"clip bytes")
    ra, rb = file_recording(a), file_recording(b)
    assert ra == rb and len(ra["sha256"]) == 64 and ra["id"].startswith("a.avi sha256:")
    b.write_bytes(b"clip bytes, edited")
    assert file_recording(b)["id"] != ra["id"]
    assert source_recording(f"file://{a}") == ra
    assert source_recording("sim://drag-90?seed=3")["id"] == "simulated:drag-90 seed 3"
    assert sim_recording("x.toml", 2)["id"] == "simulated:x seed 2"
    assert source_recording("v4l2:///dev/video0", 0.0)["id"].startswith("live:v4l2")


def test_profile_ref_hashes_the_parsed_profile():
    r = profile_ref("roboskin")
    assert r["name"] == "roboskin" and len(r["sha256"]) == 64
    assert profile_ref("tactip331")["sha256"] != r["sha256"]
    assert profile_ref("no-such-profile")["sha256"] is None


def test_dataset_windows_carry_the_simulated_recording_and_frame(sim_ds, cache):
    ws = load_spec(str(sim_ds), "surface", 3, progress=False, cache=cache)
    ids = set(ws.recording_ids().tolist())
    assert ids == {"simulated:press-hard seed 0", "simulated:press-hard seed 1",
                   "simulated:press-soft seed 0"}
    assert np.array_equal(ws.frame_index, ws.t_index)      # trials start at frame 0
    assert set(ws.summary()["recordings"]) == ids
    sub = ws.subset(ws.groups == 1)
    assert set(sub.recordings.tolist()) == {"simulated:press-hard seed 1"}


def test_two_rows_of_one_clip_are_one_recording(tmp_path, write_csv, cache):
    man = write_csv(tmp_path / "m.csv", ["path,label,start_frame,end_frame",
                                         "sim://press-hard,hard,0,48",
                                         "sim://press-hard?seed=0,hard,48,96",
                                         "sim://press-soft,soft,,"])
    ws = load_spec(str(man), "surface", 3, progress=False, cache=cache)
    assert set(ws.recording_ids().tolist()) == {"simulated:press-hard seed 0",
                                                "simulated:press-soft seed 0"}
    hard = ws.recording_ids() == "simulated:press-hard seed 0"
    assert ws.frame_index[hard].max() > 48 and ws.frame_index[hard].min() < 48
