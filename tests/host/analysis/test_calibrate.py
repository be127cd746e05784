"""host calibrate (host/analysis/calibrate.py) fits a [vision] profile that the Pi loads
and that finds the pins."""
from __future__ import annotations

import json

import pytest

from device.profile import load_pipeline_profile
from host.cli import main


def test_calibrate_on_the_simulated_rest_clip(tmp_path, capsys):
    out = tmp_path / "sim.toml"
    assert main(["calibrate", "sim://no-touch", "--out", str(out), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    prof = load_pipeline_profile(out)
    assert prof.name == "sim"
    assert prof.pitch_px == pytest.approx(11.6, rel=0.1)
    assert abs(prof.n_pins - 133) <= 4
    assert prof.dome_px[2] == pytest.approx(145, rel=0.05)
    assert res["fit"]["regular_fraction"] > 0.9


def test_calibrate_on_real_clips(tmp_path):
    from tests.realdata import real_data_dir
    data = real_data_dir("roboskin/smooth.avi", "tactip_shear/images/image_1.png")
    out = tmp_path / "smooth.toml"
    assert main(["calibrate", str(data / "roboskin" / "smooth.avi"), "--out", str(out)]) == 0
    prof = load_pipeline_profile(out)
    assert prof.pitch_px == pytest.approx(11.7, rel=0.1)      # measured by hand: 11.7 px
    assert abs(prof.n_pins - 131) <= 8
    out2 = tmp_path / "shear.toml"
    folder = tmp_path / "one"
    folder.mkdir()
    (folder / "image_1.png").write_bytes((data / "tactip_shear/images/image_1.png").read_bytes())
    assert main(["calibrate", str(folder), "--out", str(out2)]) == 0
    prof2 = load_pipeline_profile(out2)
    assert prof2.n_pins == 331 and prof2.pitch_px == pytest.approx(19.2, rel=0.05)


def test_calibrate_without_a_dome_is_exit_2(tmp_path, capsys):
    import cv2
    import numpy as np
    folder = tmp_path / "black"
    folder.mkdir()
    cv2.imwrite(str(folder / "a.png"), np.zeros((100, 100), np.uint8))
    assert main(["calibrate", str(folder), "--out", str(tmp_path / "x.toml")]) == 2
    assert "no dome" in capsys.readouterr().err
