"""host plot directions: paper-layout .npy files and analyse JSON lines."""
from __future__ import annotations

import json

import numpy as np
import pytest

from host.cli import main
from host.analysis.plots import load_directions


def test_direction_scatter_from_npy_and_jsonl(tmp_path, capsys):
    a = np.random.default_rng(0).normal(size=(5, 3, 3, 2))
    np.save(tmp_path / "d.npy", a)
    lines = [{"frame": i, "contact": i % 2 == 0, "shear_x": float(i), "shear_y": -1.0}
             for i in range(6)] + [{"summary": True}]
    (tmp_path / "a.jsonl").write_text("\n".join(json.dumps(x) for x in lines))
    out = tmp_path / "dirs.png"
    assert main(["plot", "directions", str(tmp_path / "d.npy"), str(tmp_path / "a.jsonl"),
                 "--out", str(out), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["points"] == [45, 3]           # only contact frames from the JSON lines
    assert out.stat().st_size > 5000
    d = load_directions(tmp_path / "d.npy")
    assert d["sensation"].tolist()[:9] == [0, 0, 0, 1, 1, 1, 2, 2, 2]
    assert d["pressure"].tolist()[:3] == [0, 1, 2]


def test_bad_inputs_are_exit_2(tmp_path, capsys):
    np.save(tmp_path / "bad.npy", np.zeros((3, 2)))
    assert main(["plot", "directions", str(tmp_path / "bad.npy"), "--out",
                 str(tmp_path / "x.png")]) == 2
    assert "expected shape" in capsys.readouterr().err
    (tmp_path / "bad.jsonl").write_text("not json\n")
    assert main(["plot", "directions", str(tmp_path / "bad.jsonl"), "--out",
                 str(tmp_path / "x.png")]) == 2
    assert "bad.jsonl:1" in capsys.readouterr().err
