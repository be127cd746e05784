"""host simulate / view / scenes / demo (host/cli/sim.py)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from host.data import dataset
from host.cli import main
from host.data.simulate import simulate_to_dataset


def test_simulate_writes_a_dataset_that_reads_back(tmp_path, capsys):
    out = tmp_path / "ds"
    rc = main(["simulate", "press-soft", "--out", str(out), "--seed", "4", "--trials", "2",
               "--json"])
    assert rc == 0
    res = json.loads(capsys.readouterr().out)
    assert len(res["trials"]) == 2
    idx = dataset.read_index(out)
    assert [t["seed"] for t in idx["trials"]] == [4, 5]
    tr = dataset.load_trial(out, 1)
    from device.sim import Simulator, load_scene
    sim = Simulator(load_scene("press-soft"), seed=5)
    assert tr["frames"].shape == (sim.n_frames, 480, 640)
    assert np.array_equal(tr["frames"][30], sim.render(30))
    assert np.array_equal(tr["pins_px"], sim.truth["pins_px"])
    assert tr["info"]["profile"] == "roboskin" and tr["info"]["n_pins"] == 133
    assert idx["surface_labels"][0] == "no-touch"


@pytest.mark.parametrize("suffix", ["gif", "png"])
def test_view_draws_scene_and_dataset(tmp_path, suffix, capsys):
    out = tmp_path / f"p.{suffix}"
    assert main(["view", "drag-90", "--out", str(out), "--max-frames", "4"]) == 0
    from PIL import Image
    im = Image.open(out)
    assert im.size[0] > 100
    if suffix == "gif":
        assert getattr(im, "n_frames", 1) == 4
    ds = tmp_path / "ds"
    simulate_to_dataset("drag-90", ds, progress=False)
    out2 = tmp_path / f"d.{suffix}"
    assert main(["view", str(ds), "--out", str(out2)]) == 0
    im2 = Image.open(out2)
    assert im2.size == im.size and np.asarray(im2.convert("L")).std() > 1.0   # not blank


def test_view_bad_suffix_is_exit_2(tmp_path, capsys):
    assert main(["view", "drag-90", "--out", str(tmp_path / "x.jpg")]) == 2
    assert ".gif or .png" in capsys.readouterr().err


def test_scenes_json_lists_every_builtin(capsys):
    assert main(["scenes", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    names = {r["name"] for r in rows}
    assert {"walk", "no-touch", "slip-onset"} <= names
    assert all(r["frames"] > 0 for r in rows)


def test_demo_writes_preview_and_truth_plot(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    from PIL import Image
    gif = Image.open(tmp_path / "preview.gif")
    assert gif.n_frames > 10 and min(gif.size) > 100
    png = Image.open(tmp_path / "ground_truth.png")
    assert min(png.size) > 100 and np.asarray(png.convert("L")).std() > 1.0
    assert res["contact_frames"] > 0 and res["slip_frames"] > 0
    # the real runtime ran on the simulated hardware; every packet it sent was decoded
    packets = [json.loads(x) for x in (tmp_path / "packets.jsonl").read_text().splitlines()]
    kinds = {p["type"] for p in packets}
    assert {"surface", "heartbeat", "imu_summary"} <= kinds
    surf = [p for p in packets if p["type"] == "surface"]
    # the camera is paced at the scene's rate, so a frame the loop was too late for
    # is dropped (newest wins) and counted; every frame is either decided or counted
    rt = res["runtime"]
    assert len(surf) == rt["frames"] and rt["frames"] + rt["frames_dropped_behind"] == res["frames"]
    assert rt["frames_dropped_behind"] <= 0.05 * res["frames"]
    assert res["decoder"]["crc_errors"] == 0 and res["runtime"]["packets_dropped"] == 0
    assert sorted(p["seq"] for p in packets) == list(range(len(packets)))
    # the demo plays the gait MCU: the runtime decided with its GAIT context ...
    ds = [json.loads(x) for x in (tmp_path / "decisions.jsonl").read_text().splitlines()]
    stance = [d for d in ds if d["gait"] and d["gait"]["stance"]]
    assert res["runtime"]["gait_packets"] > 0.9 * res["frames"] and len(stance) > 100
    assert all(abs(d["expected_mag_px"] - 8.0 * 0.42) < 1e-3 for d in stance)
    # ... and with it the walk's drag steps come out as the ground truth says
    drags = [r for r in res["segments"] if r["action"] == "drag" and r["contact_frames"] > 20]
    assert len(drags) == 8
    assert sum(r["reported"] == r["truth"] for r in drags) >= 6
    assert sum(p["slip"] for p in surf) > 0


def test_view_runs_the_pipeline_on_recordings(tmp_path, capsys):
    out = tmp_path / "p.gif"
    assert main(["view", "sim://drag-45", "--out", str(out), "--max-frames", "6",
                 "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert 3 <= len(res["frames"]) <= 6 and min(res["frames"]) >= 4   # after the reference
    from tests.realdata import real_data_dir
    clip = real_data_dir("roboskin/north.avi") / "roboskin" / "north.avi"
    png = tmp_path / "north.png"
    assert main(["view", str(clip), "--out", str(png)]) == 0
    from PIL import Image
    im = Image.open(png)
    assert min(im.size) > 100 and np.asarray(im.convert("L")).std() > 1.0


def test_cli_bad_scene_exit_2_no_traceback(tmp_path, capsys):
    p = tmp_path / "bad.toml"
    p.write_text('[surface]\nmu = -0.5\n[[timeline]]\naction = "hold"\nduration_s = 0.1\n')
    rc = main(["simulate", str(p), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2
    assert "surface.mu" in err and "-0.5" in err and "Traceback" not in err
    rc = main(["simulate", "no-such-scene", "--out", str(tmp_path / "o")])
    assert rc == 2 and "unknown scene" in capsys.readouterr().err
