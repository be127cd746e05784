"""What every host command shares (host.cli.common): JSON output, bad input as
exit status 2, finding the real recordings."""
from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from host.cli import main
from host.cli.common import EXIT_BAD_INPUT, UserError, dataset_folder, emit, real_data_dir
from tests import REPO_ROOT


def test_emit_prints_json_with_numpy_values_or_the_text(capsys):
    emit(argparse.Namespace(json=True), {"n": np.int64(3), "xy": np.array([1.5, 2.0])}, "t")
    assert json.loads(capsys.readouterr().out) == {"n": 3, "xy": [1.5, 2.0]}
    emit(argparse.Namespace(json=False), {"n": 3}, "three")
    assert capsys.readouterr().out == "three\n"


def test_real_data_dir_takes_the_given_folder_or_the_environment(tmp_path, monkeypatch):
    assert real_data_dir(str(tmp_path)) == tmp_path
    monkeypatch.setenv("TACFOOT_REAL_DATA", str(tmp_path))
    assert real_data_dir(None) == tmp_path
    monkeypatch.setenv("TACFOOT_REAL_DATA", str(tmp_path / "none"))
    default = REPO_ROOT.parent / "shared" / "data"       # ../shared/data beside the repo
    if default.is_dir():
        assert real_data_dir(str(tmp_path / "none")) == default
    else:
        with pytest.raises(UserError, match="--data DIR or set TACFOOT_REAL_DATA"):
            real_data_dir(str(tmp_path / "none"))


