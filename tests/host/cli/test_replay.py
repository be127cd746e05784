"""``host train --config models/<model>/train.toml --out D`` replays a shipped model:
its train.toml names the module that made it, and host train runs that training
(issue 32 item 6)."""
from __future__ import annotations

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
