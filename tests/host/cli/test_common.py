"""What every host command shares (host.cli.common): JSON output, bad input as
exit status 2, finding the real recordings."""
from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from host.cli import main
from host.cli.common import EXIT_BAD_INPUT, UserError, emit, real_data_dir
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
    assert "--count must be at least 1, got 0" in capsys.readouterr().err
    assert main(["monitor", "loop://", "--seconds", "-1"]) == 2
    assert "--seconds must be positive, got -1.0" in capsys.readouterr().err


def test_eval_of_a_folder_without_a_model_is_exit_2(capsys, tmp_path):
    assert main(["eval", str(tmp_path), "--data", str(tmp_path)]) == 2
    assert "host eval: error:" in capsys.readouterr().err
