"""host simulate / view / scenes / demo (host/cli/sim.py)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from host.data import dataset
from host.cli import main
from tests.mcapread import read_mcap
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
    # how many are dropped depends on what else the machine runs (under 5 % idle, a
    # quarter beside another busy test worker); the rate is measured by `make bench`,
    # this only catches a loop that falls behind on most frames
    assert rt["frames_dropped_behind"] <= 0.5 * res["frames"]
    assert res["decoder"]["crc_errors"] == 0 and res["runtime"]["packets_dropped"] == 0
    assert sorted(p["seq"] for p in packets) == list(range(len(packets)))
    # the demo plays the gait MCU: the runtime decided with its GAIT context ...
    ds = [json.loads(x) for x in (tmp_path / "decisions.jsonl").read_text().splitlines()]
    stance = [d for d in ds if d["gait"] and d["gait"]["stance"]]
    # (a GAIT answers each SURFACE: counted against the frames decided, not those dropped)
    assert res["runtime"]["gait_packets"] > 0.9 * rt["frames"] and len(stance) > 100
    assert all(abs(d["expected_mag_px"] - 8.0 * 0.42) < 1e-3 for d in stance)
    # ... and with it the walk's drag steps come out as the ground truth says
    # (a drag holds over 20 contact frames when every frame is decided; dropped frames
    # thin every segment alike, so the bar scales with the share decided)
    decided = rt["frames"] / res["frames"]
    drags = [r for r in res["segments"]
             if r["action"] == "drag" and r["contact_frames"] > 20 * decided]
    assert len(drags) == 8
    assert sum(r["reported"] == r["truth"] for r in drags) >= 6
    assert sum(p["slip"] for p in surf) > 0
    _check_demo_texture(res, packets, ds)
    # make demo writes out/demo/run.mcap beside the GIF and PNG (with the viz extra)
    from device.pi.runtime.mcaplog import read_log
    assert res["mcap_file"] == str(tmp_path / "run.mcap")
    msgs, complete = read_log(tmp_path / "run.mcap")
    assert complete
    dec = [m for m in msgs if m["topic"] == "/tacfoot/decision"]
    assert [m["data"]["frame"] for m in dec] == [d["frame"] for d in ds]
    gait_in = [m for m in msgs if m["topic"] == "/tacfoot/packets/in"
               and m["data"]["type"] == "gait"]
    assert len(gait_in) == res["runtime"]["gait_packets"]


def _check_demo_texture(res, packets, ds):
    """The demo's texture column is the runtime's: each step's value is the
    majority of the texture ids in the SURFACE packets of its contact frames (named
    in the texture model's classes), beside the simulator's truth; the label names
    the model that decided."""
    from collections import Counter
    from tests import REPO_ROOT
    from host.cli.sim import demo_text
    surf = [p for p in packets if p["type"] == "surface"]
    # each SURFACE packet carries its frame, its texture by name and the truth
    assert [p["frame"] for p in surf] == [d["index"] for d in ds]
    assert all(p["texture"] == (d["texture"] or "-") for p, d in zip(surf, ds))
    assert all((p["texture"] == "-") == (p["texture_id"] == 255) for p in surf)
    assert {p["texture_truth"] for p in surf} == {"-", "smooth", "lego", "concrete"}
    starts = [round(r["t_s"] * 120) for r in res["segments"]] + [res["frames"]]
    rows = [r for r in res["segments"] if r["contact_frames"]]
    for k, r in enumerate(res["segments"]):
        mine = [p for p in surf if starts[k] <= p["frame"] < starts[k + 1]
                and p["texture_truth"] != "-"]
        assert len(mine) == r["contact_frames"]
        if mine:
            assert r["texture"] == Counter(p["texture"] for p in mine).most_common(1)[0][0]
            assert r["texture_truth"] == Counter(p["texture_truth"] for p in mine
                                                 ).most_common(1)[0][0]
    # the walk's floors: Lego on one drag step of eight, concrete on one, smooth on six
    drags = [r["texture_truth"] for r in rows if r["action"] == "drag"]
    assert sorted(drags) == ["concrete", "lego"] + ["smooth"] * 6
    text = demo_text(res)
    head = next(x for x in text.splitlines() if "tex-truth" in x)
    assert head.split()[-2:] == ["texture", "tex-truth"]
    table = [x.split() for x in text.splitlines() if x.split()[1:2] in (["lower"], ["drag"],
                                                                          ["lift"])]
    assert [x[-2:] for x in table] == [[r["texture"], r["texture_truth"]] for r in rows]
    # labelled by the model that decided
    sim_model = (REPO_ROOT / "models" / "texture-sim" / "manifest.json").is_file()
    label = res["texture"]["label"]
    if sim_model:
        assert label == ["texture: simulation-trained model (models/texture-sim)"]
        assert res["texture"]["trained_on"]["data"] == "simulated"
    else:
        assert label[0].startswith("texture: real-trained model (models/texture")
        assert "out of domain" in label[1]
    assert all(x in text for x in label)
    ag = res["texture"]["agreement"]
    assert ag["steps"] == len(rows)
    assert ag["frames_right"] == sum(p["texture"] == p["texture_truth"] for p in surf
                                     if p["texture_truth"] != "-")


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


def _manifest(folder, trained_on):
    from tests import REPO_ROOT
    folder.mkdir(parents=True)
    doc = json.loads((REPO_ROOT / "models" / "texture" / "manifest.json").read_text())
    doc["trained_on"] = trained_on
    (folder / "manifest.json").write_text(json.dumps(doc))
    return doc


def test_demo_labels_a_real_texture_model_with_its_manifests_figures(tmp_path):
    from host.cli.sim import _demo_models, _texture_label
    models = tmp_path / "models"
    (models / "surface").mkdir(parents=True)
    doc = _manifest(models / "texture", {"data": "real", "real_accuracy": 0.8123,
                                         "split": "a second recording"})
    out = tmp_path / "out"
    out.mkdir()
    run, tex = _demo_models(out, models)
    assert run == models and tex["folder"] == "models/texture"
    assert not (out / "runtime-models").exists()
    ag = {"steps": 24, "steps_right": 5, "frames": 420, "frames_right": 80, "frames_share": 0.19}
    lines = _texture_label(tex, ag)
    n = doc["metrics"]["test"]["n"]
    assert lines[0] == (f"texture: real-trained model (models/texture): "
                        f"held-out accuracy 0.81 on real frames (n={n}), a second recording")
    assert lines[1] == ("  out of domain on this simulated walk: right on 5 of 24 textured "
                        "steps, 0.19 of their contact frames")
    # a manifest that does not say what the model was trained on is not called real
    tex["spec"].measured.trained_on = {"data": "unknown", "recordings": []}
    lines = _texture_label(tex, ag)
    assert "real" not in lines[0].replace("real or simulated", "")
    assert lines[0].startswith("texture: models/texture, whose manifest does not say")
    assert lines[1].startswith("  on this simulated walk: right on 5 of 24")


def test_demo_runs_a_simulation_trained_texture_model_when_there(tmp_path):
    from host.cli.common import UserError
    from host.cli.sim import _demo_models, _texture_label
    models = tmp_path / "models"
    for name in ("surface", "slip", ".texture.building"):
        (models / name).mkdir(parents=True)
    _manifest(models / "texture", {"data": "real", "real_accuracy": 0.9})
    _manifest(models / "texture-sim", {"data": "simulated"})
    out = tmp_path / "out"
    (out / "runtime-models" / "stale").mkdir(parents=True)       # an earlier demo's
    run, tex = _demo_models(out, models)
    assert run == out / "runtime-models"
    assert sorted(p.name for p in run.iterdir()) == ["slip", "surface", "texture"]
    assert (run / "texture").resolve() == (models / "texture-sim").resolve()
    assert (run / "surface").resolve() == (models / "surface").resolve()
    assert _texture_label(tex, {"steps": 0}) == [
        "texture: simulation-trained model (models/texture-sim)"]
    assert _texture_label({"folder": None, "manifest": None}, {})[0].startswith(
        "texture: no texture model")
    with pytest.raises(UserError, match="no-such"):
        _demo_models(out, tmp_path / "no-such")


def test_simulate_mcap_writes_each_frame_at_its_dataset_time(tmp_path, capsys):
    pytest.importorskip("mcap")
    from device.pi.runtime.mcaplog import CHANNELS
    out, log = tmp_path / "ds", tmp_path / "s.mcap"
    assert main(["simulate", "press-soft", "--out", str(out), "--trials", "2", "--mcap",
                 str(log), "--mcap-image-every", "5", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    chans, msgs = read_mcap(log)
    assert {t: chans[t] for t in CHANNELS} == {t: s["title"] for t, s in CHANNELS.items()}
    assert chans["/tacfoot/labels"] == "tacfoot.Labels"
    trials = [dataset.load_trial(out, i) for i in range(2)]
    n = [len(tr["frames"]) for tr in trials]
    for topic in ("/tacfoot/imu", "/tacfoot/labels"):
        assert [d["frame"] for _, d in msgs[topic]] == list(range(n[0])) + list(range(n[1]))
    assert len(msgs["/tacfoot/grid"]) == n[0] + n[1]          # foxglove.Grid: no frame field
    assert len(msgs["/tacfoot/image"]) == -(-n[0] // 5) + -(-n[1] // 5)
    # the dataset's own frame times, trial 1 a second after trial 0 ends
    t0 = np.asarray(trials[0]["t_s"]) - trials[0]["t_s"][0]
    t_ns = [t for t, _ in msgs["/tacfoot/grid"]]
    assert np.allclose(t_ns[:n[0]], t0 * 1e9, atol=1e3)
    assert abs(t_ns[n[0]] - (t0[-1] + 1.0) * 1e9) <= 1e3
    labels = [d for _, d in msgs["/tacfoot/labels"]]
    assert [x["trial"] for x in labels] == [0] * n[0] + [1] * n[1]
    assert [x["contact"] for x in labels[:n[0]]] == [bool(c) for c in trials[0]["contact"]]
    assert res["mcap"] == {"file": str(log), "messages": sum(len(v) for v in msgs.values())}


def test_simulate_mcap_appends_only_the_new_trials(tmp_path, capsys):
    pytest.importorskip("mcap")
    out = tmp_path / "ds"
    assert main(["simulate", "press-soft", "--out", str(out), "--json"]) == 0
    assert main(["simulate", "press-soft", "--out", str(out), "--seed", "7", "--mcap",
                 str(tmp_path / "s.mcap"), "--json"]) == 0
    _, msgs = read_mcap(tmp_path / "s.mcap")
    assert {d["trial"] for _, d in msgs["/tacfoot/labels"]} == {1}   # the second trial
