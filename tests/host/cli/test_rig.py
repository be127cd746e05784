"""host record --mcap (host/cli/rig.py): the recorded trial as the leg's MCAP
channels, read back with mcap's reader (the rest of host record and host rig is
tested in tests/host/rig/)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from host.cli import main
from tests.mcapread import read_mcap
from host.data import dataset

mcap = pytest.importorskip("mcap")


def test_record_mcap_writes_the_trial_a_message_per_frame_at_its_time(tmp_path, capsys):
    from device.pi.runtime.mcaplog import CHANNELS
    out, log = tmp_path / "ds", tmp_path / "r.mcap"
    assert main(["record", "--camera", "sim://walk", "--imu", "sim://walk", "--label", "walk",
                 "--frames", "24", "--out", str(out), "--mcap", str(log), "--json"]) == 0
    entry = json.loads(capsys.readouterr().out)
    chans, msgs = read_mcap(log)
    assert {t: chans[t] for t in CHANNELS} == {t: s["title"] for t, s in CHANNELS.items()}
    tr = dataset.load_trial(out, 0)
    for topic in ("/tacfoot/imu", "/tacfoot/labels"):
        assert [d["frame"] for _, d in msgs[topic]] == list(range(24)), topic
    assert len(msgs["/tacfoot/grid"]) == 24                  # foxglove.Grid: no frame field
    assert len(msgs["/tacfoot/image"]) == len(msgs["/tacfoot/pins"]) == 6   # every 4th
    t = np.asarray(tr["t_s"]) - tr["t_s"][0]
    assert np.allclose([x for x, _ in msgs["/tacfoot/grid"]], t * 1e9, atol=1e3)
    imu = np.array([d["acc_g"] + d["gyro_dps"] for _, d in msgs["/tacfoot/imu"]])
    assert np.allclose(imu, tr["imu"], atol=1e-4)                # the recorded rows
    assert {d["texture"] or d["surface"] for _, d in msgs["/tacfoot/labels"]} == {"walk"}
    assert entry["mcap"]["messages"] == sum(len(v) for v in msgs.values())


def test_record_mcap_to_a_missing_folder_records_nothing(tmp_path, capsys):
    out = tmp_path / "ds"
    rc = main(["record", "--camera", "sim://walk", "--label", "walk", "--frames", "4",
               "--out", str(out), "--mcap", str(tmp_path / "nope" / "r.mcap")])
    assert rc == 2 and "does not exist" in capsys.readouterr().err
    assert not (out / "dataset.json").exists()


def test_record_errors_name_the_command_once(tmp_path, capsys):
    """`host record: error: host record: ...` doubled its prefix (issue 33): each
    refusal is one line with the prefix once."""
    import cv2
    noise = tmp_path / "clip"
    noise.mkdir()
    cv2.imwrite(str(noise / "a.png"), np.zeros((64, 64), np.uint8))
    cases = [(["--camera", "sim://no-touch", "--seconds", "1", "--frames", "3"],
              "give --seconds or --frames, not both"),
             (["--camera", "v4l2:///dev/video9", "--frames", "3"],
              "--start/--frames need a file or sim:// source"),
             (["--camera", str(noise), "--frames", "3", "--start", "5"],
              "no frames from frame 5; nothing was added to")]
    for argv, what in cases:
        assert main(["record", *argv, "--label", "x", "--out", str(tmp_path / "d")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("host record: error: ") and what in err[0], err
        assert err[0].count("host record:") == 1, err
