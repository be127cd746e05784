"""host export mcap (host/cli/export.py): a dataset folder as the leg's MCAP
channels, read back with mcap's reader: one grid, IMU and label message per frame,
the images and one annotation point per detected pin, the labels named."""
from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("mcap")

from mcap.reader import make_reader  # noqa: E402

from host.cli import main  # noqa: E402
from host.data.dataset import load_trial, read_index  # noqa: E402
from host.data.simulate import simulate_to_dataset  # noqa: E402


def test_export_mcap_writes_the_leg_channels_and_the_labels(tmp_path, capsys):
    ds = tmp_path / "ds"
    simulate_to_dataset("minimal", ds, trials=2, progress=False)
    out = tmp_path / "ds.mcap"
    assert main(["export", "mcap", str(ds), "--out", str(out), "--image-every", "2",
                 "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    doc = read_index(ds)
    n = [t["frames"] for t in doc["trials"]]
    assert res["trials"] == 2 and res["frames"] == sum(n)
    by = {}
    with open(out, "rb") as fh:
        for schema, ch, msg in make_reader(fh).iter_messages(log_time_order=False):
            by.setdefault(ch.topic, []).append((schema.name, msg.log_time,
                                                json.loads(msg.data)))
    assert res["messages"] == sum(len(v) for v in by.values())
    assert {t: v[0][0] for t, v in by.items()} == {
        "/tacfoot/image": "foxglove.CompressedImage",
        "/tacfoot/pins": "foxglove.ImageAnnotations", "/tacfoot/grid": "foxglove.Grid",
        "/tacfoot/imu": "tacfoot.Imu", "/tacfoot/labels": "tacfoot.Labels"}
    for topic in ("/tacfoot/grid", "/tacfoot/imu", "/tacfoot/labels"):
        assert len(by[topic]) == sum(n), topic
    assert len(by["/tacfoot/image"]) == sum(-(-k // 2) for k in n)
    labels = [m[2] for m in by["/tacfoot/labels"]]
    t0 = load_trial(ds, 0)
    want = [doc["surface_labels"][c] for c in t0["surface"]]
    assert [x["surface"] for x in labels[:n[0]]] == want
    assert [x["contact"] for x in labels[:n[0]]] == [bool(c) for c in t0["contact"]]
    assert [x["trial"] for x in labels] == [0] * n[0] + [1] * n[1]
    times = [m[1] for m in by["/tacfoot/labels"]]
    assert times == sorted(times) and times[n[0]] - times[n[0] - 1] >= 10**9   # trial gap
    imu = np.array([m[2]["acc_g"] for m in by["/tacfoot/imu"][:n[0]]])
    assert np.allclose(imu, t0["imu"][:, :3], atol=1e-4)
    for _, _, ann in by["/tacfoot/pins"]:
        assert ann["points"][0]["type"] == 1 and len(ann["points"][0]["points"]) > 0


def test_export_mcap_refuses_a_missing_folder_and_a_bad_out(tmp_path, capsys):
    assert main(["export", "mcap", str(tmp_path / "nope"), "--out",
                 str(tmp_path / "x.mcap")]) == 2
    assert "nope" in capsys.readouterr().err
    ds = tmp_path / "ds"
    simulate_to_dataset("minimal", ds, progress=False)
    assert main(["export", "mcap", str(ds), "--out", str(tmp_path / "no" / "x.mcap")]) == 2
    err = capsys.readouterr().err
    assert "--out" in err and "does not exist" in err
