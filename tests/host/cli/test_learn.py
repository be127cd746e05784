"""host train (host.cli.learn) on the paper's kind of data: one recording per class.
Real clips from ../shared/data (skipped without them)."""
from __future__ import annotations

import json
import os
import re
import time
from pathlib import Path

import numpy as np
import pytest

from host.cli import main
from host.learn.tasks import DEFAULT_MODEL, DEFAULT_WINDOW
from tests.realdata import real_data_dir


def _manifest(path, rows):
    path.write_text("path,label\n" + "".join(f"{p},{lab}\n" for p, lab in rows))
    return path


@pytest.fixture(scope="module")
def clips():
    return real_data_dir("roboskin/smooth.avi", "roboskin/concrete.avi") / "roboskin"


def test_one_clip_per_class_trains_with_a_time_split_that_keeps_both_classes(
        tmp_path, clips, capsys):
    """Without --model and --window, one clip per class, contact windows only: the
    held-out split is the end of each clip, both classes are tested, and it says so."""
    # the first 300 frames of each clip: enough contact windows for both splits
    spec = tmp_path / "tex.csv"
    spec.write_text("path,label,start_frame,end_frame\n"
                    f"{clips / 'smooth.avi'},smooth,0,300\n"
                    f"{clips / 'concrete.avi'},concrete,0,300\n")
    out = tmp_path / "model"
    # the identity check has its own tests (tests/host/learn/test_identity.py and
    # test_train.py); this one is about the split
    # (and the session copies theirs, tests/host/learn/test_sessions.py)
    rc = main(["train", "--task", "texture", "--data", str(spec), "--contact-only",
               "--no-identity-check", "--no-session-copies", "--out", str(out), "--json"])
    assert rc == 0
    res = json.loads(capsys.readouterr().out)
    assert res["model"] == DEFAULT_MODEL["texture"] and res["T"] == DEFAULT_WINDOW["texture"]
    man = json.loads((out / "manifest.json").read_text())
    assert man["training"]["sessions"] is False             # the flag reached the spec
    assert res["holdout"].startswith("time split within each trial")
    test = res["metrics"]["test"]
    assert set(test["per_class"]) == {"concrete", "smooth"}
    assert all(v["support"] > 0 for v in test["per_class"].values())
    man = json.loads((out / "manifest.json").read_text())
    assert man["classes"] == ["concrete", "smooth"]
    assert man["training"]["holdout"] == res["holdout"]


def test_a_class_missing_from_training_is_exit_2_naming_it(tmp_path, clips, capsys):
    train = _manifest(tmp_path / "train.csv", [(clips / "smooth.avi", "smooth"),
                                               (clips / "concrete.avi", "concrete")])
    test = _manifest(tmp_path / "test.csv", [(clips / "smooth.avi", "smooth"),
                                             (clips / "concrete.avi", "lego")])
    rc = main(["train", "--task", "texture", "--model", "fnn", "--window", "2",
               "--data", str(train), "--test", str(test), "--contact-only",
               "--out", str(tmp_path / "m")])
    assert rc == 2
    err = capsys.readouterr().err
    assert "lego" in err and "no training windows" in err
    assert not (tmp_path / "m" / "manifest.json").exists()


def test_an_explicit_test_set_is_used_as_given(tmp_path, clips, capsys):
    train = _manifest(tmp_path / "train.csv", [(clips / "smooth.avi", "smooth"),
                                               (clips / "concrete.avi", "concrete")])
    rc = main(["train", "--task", "texture", "--model", "grid-fnn", "--window", "2",
               "--data", str(train), "--test", str(train), "--contact-only",
               "--out", str(tmp_path / "m"), "--json"])
    assert rc == 0
    res = json.loads(capsys.readouterr().out)
    assert res["holdout"] == "given"
    assert res["metrics"]["test"]["n"] == res["metrics"]["train"]["n"]