def test_a_missing_source_is_one_line_and_exit_2(capsys, tmp_path):
    assert EXIT_BAD_INPUT == 2
    assert main(["analyse", str(tmp_path / "missing.avi")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("host analyse: error:") and err.count("\n") == 1


def test_monitor_checks_its_arguments(capsys):
    assert main(["monitor"]) == 2
    assert "SERIAL_URL_OR_FILE" in capsys.readouterr().err
    assert main(["monitor", "loop://", "--count", "0"]) == 2
    assert "--count: must be a whole number >= 1, got '0'" in capsys.readouterr().err
    assert main(["monitor", "loop://", "--seconds", "-1"]) == 2
    assert "--seconds: must be a finite number > 0, got '-1'" in capsys.readouterr().err


def test_eval_of_a_folder_without_a_model_is_exit_2(capsys, tmp_path):
    assert main(["eval", str(tmp_path), "--data", str(tmp_path)]) == 2
    assert "host eval: error:" in capsys.readouterr().err


# ---------------------------------------------------------------------------
# Bad input to every command: one line on stderr, exit 2, never a traceback
# ---------------------------------------------------------------------------

MODELS = REPO_ROOT / "models"
TRIALS = REPO_ROOT / "trials" / "sim-smoke.toml"


@pytest.fixture(scope="module")
def bad(tmp_path_factory):
    """A folder of bad inputs, each named for what is wrong with it."""
    import shutil

    import cv2

    from host.data.simulate import simulate_to_dataset

    d = tmp_path_factory.mktemp("bad")
    rng = np.random.default_rng(0)
    for name, at in (("unreadable", "not an image"), ("odd", None)):
        (d / name).mkdir()
        for i in range(6):
            cv2.imwrite(str(d / name / f"f{i}.png"), rng.integers(0, 255, (48, 64), np.uint8))
        if at:
            (d / name / "f3.png").write_text(at)
        else:
            cv2.imwrite(str(d / name / "f3.png"), np.zeros((20, 30), np.uint8))
    (d / "unreadable.csv").write_text("path,label\nunreadable,hard\n")
    (d / "latin1.toml").write_bytes(b'name = "caf\xe9"\n')
    (d / "folder.toml").mkdir()
    (d / "folder.png").mkdir()
    (d / "file").write_text("x\n")
    (d / "full").mkdir()
    (d / "full" / "notes.txt").write_text("mine\n")
    simulate_to_dataset("minimal", d / "ds", progress=False)
    for name, edit in (("truncated", None), ("trials", {"trials": "x"}),
                       ("version", {"version": "x"})):
        shutil.copytree(d / "ds", d / name)
        if edit is None:
            f = d / name / "trial_0000.npz"
            f.write_bytes(f.read_bytes()[:4000])
        else:
            doc = json.loads((d / name / "dataset.json").read_text())
            (d / name / "dataset.json").write_text(json.dumps(dict(doc, **edit)))
    for kind, edit in (("onnx", {"onnx": 5}), ("version", {"version": "abc"}),
                       ("T", {"T": 1e9})):
        for model in ("pressure", "surface"):
            shutil.copytree(MODELS / model, d / f"{model}-{kind}")
            for m in (d / f"{model}-{kind}").glob("manifest*.json"):
                m.write_text(json.dumps(dict(json.loads(m.read_text()), **edit)))
    return d


# (command line with {d} for the bad-inputs folder, what the one line must say)
BAD_INPUTS = [
    # an unreadable or odd-sized image in a folder
    ("analyse {d}/unreadable --out {d}/o.jsonl", "f3.png: cannot decode image"),
    ("analyse {d}/odd --out {d}/o.jsonl", "f3.png: image is 30x20, the folder's first is 64x48"),
    ("view {d}/unreadable --out {d}/v.png", "f3.png: cannot decode image"),
    ("view {d}/odd --out {d}/v.gif", "f3.png: image is 30x20"),
    ("calibrate {d}/unreadable --out {d}/c.toml", "f3.png: cannot decode image"),
    ("calibrate {d}/odd --out {d}/c.toml", "f3.png: image is 30x20"),
    ("train --task surface --data {d}/unreadable.csv --out {d}/m0",
     "unreadable: cannot read a frame: {d}/unreadable/f3.png: cannot decode image"),
    # a scene, profile or trial file that is not UTF-8, or is a folder
    ("simulate {d}/latin1.toml --out {d}/s0", "latin1.toml: not UTF-8 text"),
    ("simulate {d}/folder.toml --out {d}/s0", "folder.toml: is a folder, not a TOML file"),
    ("analyse sim://minimal --profile {d}/latin1.toml", "latin1.toml: not UTF-8 text"),
    ("analyse sim://minimal --profile {d}/folder.toml", "folder.toml: is a folder"),
    ("rig check {d}/latin1.toml", "latin1.toml: not UTF-8 text"),
    ("rig check {d}/folder.toml", "folder.toml: is a folder"),
    # a truncated trial, a dataset index with fields of the wrong type
    ("train --task surface --data {d}/truncated --out {d}/m1",
     "trial_0000.npz: corrupt or truncated trial file"),
    ("view {d}/truncated --out {d}/v.png", "trial_0000.npz: corrupt or truncated trial file"),
    ("train --task surface --data {d}/trials --out {d}/m2",
     "dataset.json: trials must be a list of trial entries, got 'x'"),
    ("view {d}/version --out {d}/v.png",
     "dataset.json: index version must be a whole number >= 0, got 'x'"),
    ("eval models/surface --data {d}/version", "index version must be a whole number"),
    # model manifests with fields of the wrong type
    ("analyse sim://minimal --pressure {d}/pressure-onnx",
     "onnx must be the model file's name (null only for a rule model), got 5"),
    ("analyse sim://minimal --pressure {d}/pressure-version",
     "manifest version must be a whole number >= 0, got 'abc'"),
    ("analyse sim://minimal --pressure {d}/pressure-T",
     "T must be a whole number of frames in [1, 1000], got 1000000000.0"),
    ("eval {d}/surface-onnx --data {d}/ds", "onnx must be the model file's name"),
    ("eval {d}/surface-version --data {d}/ds", "manifest version must be a whole number"),
    ("eval {d}/surface-T --data {d}/ds", "T must be a whole number of frames"),
    # numbers out of range
    ("view minimal --out {d}/v.png --gain nan",
     "argument --gain: must be a finite number in (0, 1000], got 'nan'"),
    ("view minimal --out {d}/v.png --max-frames -3",
     "argument --max-frames: must be a whole number in [0, 100000], got '-3'"),
    ("simulate minimal --out {d}/s1 --trials -3",
     "argument --trials: must be a whole number in [1, 10000], got '-3'"),
    ("calibrate sim://minimal --out {d}/c.toml --frames -5",
     "argument --frames: must be a whole number in [2, 100000], got '-5'"),
    ("train --task surface --data {d}/ds --out {d}/m3 --window 0",
     "argument --window: must be a whole number in [1, 1000], got '0'"),
    ("simulate minimal --out {d}/s1 --seed -1", "argument --seed: must be a whole number"),
    ("report --windows 1,x --out {d}/r.md", "--windows: expected whole numbers like 1,3,10 "
                                           "or 1-10, got '1,x'"),
    ("bench runtime --frames 0", "argument --frames: must be a whole number in [1, 1000000]"),
    # --out: a folder where a file goes, a file where a folder goes, a folder in use
    ("analyse sim://minimal --out {d}/full", "--out {d}/full: is a folder; give the name of a "
                                             "file to write"),
    ("calibrate sim://minimal --out {d}/full", "--out {d}/full: is a folder"),
    ("view minimal --out {d}/folder.png", "--out {d}/folder.png: is a folder"),
    ("simulate minimal --out {d}/file", "--out {d}/file: is a file, not a folder"),
    ("simulate minimal --out {d}/full", "--out {d}/full: the folder is not empty and is not a "
                                        "tacfoot dataset; choose a new or empty folder"),
    ("train --task surface --data {d}/ds --out {d}/file", "--out {d}/file: is a file"),
    ("train --task surface --data {d}/ds --out {d}/ds", "--out {d}/ds: the folder is not "
                                                        "empty; add --force to replace what it "
                                                        "holds, or choose a new or empty folder"),
    ("rig run {trials} --rig sim:// --camera sim://?fps=30 --out {d}/full --yes",
     "--out {d}/full: the folder is not empty and is not a tacfoot dataset"),
    ("rig run {trials} --rig sim:// --camera sim://?fps=30 --out {d}/file --yes",
     "--out {d}/file: is a file, not a folder"),
    ("record --camera sim://minimal --label x --out {d}/full", "the folder is not empty"),
    # a socket:// URL without a port
    ("monitor socket://notahost", "'socket://notahost': a socket:// URL needs a host and a "
                                  "port 1-65535"),
    ("rig run {trials} --rig socket://notahost --camera sim://?fps=30 --out {d}/r0 --yes",
     "a socket:// URL needs a host and a port"),
]


@pytest.mark.parametrize("line, says", BAD_INPUTS, ids=[b[0].split(" --")[0].replace("{d}/", "")
                                                      + f" [{i}]"
                                                      for i, b in enumerate(BAD_INPUTS)])
def test_bad_input_to_any_command_is_one_line_and_exit_2(bad, capsys, monkeypatch, line, says):
    monkeypatch.chdir(REPO_ROOT)
    argv = line.format(d=bad, trials=TRIALS).split()
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"host {argv[0]}: error: ") and err.count("\n") == 1, err
    assert says.format(d=bad) in err


def test_the_out_rule_creates_missing_parents_and_keeps_folders_it_adds_to(bad, tmp_path, capsys):
    out = tmp_path / "a" / "b" / "o.jsonl"
    assert main(["analyse", "sim://minimal?end_frame=3", "--out", str(out)]) == 0
    assert len(out.read_text().splitlines()) == 4          # 3 frames and the summary
    assert main(["analyse", "sim://minimal?end_frame=2", "--out", str(out)]) == 0
    assert len(out.read_text().splitlines()) == 3          # an existing file is replaced
    ds = tmp_path / "x" / "y" / "ds"
    assert main(["simulate", "minimal", "--out", str(ds)]) == 0
    assert main(["simulate", "minimal", "--out", str(ds), "--seed", "1"]) == 0   # appends
    assert len(json.loads((ds / "dataset.json").read_text())["trials"]) == 2
    stopped = tmp_path / "stopped"          # a writer killed in its first trial
    stopped.mkdir()
    (stopped / ".trial_0000.npz.k3j2.tmp").write_bytes(b"partial")
    assert dataset_folder(stopped) and main(["simulate", "minimal", "--out", str(stopped)]) == 0
    (ds / "notes.txt").write_text("mine\n")
    assert dataset_folder(ds)                # a dataset may hold other files
    assert not dataset_folder(bad / "full")
    m = tmp_path / "m"
    train = ["train", "--task", "surface", "--model", "rule", "--data", str(bad / "ds"),
             "--out", str(m)]
    capsys.readouterr()
    assert main(train) == 0
    assert main(train) == 2 and "add --force" in capsys.readouterr().err
    assert main(train + ["--force"]) == 0
