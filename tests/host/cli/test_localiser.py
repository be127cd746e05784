"""host localiser (host.cli.localiser): the Ridge localiser retrained for any
calibrated sensor from its own clips, and used by host analyse."""
from __future__ import annotations

import json

import numpy as np

from device.profile import load_layout
from host.cli import main
from tests.realdata import real_data_dir


def test_calibrate_then_retrain_the_localiser_on_real_clips(tmp_path, capsys):
    clips = real_data_dir("roboskin/smooth.avi", "roboskin/concrete.avi") / "roboskin"
    prof = tmp_path / "my-sensor.toml"
    assert main(["calibrate", str(clips / "smooth.avi"), "--out", str(prof)]) == 0
    n = len(load_layout(prof))
    loc = tmp_path / "loc"
    capsys.readouterr()
    assert main(["localiser", "--profile", str(prof), "--clip", str(clips / "smooth.avi"),
                 "--clip", str(clips / "concrete.avi"), "--sim-scenes", "0", "--out", str(loc),
                 "--quiet", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["n_pins"] == n and res["training"]["sim_frames"] == 0
    assert res["training"]["real_frames"] > 300
    held = res["metrics"]["real_heldout_measured"]
    assert held["median_px"] < 1.0 and held["p90_px"] < 3.0     # a fraction of the 11 px pitch
    out = tmp_path / "a.jsonl"
    assert main(["analyse", str(clips / "concrete.avi"), "--profile", str(prof),
                 "--localiser", str(loc), "--out", str(out)]) == 0
    frames = [json.loads(x) for x in out.read_text().splitlines()][:-1]
    pins = np.array([f["localised_px"] for f in frames[-50:]], float)
    assert pins.shape == (50, n, 2) and np.isfinite(pins).all()


def test_a_calibrated_profile_cannot_be_simulated(tmp_path, capsys):
    prof = tmp_path / "cal.toml"
    prof.write_text('[vision]\npitch_px = 10\nn_pins = 2\ndome_px = [50, 50, 40]\n\n'
                    '[layout]\nkind = "points"\npins_px = [[40, 50], [60, 50]]\n')
    assert main(["localiser", "--profile", str(prof), "--out", str(tmp_path / "l")]) == 2
    assert "--sim-scenes 0" in capsys.readouterr().err
    assert not (tmp_path / "l").exists()
