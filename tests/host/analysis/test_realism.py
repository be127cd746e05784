"""The roboskin simulator profile against the real clips, measured the same way."""
from __future__ import annotations

import pytest

from host.analysis.realism import roboskin_realism
from tests.realdata import real_data_dir


@pytest.fixture(scope="module")
def realism():
    return roboskin_realism(real_data_dir())


def test_every_compared_figure_is_within_20_percent(realism):
    bad = [(p["real_clip"], r["figure"], round(r["ratio"], 2)) for p in realism["pairs"]
           for r in p["rows"] if "not_compared" not in r and not r["within_20pct"]]
    assert not bad, bad
    assert realism["all_within_20pct"]


def test_only_the_documented_figure_is_left_out(realism):
    left = [(p["real_clip"], r["figure"]) for p in realism["pairs"] for r in p["rows"]
            if "not_compared" in r]
    assert left == [("concrete.avi", "glare blob area [px^2]")]


def test_cli_realism_writes_png(tmp_path, capsys):
    from host.cli import main
    png = tmp_path / "side.png"
    rc = main(["realism", "--data", str(real_data_dir()), "--png", str(png)])
    out = capsys.readouterr().out
    assert rc == 0 and "within 20%: yes" in out
    import cv2
    img = cv2.imread(str(png))
    assert img is not None and img.shape[1] > 2 * img.shape[0] - 20
