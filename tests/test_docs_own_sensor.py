"""docs/own-sensor.md: every command of the walkthrough runs, in order, on the real
clips, and what each step promises holds."""
from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys

import pytest

from host.cli import main
from tests import REPO_ROOT
from tests.realdata import real_data_dir

DOC = REPO_ROOT / "docs" / "own-sensor.md"


def _blocks(kind: str) -> list[str]:
    return re.findall(rf"```{kind}\n(.*?)```", DOC.read_text(), re.S)


def _shortened(check: dict) -> dict:
    """The recording-identity check as the page shows it: no recording names, no method."""
    keep = ("mode", "balanced_accuracy", "balanced_accuracy_ci95", "chance", "n_windows",
            "flagged", "inconclusive", "skipped")
    return {"flagged": check["flagged"], "warning": check["warning"],
            "classes": {c: {k: e[k] for k in keep if k in e}
                        for c, e in check["classes"].items()}}


def _conclusive(e: dict) -> bool:
    return "skipped" not in e and "inconclusive" not in e


def _same_check(shown: dict, got: dict) -> bool:
    """The page's excerpt is this run's output: the same verdicts (flagged, the mode,
    whether each class's check could conclude), and the figures, where both have them,
    within run-to-run and machine-to-machine noise."""
    if (shown["flagged"], shown["warning"]) != (got["flagged"], got["warning"]) or \
            set(shown["classes"]) != set(got["classes"]):
        return False
    for c, a in shown["classes"].items():
        b = got["classes"][c]
        if (a["mode"], bool(a.get("flagged")), _conclusive(a)) != \
                (b["mode"], bool(b.get("flagged")), _conclusive(b)):
            return False
        if "balanced_accuracy" in a and "balanced_accuracy" in b and (
                abs(a["balanced_accuracy"] - b["balanced_accuracy"]) > 0.15
                or abs(a["n_windows"] - b["n_windows"]) > max(5, 0.3 * a["n_windows"])):
            return False
    return True


def test_the_walkthrough_runs_on_the_real_clips(tmp_path, monkeypatch, capsys):
    data = real_data_dir("roboskin/smooth.avi", "roboskin/concrete.avi",
                         "roboskin/concrete_gyro.npy")
    (tmp_path / "roboskin").symlink_to(data / "roboskin")
    monkeypatch.chdir(tmp_path)
    toml, = _blocks("toml")
    name = re.match(r"# (\S+)\n", toml).group(1)
    (tmp_path / name).write_text(toml)
    csv, = _blocks("csv")
    (tmp_path / "later.csv").write_text(csv)
    commands = [line for block in _blocks("sh") for line in block.splitlines()
                if line.strip() and not line.startswith("#")]
    assert [c.split()[:2] for c in commands][:1] == [["host", "calibrate"]]
    assert len(commands) >= 8
    for cmd in commands:
        argv = shlex.split(cmd)
        if argv[0] == "host":
            capsys.readouterr()
            assert main(argv[1:]) == 0, cmd
            if argv[1] == "train":
                got = _shortened(json.loads(capsys.readouterr().out)["identity_check"])
                try:
                    shown = json.loads(_blocks("json")[0])
                except ValueError:
                    shown = None
                assert shown and _same_check(shown, got), json.dumps(got, indent=1)
            if argv[1] == "eval":
                out = capsys.readouterr().out       # the text summary (no --json)
                acc = float(re.search(r"accuracy ([0-9.]+)", out).group(1))
                assert acc >= 0.75, out                         # a later part of each clip
        else:
            assert argv[:3] == ["python", "-m", "device.pi"], cmd
            env = dict(os.environ, PYTHONPATH=str(REPO_ROOT))
            r = subprocess.run([sys.executable, *argv[1:]], env=env, capture_output=True,
                               text=True, timeout=600)
            assert r.returncode == 0, r.stderr[-2000:]
    assert (tmp_path / "my-sensor.toml").is_file()
    man = json.loads((tmp_path / "my-models" / "texture" / "manifest.json").read_text())
    assert man["classes"] == ["concrete", "smooth"]
    # the final check's frames start more than T frames after each clip's training frames
    trained = {re.search(r"roboskin/(\S+)", c).group(1): int(re.search(r"--frames (\d+)",
                                                                      c).group(1))
               for c in commands if c.startswith("host record")}
    for row in csv.splitlines()[1:]:
        path, _, start, _ = row.split(",")
        assert int(start) >= trained[path.split("/")[-1]] + man["T"], row
    log = [json.loads(x) for x in (tmp_path / "run.jsonl").read_text().splitlines()]
    textures = [d.get("texture") for d in log if d.get("texture")]
    assert textures, "the runtime named no texture"
