"""Scene files (device/sim/scene.py): the built-in scenes and presets, a custom
profile, and one clear error per bad field."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from device.config import ConfigError
from device.profile import load_profile
from device.sim import PRESETS, Simulator, builtin_scenes, load_scene, parse_scene
from tests.device.sim.scene_docs import SMALL, scene_doc


def test_custom_profile_from_toml(tmp_path):
    p = tmp_path / "mine.toml"
    p.write_text('[profile]\nname="mine"\nwidth=200\nheight=200\ndome_centre_px=[100,100]\n'
                 'dome_radius_px=90\npx_per_mm=5\ndome_radius_mm=15\npin_diameter_px=5\n'
                 '[layout]\nkind="radial"\nrings=[1,8,16]\nring_radii_px=[0,20,40]\n')
    prof = load_profile(p)
    assert prof.n_pins == 25
    scene = parse_scene(scene_doc(sensor={"profile": str(p), "fps": 30}))
    sim = Simulator(scene)
    assert sim.render(0).shape == (200, 200)


def test_every_builtin_scene_loads_and_runs():
    names = builtin_scenes()
    for need in ["press-hard", "press-soft", "press-wet", "slip-onset", "lego-drag",
                 "concrete-drag", "smooth-drag", "no-touch", "walk"]:
        assert need in names
    assert sum(n.startswith("drag-") for n in names) == 8
    for n in names:
        sim = Simulator(replace(load_scene(n), **SMALL))
        assert sim.n_frames > 0 and np.isfinite(sim.truth["pins_px"]).all()


@pytest.mark.parametrize("mutate,match", [
    (lambda d: d["surface"].update(mu=-0.5), r"surface\.mu must be >= 0, got -0\.5"),
    (lambda d: d["timeline"][0].update(depth_mm=-1.0), r"timeline\[0\]\.depth_mm .*-1\.0"),
    (lambda d: d["timeline"][0].update(depth_mm="deep"), r"timeline\[0\]\.depth_mm must be a number"),
    (lambda d: d["surface"].update(colour="red"), r"surface\.colour is not a known key"),
    (lambda d: d.update(bogus=1), r"bogus is not a known key"),
    (lambda d: d["timeline"][1].update(action="jump"), r"timeline\[1\]\.action must be one of"),
    (lambda d: d.update(effects=["sparkle"]), r"effects\[0\]\.name must be one of"),
    (lambda d: d.update(effects=[{"name": "camera_noise", "sigma": -2}]),
     r"effects\[0\]\.sigma must be >= 0"),
    (lambda d: d["sensor"].update(fps=0), r"sensor\.fps must be >= 1"),
    # a scene plays as a camera source: the bound --fps has (issue 21, item 5)
    (lambda d: d["sensor"].update(fps=1e9), r"sensor\.fps must be <= 1000"),
    (lambda d: d.update(timeline=[]), r"timeline must be a non-empty list"),
    (lambda d: d["timeline"][0].update(surface="lava"), r"timeline\[0\]\.surface must name"),
    (lambda d: d["sensor"].update(profile="nope"), r"unknown profile 'nope'"),
])
def test_bad_scene_gets_one_clear_error(mutate, match):
    doc = scene_doc()
    mutate(doc)
    with pytest.raises(ConfigError, match=match):
        parse_scene(doc, source="bad.toml")


def test_presets_are_physical():
    for name, s in PRESETS.items():
        assert s.mu >= 0 and s.stiffness_n_per_mm > 0, name
    assert PRESETS["wet"].mu < 0.2 < PRESETS["hard"].mu
    assert PRESETS["soft"].stiffness_n_per_mm < PRESETS["hard"].stiffness_n_per_mm



def test_roboskin_presets_grip_and_shake_as_the_real_clips_do():
    smooth, concrete = PRESETS["roboskin-smooth"], PRESETS["roboskin-concrete"]
    assert (smooth.texture, concrete.texture) == ("smooth", "concrete")
    assert smooth.mu > 2 * concrete.mu and smooth.stick_slip
    assert smooth.pin_shake_mm > concrete.pin_shake_mm > 0
    sc = parse_scene(scene_doc(surface={"preset": "roboskin-smooth"}))
    assert sc.surfaces["scene"].pin_shake_mm == smooth.pin_shake_mm
