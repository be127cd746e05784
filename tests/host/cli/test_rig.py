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
    for topic in ("/tacfoot/grid", "/tacfoot/imu", "/tacfoot/labels"):
        assert [d["frame"] for _, d in msgs[topic]] == list(range(24)), topic
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
