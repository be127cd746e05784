"""host train (host.cli.learn) on the paper's kind of data: one recording per class.
Real clips from ../shared/data (skipped without them)."""
from __future__ import annotations

import json

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
    spec = _manifest(tmp_path / "tex.csv", [(clips / "smooth.avi", "smooth"),
                                            (clips / "concrete.avi", "concrete")])
    out = tmp_path / "model"
    rc = main(["train", "--task", "texture", "--data", str(spec), "--contact-only",
               "--out", str(out), "--json"])
    assert rc == 0
    res = json.loads(capsys.readouterr().out)
    assert res["model"] == DEFAULT_MODEL["texture"] and res["T"] == DEFAULT_WINDOW["texture"]
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