@pytest.mark.parametrize("argv,msg", [
    (["--jobs", "0"], "--jobs"),
    (["--windows", "1,x"], "--windows: expected whole numbers"),
    (["--seeds", "-3"], "--seeds"),
    (["--sim-windows", "0"], "--sim-windows: every value must be >= 1"),
])
def test_report_refuses_bad_grids_with_exit_2(tmp_path, argv, msg, capsys):
    rc = main(["report", "--out", str(tmp_path / "a.md"), "--work", str(tmp_path / "w"),
               "--data", str(tmp_path)] + argv)
    assert rc == 2
    assert msg in capsys.readouterr().err
    assert not (tmp_path / "a.md").exists()


# -- small windows from an .npz (no video): the output lock, the texture label rule --

def _texture_npz(path, names=("smooth", "lego"), n=24, T=2, M=6, seed=0):
    """Two separable texture classes of n windows each, 4 groups per class."""
    rng = np.random.default_rng(seed)
    v = rng.normal(0, 0.3, (2 * n, T, M, 2))
    v[n:] += 2.0
    np.savez(path, vectors=v, labels=np.array([names[0]] * n + [names[1]] * n),
             contact=np.ones(2 * n, bool), groups=np.arange(2 * n) // (n // 4))
    return path


def test_pressure_data_off_the_profiles_pin_count_is_refused_in_one_line(tmp_path, capsys,
                                                                          monkeypatch):
    """Pressure windows made from recordings with another marker count than the
    profile's pins (the leg would refuse the model) are refused before training,
    naming both (issue 33); a vector set given as .npz (another rig's markers) is not
    held to the profile."""
    import host.cli.learn as learn_cli
    rng = np.random.default_rng(0)
    p = tmp_path / "p.npz"
    np.savez(p, vectors=rng.normal(0, 0.3, (40, 2, 6, 2)), targets=rng.uniform(0, 5, 40),
             contact=np.ones(40, bool), groups=np.arange(40) // 10)
    assert main(["train", "--task", "pressure", "--model", "ridge", "--window", "2",
                 "--data", str(p), "--out", str(tmp_path / "npz"), "--json"]) == 0
    capsys.readouterr()
    real = learn_cli._load_windows

    def as_recordings(*a, **kw):                  # the same windows, cut from recordings
        ws = real(*a, **kw)
        ws.source["trials"] = [dict(t, kind="folder") for t in ws.source["trials"]]
        return ws
    monkeypatch.setattr(learn_cli, "_load_windows", as_recordings)
    out = tmp_path / "m"
    assert main(["train", "--task", "pressure", "--model", "ridge", "--window", "2",
                 "--data", str(p), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "6 markers a frame" in err[0] and "n_pins=133" in err[0]
    assert not (out / "model.onnx").exists()


def test_a_second_train_into_a_locked_out_folder_is_refused_with_one_line(tmp_path, capsys):
    """While one host train holds --out (here: the test holds its lock), another is
    exit 2 with one line and writes nothing; once it is free, training proceeds."""
    from host.data.dataset import lock_folder
    data = _texture_npz(tmp_path / "v.npz")
    out = tmp_path / "m"
    out.mkdir()
    argv = ["train", "--task", "texture", "--window", "2", "--data", str(data),
            "--out", str(out), "--json"]
    fd = lock_folder(out, "held by the test")
    try:
        rc = main(argv)
        err = capsys.readouterr().err.strip()
        assert rc == 2 and len(err.splitlines()) == 1
        assert "another host train is writing a model to this folder" in err
        assert list(out.iterdir()) == []
    finally:
        os.close(fd)
    assert main(argv) == 0
    assert json.loads((out / "manifest.json").read_text())["classes"] == ["lego", "smooth"]


def test_one_host_train_writes_its_manifest_once_with_every_measured_fact(
        tmp_path, capsys, monkeypatch):
    """host train builds the spec, fills in what it measured (the int8 check, the
    recording-identity check, the cost per decision, the training data) and writes
    each manifest once (it used to write manifest.json three times, five with int8)."""
    from device.pi.models.manifest import FLOAT_MANIFEST, MANIFEST

    data = _texture_npz(tmp_path / "v.npz")
    out = tmp_path / "m"
    written = []
    real = os.replace
    monkeypatch.setattr(os, "replace", lambda a, b: written.append(os.path.basename(b))
                        or real(a, b))
    rc = main(["train", "--task", "texture", "--window", "2", "--data", str(data),
               "--out", str(out), "--quantise", "--json"])
    assert rc == 0, capsys.readouterr().err
    doc = json.loads((out / MANIFEST).read_text())
    want = [MANIFEST, FLOAT_MANIFEST] if doc["variant"] == "int8" else [MANIFEST]
    assert [w for w in written if w.startswith("manifest")] == want
    m = doc["measured"]
    assert m["int8"] and m["identity"] and m["trained_on"]["recordings"]
    assert set(m["cost_per_decision"]["files"]) == set(doc["files"])
    assert not {"int8", "identity", "cost_per_decision", "trained_on"} & set(doc["params"])


def test_a_failed_train_leaves_no_empty_out_folder_it_created(tmp_path, capsys):
    data = _texture_npz(tmp_path / "v.npz", names=("smooth", "smooth"))
    out = tmp_path / "new" / "m"
    rc = main(["train", "--task", "texture", "--window", "2", "--data", str(data),
               "--out", str(out)])
    assert rc == 2 and "at least 2 classes" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize("bad, shown", [("no-touch", "'no-touch'"), ("x" * 5000, "'xxxx"),
                                        ("smooth\nlego", r"'smooth\\nlego'")])
def test_train_refuses_texture_labels_host_record_refuses(tmp_path, capsys, bad, shown):
    data = _texture_npz(tmp_path / "v.npz", names=("smooth", bad))
    rc = main(["train", "--task", "texture", "--window", "2", "--data", str(data),
               "--out", str(tmp_path / "m")])
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1
    assert re.search(rf"labels\[24\]( \(a window with contact\))?: a texture label must be "
                     rf"1-64 .* got {shown}", err)
    assert not (tmp_path / "m").exists()


# -- the CNN from the command line ----------------------------------------------------

_TINY_PRESS = """\
[sensor]
profile = "roboskin"
fps = 60
[surface]
preset = "{preset}"
[[timeline]]
action = "hold"
duration_s = 0.05
[[timeline]]
action = "lower"
depth_mm = 3.0
duration_s = 0.1
[[timeline]]
action = "hold"
duration_s = 0.15
[[timeline]]
action = "lift"
duration_s = 0.1
"""


def test_train_cnn_quantise_from_the_command_line(tmp_path, capsys, monkeypatch):
    """--model cnn --quantise, with the default held-out split and with --test: the
    int8 model is calibrated on the training windows and becomes the default; both
    variants load, and each manifest is written once, as for the other kinds (the
    CNN's used to be written three times). (Before the fix: an index out of range,
    or an unbound name.)"""
    pytest.importorskip("torch", reason="the CNN needs PyTorch, the optional 'cnn' extra: "
                                        "make install-cnn")
    import functools

    import host.learn.cnn as cnn
    from device.pi.models.artefact import load_model
    from host.data.simulate import simulate_to_dataset

    ds = tmp_path / "ds"
    for preset in ("hard", "soft"):
        scene = tmp_path / f"{preset}.toml"
        scene.write_text(_TINY_PRESS.format(preset=preset))
        simulate_to_dataset(str(scene), ds, seed=0, trials=2, progress=False)
    # a small, short training (the command's own defaults take minutes)
    monkeypatch.setattr(cnn, "train_cnn",
                        functools.partial(cnn.train_cnn, epochs=2, hidden=16, filters=2))
    # two simulated runs (recordings) per class: whole recordings are held out
    written = []
    real = os.replace
    monkeypatch.setattr(os, "replace", lambda a, b: written.append(os.path.basename(b))
                        or real(a, b))
    for extra, holdout in (([], "grouped split"), (["--test", str(ds)], "given")):
        out = tmp_path / f"m{len(extra)}"
        written.clear()
        rc = main(["train", "--task", "surface", "--model", "cnn", "--window", "2",
                   "--data", str(ds), *extra, "--quantise", "--out", str(out), "--json"])
        res = json.loads(capsys.readouterr().out)
        assert rc == 0 and res["holdout"].startswith(holdout)
        assert "agreement" in res["int8"]
        assert [w for w in written if w.startswith("manifest")] == \
            ["manifest.json", "manifest.float.json"]
        man = json.loads((out / "manifest.json").read_text())
        assert man["measured"]["int8"]["agreement"] == res["int8"]["agreement"]
        assert set(man["measured"]["cost_per_decision"]["files"]) == set(man["files"])
        assert man["variant"] == "int8" and man["model"] == "cnn"
        assert man["classes"] == ["hard", "no-touch", "soft"]
        for m in ("manifest.json", "manifest.float.json"):
            assert load_model(out / m, expect_kind="surface") is not None


def test_eval_without_contact_only_says_to_pass_it_not_to_fix_the_labels(tmp_path, capsys):
    """A texture model trained on contact windows has no no-touch class; evaluated on
    data whose windows without contact are no-touch, the fix is --contact-only."""
    out = tmp_path / "m"
    assert main(["train", "--task", "texture", "--window", "2", "--data",
                 str(_texture_npz(tmp_path / "v.npz")), "--out", str(out)]) == 0
    p = tmp_path / "ok.npz"
    rng = np.random.default_rng(1)
    labels = np.array(["smooth", "lego", "no-touch", "no-touch"] * 4)
    np.savez(p, vectors=rng.normal(0, 0.3, (16, 2, 6, 2)), labels=labels,
             contact=labels != "no-touch")
    capsys.readouterr()
    rc = main(["eval", str(out), "--data", str(p)])
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1
    assert "the model has no no-touch class" in err and "8 of the 16 windows have no contact" in err
    assert "evaluate with --contact-only" in err and "fix the labels" not in err
    assert main(["eval", str(out), "--data", str(p), "--contact-only", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["n_windows"] == 8
    # without --json: a short text summary, not the JSON document (issue 33)
    assert main(["eval", str(out), "--data", str(p), "--contact-only"]) == 0
    text = capsys.readouterr().out
    assert not text.lstrip().startswith("{") and "on 8 windows" in text
    assert "accuracy" in text and "--json prints every figure" in text


# -- host report on the user's own data specs and profile --

def test_report_with_a_missing_recording_in_the_spec_is_one_line_and_exit_2(tmp_path, capsys):
    (tmp_path / "mine.csv").write_text("path,label\nmine_a.avi,lego\nmine_b.avi,smooth\n")
    (tmp_path / "mine_a.avi").write_bytes(b"")
    t0 = time.perf_counter()
    rc = main(["report", "--out", str(tmp_path / "a.md"), "--work", str(tmp_path / "w"),
               "--data", str(tmp_path / "mine.csv"), "--profile", "tactip331"])
    assert time.perf_counter() - t0 < 1.0
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1
    assert "no such file or folder" in err[0] and "mine_b.avi" in err[0]
    assert "Traceback" not in err[0]
    assert not (tmp_path / "w").exists() and not (tmp_path / "a.md").exists()


def test_report_given_the_folder_of_the_authors_clips_says_how_to_make_their_specs(
        tmp_path, capsys):
    (tmp_path / "data" / "roboskin").mkdir(parents=True)
    rc = main(["report", "--out", str(tmp_path / "a.md"), "--work", str(tmp_path / "w"),
               "--data", str(tmp_path / "data")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1
    assert "python -m host.bench.specs --real-data" in err[0]


def test_report_passes_the_specs_and_the_profile_and_names_them_in_its_command(
        tmp_path, monkeypatch, capsys):
    import host.cli.learn as learn

    seen = {}

    def fake(out, work, specs, **kw):
        seen.update(specs=specs, **kw)
        return Path(out)

    monkeypatch.setattr(learn, "build_report", fake)
    rc = main(["report", "--out", str(tmp_path / "a.md"), "--work", str(tmp_path / "w"),
               "--data", "a.csv", "--data", "own-folder", "--profile", "mine.toml",
               "--windows", "2", "--seeds", "0", "--kinds", "grid-fnn", "--real-only"])
    assert rc == 0
    assert seen["specs"] == ["a.csv", "own-folder"] and seen["profile"] == "mine.toml"
    assert seen["real_kinds"] == ["grid-fnn"] and seen["tasks"] == ()
    assert "--data a.csv --data own-folder --profile mine.toml" in seen["command"]


# -- a model carries its sensor: host train --profile, host eval, --config --

def test_train_computes_every_feature_with_its_profile_and_the_model_carries_it(
        tmp_path, capsys):
    """host train --profile tactip331 (331 pins, not 133): the texture roughness
    features use that layout (cmd_train used to drop the profile, so the neighbour
    list came from the 133-pin default and roughness was silently off)."""
    from device.pi.models.classifier import Classifier
    from device.pi.models.window import RollingWindow
    data = _texture_npz(tmp_path / "v.npz", n=16, M=331)
    out = tmp_path / "m"
    assert main(["train", "--task", "texture", "--window", "2", "--data", str(data),
                 "--profile", "tactip331", "--out", str(out), "--json"]) == 0
    man = json.loads((out / "manifest.json").read_text())
    assert man["params"]["roughness"] is True
    assert man["profile"]["name"] == "tactip331" and man["profile"]["n_pins"] == 331
    assert "[vision]" in man["profile"]["toml"]
    clf = Classifier.load(out)
    assert clf.n_features == man["input"]["shape"][1] == \
        RollingWindow(2, 331).encode("vectors").size
    assert man["measured"]["trained_on"]["recordings"][0]["sha256"] and man["config"]["profile"] == \
        "tactip331"
    assert (out / "README.md").is_file() and "331 pins" in (out / "README.md").read_text()
    # eval takes the profile from the model; another profile is an error naming both
    capsys.readouterr()
    assert main(["eval", str(out), "--data", str(data), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["n_windows"] > 0
    rc = main(["eval", str(out), "--data", str(data), "--profile", "roboskin"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1
    assert "roboskin.toml (roboskin, 133 pins" in err and "(tactip331, 331 pins" in err


def test_train_config_replays_the_model_and_refuses_flags_beside_it(tmp_path, capsys):
    data = _texture_npz(tmp_path / "v.npz")
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["train", "--task", "texture", "--window", "2", "--data", str(data),
                 "--seed", "3", "--out", str(a), "--json"]) == 0
    toml = (a / "train.toml").read_text()
    assert 'task = "texture"' in toml and "T = 2" in toml and "seed = 3" in toml
    assert main(["train", "--config", str(a / "train.toml"), "--out", str(b), "--json"]) == 0
    ma, mb = (json.loads((d / "manifest.json").read_text()) for d in (a, b))
    assert ma["config"] == mb["config"] and ma["metrics"] == mb["metrics"]
    assert (b / "train.toml").read_text() == toml
    capsys.readouterr()
    rc = main(["train", "--config", str(a / "train.toml"), "--task", "surface",
               "--out", str(tmp_path / "c")])
    err = capsys.readouterr().err
    assert rc == 2 and "takes no --task" in err
    rc = main(["train", "--task", "texture", "--out", str(tmp_path / "d")])
    assert rc == 2 and "needs --task and --data" in capsys.readouterr().err


def test_train_builds_one_config_from_the_flags_or_a_train_toml_and_leaves_args_alone(
        tmp_path):
    """The config is built once, from the flags (task defaults filled) or from a
    train.toml; the parsed arguments are not changed (they used to be set onto)."""
    import copy

    from host.cli import build_parser
    from host.cli.learn import train_config
    from host.learn.config import TrainConfig

    data = _texture_npz(tmp_path / "v.npz")
    args = build_parser().parse_args(["train", "--task", "texture", "--data", str(data),
                                      "--out", str(tmp_path / "m"), "--no-identity-check"])
    before = copy.deepcopy(vars(args))
    cfg = train_config(args)
    assert vars(args) == before
    assert cfg == TrainConfig("texture", DEFAULT_MODEL["texture"], T=DEFAULT_WINDOW["texture"],
                              data=(str(data),), identity=False, measure=True)
    toml = tmp_path / "train.toml"
    from host.learn.card import write_train_toml
    write_train_toml(tmp_path, cfg.but(seed=5).replay())
    args = build_parser().parse_args(["train", "--config", str(toml), "--out",
                                      str(tmp_path / "n")])
    before = copy.deepcopy(vars(args))
    again = train_config(args)
    assert vars(args) == before
    assert again == cfg.but(seed=5, data=(str(data.resolve()),), identity=True)


@pytest.mark.real
@pytest.mark.slow
def test_train_pressure_default_reports_grouped_cv_mae_at_most_180_on_the_hard_plate(
        tmp_path, capsys):
    """Issue 23's pressure figure, as reviewers run it: host train --task pressure (the
    default model) on an .npz of the hard-plate presses, groups = trials, --cv 5:
    the grouped CV MAE and the top of its 95 % interval over trials are <= 180
    load-cell units (the former Ridge default: 70 on this set, 230 on theirs)."""
    from host.learn.pressure import hard_plate_npz
    root = real_data_dir("roboskin/vectors2.npy", "roboskin/pressures2.npy") / "roboskin"
    data = hard_plate_npz(root / "vectors2.npy", root / "pressures2.npy",
                          tmp_path / "hard_plate.npz")["path"]
    out = tmp_path / "pressure"
    rc = main(["train", "--task", "pressure", "--data", data, "--cv", "5", "--json",
               "--out", str(out)])
    assert rc == 0
    res = json.loads(capsys.readouterr().out)
    cv = res["metrics"]["cv"]
    assert res["model"] == DEFAULT_MODEL["pressure"] == "gbt"
    assert cv["folds"] == 5 and cv["grouped"] and cv["trials"] >= 70
    lo, hi = cv["mae_ci95"]
    assert lo <= cv["mae"] <= hi <= 180, cv
    assert cv["mae"] <= 0.1 * cv["mae_predict_mean"], cv


# ---------------------------------------------------------------------------
# Replaying a shipped model's train.toml (host train --config)
# ``host train --config models/<model>/train.toml --out D`` replays a shipped model:
# its train.toml names the module that made it, and host train runs that training
# (issue 32 item 6).

import json
from pathlib import Path

import pytest

from host.cli import main

ROOT = Path(__file__).resolve().parents[3]


def test_a_shipped_train_toml_is_read_not_refused_as_unknown_settings(tmp_path, capsys):
    bad = tmp_path / "train.toml"
    text = (ROOT / "models" / "pressure" / "train.toml").read_text()
    bad.write_text(text.replace('name = "pressure"', 'name = "bogus"'))
    assert main(["train", "--config", str(bad), "--out", str(tmp_path / "m")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "name must be one of" in err and "'bogus'" in err


@pytest.mark.slow
def test_the_shipped_pressure_model_replays_from_its_train_toml(tmp_path, capsys):
    """The pressure model (ridge on simulated presses): about a minute on a busy
    2-core machine, the cheapest of the shipped models."""
    out = tmp_path / "pressure"
    assert main(["train", "--config", str(ROOT / "models" / "pressure" / "train.toml"),
                 "--out", str(out), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["name"] == "pressure" and "model.onnx" in res["files"]
    new = json.loads((out / "manifest.json").read_text())
    old = json.loads((ROOT / "models" / "pressure" / "manifest.json").read_text())
    assert new["kind"] == old["kind"]
    mae_new, mae_old = (m["metrics"]["test"]["mae"] for m in (new, old))
    assert 0 < mae_new < 2 * mae_old
    from host.learn.card import read_train_toml
    again, shipped = (read_train_toml(f) for f in (out / "train.toml",
                                                   ROOT / "models" / "pressure" / "train.toml"))
    assert {k: again[k] for k in ("module", "name", "task", "model", "T", "seed")} == \
        {k: shipped[k] for k in ("module", "name", "task", "model", "T", "seed")}


# -- the recording is the unit (issue 33): what host train prints --------------------

def test_train_prints_the_held_out_recordings_and_its_cv_figure_beside_it(tmp_path, capsys):
    """Four recordings (trials of an .npz) a class: whole recordings are held out,
    the printed figure names them with their window counts, and --cv's figure is
    printed beside the held-out one."""
    data = _texture_npz(tmp_path / "v.npz")
    out = tmp_path / "m"
    rc = main(["train", "--task", "texture", "--window", "2", "--data", str(data),
               "--cv", "2", "--no-identity-check", "--out", str(out)])
    text = capsys.readouterr().out
    assert rc == 0
    man = json.loads((out / "manifest.json").read_text())
    held = man["metrics"]["test"]["held_out"]
    assert held["inside"] == {} and len(held["whole"]) >= 2
    assert man["metrics"]["test"]["protocol"] == "leave-recordings-out"
    shown = ", ".join(f"{r} ({n} windows)" for r, n in sorted(held["whole"].items()))
    assert f"held-out recordings: {shown}" in text
    assert "optimistic" not in text
    cv = man["metrics"]["cv"]
    assert re.search(rf"held-out accuracy {man['metrics']['test']['accuracy']:.4g} .*; "
                     rf"grouped 2-fold CV \(--cv, on the training windows\): accuracy "
                     rf"{cv['accuracy']:.4g} \[", text), text


def test_train_holds_out_a_whole_recording_of_a_class_with_two_and_says_the_other_is_split_inside(
        tmp_path, clips, capsys):
    """Class rough has two recordings (two clips), class smooth one: a whole rough
    clip is held out, smooth's clip is split in time, and the printed figure says
    which is which, the split inside one recording marked optimistic."""
    spec = tmp_path / "tex.csv"
    spec.write_text("path,label,start_frame,end_frame\n"
                    f"{clips / 'smooth.avi'},smooth,0,200\n"
                    f"{clips / 'concrete.avi'},rough,0,200\n"
                    f"{clips / 'lego_train.avi'},rough,0,200\n")
    out = tmp_path / "m"
    rc = main(["train", "--task", "texture", "--model", "fnn", "--window", "3", "--data",
               str(spec), "--no-identity-check", "--no-session-copies",
               "--out", str(out)])
    text = capsys.readouterr().out
    assert rc == 0
    test = json.loads((out / "manifest.json").read_text())["metrics"]["test"]
    held = test["held_out"]
    (whole,) = held["whole"]
    (inside,) = held["inside"]
    assert whole.split(" sha256:")[0] in ("concrete.avi", "lego_train.avi")
    assert inside.startswith("smooth.avi sha256:")
    assert test["protocol"].startswith("leave-recordings-out where a class has two")
    assert (f"held-out recordings: {whole.split(' sha256:')[0]} ({held['whole'][whole]} "
            f"windows)") in text
    assert (f"split inside one recording (optimistic: the same session): smooth.avi "
            f"({held['inside'][inside]} windows)") in text
