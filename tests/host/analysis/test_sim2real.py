"""Sim-to-real (host/analysis/sim2real.py): the stroke scenes, what their randomisation
varies, and a texture model trained only on simulated strokes, scored on a short slice
of the real clips."""
from __future__ import annotations

import numpy as np
import pytest

from device.sim import PRESETS, parse_scene
from host.analysis.sim2real import (SIM2REAL_TEXTURES, real_texture_manifest, sim2real_table,
                                    sim_to_real, stroke_scene)
from tests.realdata import real_data_dir


def effect_params(doc):
    sc = parse_scene(doc)
    return {e.name: e.params for e in sc.effects}, sc


def test_calibrated_strokes_use_the_fitted_surfaces():
    for texture in ("smooth", "concrete"):
        _, sc = effect_params(stroke_scene(texture, np.random.default_rng(0)))
        assert sc.surfaces["scene"] == PRESETS[f"roboskin-{texture}"].__class__(
            **{**PRESETS[f"roboskin-{texture}"].__dict__, "name": "scene"})
        _, plain = effect_params(stroke_scene(texture, np.random.default_rng(0),
                                              calibrated=False))
        assert plain.surfaces["scene"].mu == PRESETS[texture].mu
        kinds = [a.kind for a in sc.timeline]
        assert kinds.count("drag") == 3 and kinds.count("lower") == 3


def test_randomisation_varies_glare_lost_pins_brightness_and_pitch():
    draws = [effect_params(stroke_scene("smooth", np.random.default_rng(k)))[0]
             for k in range(12)]
    for name, key in (("glare", "peak"), ("glare", "sigma_px"), ("pin_loss", "fraction"),
                      ("exposure", "gain"), ("pitch", "scale"), ("motion_blur", "exposure_ms")):
        values = [d[name][key] for d in draws]
        assert len(set(values)) == len(values), (name, key, values)
        assert (max(values) - min(values)) > 0.02 * np.mean(values), (name, key, values)
    fixed, _ = effect_params(stroke_scene("smooth", np.random.default_rng(0), randomise=False))
    assert set(fixed) == {"glare", "camera_noise"}


def test_unknown_texture_is_refused_and_a_preset_without_a_fit_is_simulated_plain():
    with pytest.raises(ValueError, match="'felt'"):
        stroke_scene("felt", np.random.default_rng(0))
    _, sc = effect_params(stroke_scene("lego", np.random.default_rng(0)))
    assert sc.surfaces["scene"].mu == PRESETS["lego"].mu


def test_real_manifest_lists_the_rows_and_cuts_each_to_its_first_frames(tmp_path):
    rows = [(tmp_path / "mine_a.avi", "smooth", 0, None), (tmp_path / "mine_b.avi", "grit", 10, 40)]
    text = real_texture_manifest(rows, tmp_path, frames=50).read_text()
    lines = text.splitlines()
    assert lines[0] == "path,label,start_frame,end_frame"
    assert [line.split(",")[1:] for line in lines[1:]] == [["smooth", "0", "50"],
                                                          ["grit", "10", "40"]]
    whole = real_texture_manifest(rows, tmp_path).read_text().splitlines()
    assert whole[1].endswith("smooth,0,") and whole[2].endswith("grit,10,40")


@pytest.mark.real
def test_sim_trained_model_is_scored_on_real_contact_windows(tmp_path):
    root = real_data_dir("roboskin/smooth.avi", "roboskin/concrete.avi") / "roboskin"
    for label in SIM2REAL_TEXTURES:        # the user's own names for the recordings
        (tmp_path / f"my_{label}.avi").symlink_to(root / f"{label}.avi")
    man = real_texture_manifest([(tmp_path / f"my_{t}.avi", t, 0, None)
                                 for t in SIM2REAL_TEXTURES], tmp_path / "real", 60)
    res = sim_to_real([man], tmp_path, n_per_texture=1, real_frames=60, strokes=2,
                      model={"epochs": 20})
    cm = res["confusion"]
    assert sorted(cm["labels"]) == ["concrete", "smooth"]
    assert sum(map(sum, cm["matrix"])) == res["real_windows"] > 20
    assert 0.0 <= res["accuracy"] <= 1.0 and set(res["per_label"]) == set(SIM2REAL_TEXTURES)
    assert res["settings"]["calibrated"] and res["settings"]["randomise"]
    for side in ("real", "sim"):
        assert set(res["motion"][side]) == {"concrete", "smooth"}
    table = sim2real_table(res)
    assert "trained only on simulated strokes" in table and "first 60 frames" in table
    assert ".avi" not in table and res["settings"]["real_specs"] == [str(man)]
