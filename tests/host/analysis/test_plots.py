"""host plot directions: paper-layout .npy files and analyse JSON lines, and the
tracked-vector vs localiser comparison (--compare)."""
from __future__ import annotations

import json

import numpy as np

from host.cli import main
from host.analysis.plots import load_comparison, load_directions
from tests import REPO_ROOT


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
    from PIL import Image
    assert np.asarray(Image.open(out).convert("L")).std() > 1.0     # a drawn plot, not blank
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


def test_compare_plots_vectors_beside_localiser_pins(tmp_path, capsys):
    a = tmp_path / "drag.jsonl"
    assert main(["analyse", "sim://drag-45", "--localiser",
                 str(REPO_ROOT / "models" / "localiser-roboskin"), "--out", str(a)]) == 0
    out = tmp_path / "fig5.png"
    assert main(["plot", "directions", str(a), "--compare", "--out", str(out), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    from PIL import Image
    assert Image.open(out).size[0] > 2 * Image.open(out).size[1] * 0.8   # two panels
    assert np.asarray(Image.open(out).convert("L")).std() > 1.0
    n = res["points"][0]
    assert res["points"] == [n, n] and n > 50
    (c,) = res["comparison"]
    assert c["source"] == str(a) and c["compared"] > 0.6 * n
    assert abs(c["vectors_deg"] - 225.0) < 3.0 and abs(c["localised_deg"] - 225.0) < 15.0
    inputs, stats = load_comparison(a)
    assert [d["label"] for d in inputs] == ["drag: tracked vectors", "drag: localiser pins"]
    assert stats["median_abs_diff_deg"] == c["median_abs_diff_deg"]


def test_compare_without_localised_pins_is_exit_2(tmp_path, capsys):
    lines = [{"frame": i, "contact": True, "shear_x": 1.0, "shear_y": 0.0, "faults": []}
             for i in range(3)]
    (tmp_path / "a.jsonl").write_text("\n".join(json.dumps(x) for x in lines))
    assert main(["plot", "directions", str(tmp_path / "a.jsonl"), "--compare", "--out",
                 str(tmp_path / "x.png")]) == 2
    assert "--localiser" in capsys.readouterr().err


def test_plots_are_written_by_the_one_figure_saver(tmp_path, monkeypatch):
    """host plot directions and host report's accuracy-vs-T plot both save through
    host.analysis.figures.save_figure (title, layout, folder, close)."""
    import host.analysis.plots as plots
    from host.analysis import figures
    from host.bench import report_doc

    saved = []

    def recording(fig, out, title="", dpi=90):
        saved.append((out, title))
        return figures.save_figure(fig, out, title, dpi)

    monkeypatch.setattr(plots, "save_figure", recording)
    monkeypatch.setattr(report_doc, "save_figure", recording)
    xy = np.array([[1.0, 2.0], [-1.0, 0.5]])
    d = {"xy": xy, "sensation": np.zeros(2, int), "pressure": np.zeros(2, int), "label": "a"}
    plots.plot_directions([d], tmp_path / "d.png", title="t")
    row = {"kind": "fnn", "T": 3, "mean": 0.9, "sd": 0.01, "n": 3, "metric": "accuracy"}
    report_doc.plot_accuracy_vs_t([row], tmp_path / "sub" / "p.png", "surface")
    assert saved == [(tmp_path / "d.png", "t"), (tmp_path / "sub" / "p.png", "")]
    assert (tmp_path / "sub" / "p.png").stat().st_size > 1000


def test_an_empty_input_is_one_line_naming_it_and_exit_2(tmp_path, capsys):
    """Issue 21, items 6 and 13: a zero-length .npy was an EOFError traceback, and an
    empty JSON-lines file wrote an empty plot and exited 0."""
    (tmp_path / "empty.npy").write_bytes(b"")
    (tmp_path / "empty.jsonl").write_text("")
    np.save(tmp_path / "none.npy", np.zeros((0, 3, 3, 2)))
    (tmp_path / "air.jsonl").write_text(json.dumps({"frame": 0, "contact": False,
                                                    "shear_x": 0.0, "shear_y": 0.0}))
    for name, compare, why in (("empty.npy", [], "empty or cut short"),
                               ("empty.jsonl", [], "no frame lines"),
                               ("empty.jsonl", ["--compare"], "no frame lines"),
                               ("none.npy", [], "no vectors"),
                               ("air.jsonl", [], "no contact frame")):
        out = tmp_path / "x.png"
        assert main(["plot", "directions", str(tmp_path / name), *compare,
                     "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and name in err[0] and why in err[0], err
        assert not out.exists()
