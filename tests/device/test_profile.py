"""device/profile.py: one parser for a sensor profile's geometry, layout and [vision]."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from device.config import ConfigError
from device.profile import (PROFILE_DIR, ProfileError, VisionParams, builtin_profiles,
                            builtin_toml, hex_layout, load_pipeline_profile, load_profile,
                            parse_pipeline_profile, radial_layout)

MINE = ('[profile]\nname="mine"\nwidth=200\nheight=200\ndome_centre_px=[100,100]\n'
        'dome_radius_px=90\npx_per_mm=5\ndome_radius_mm=15\npin_diameter_px=5\n'
        '[layout]\nkind="radial"\nrings=[1,8,16]\nring_radii_px=[0,20,40]\n'
        '[vision]\npitch_px=20.0\nn_pins=25\n')


def test_builtin_profiles_have_their_pin_counts():
    assert builtin_profiles() == ["roboskin", "tactip331"]
    assert load_profile("roboskin").n_pins == 133
    assert load_profile("tactip331").n_pins == 331


def test_one_file_gives_the_geometry_and_the_pipeline_view(tmp_path):
    p = tmp_path / "mine.toml"
    p.write_text(MINE)
    geo = load_profile(p)
    pipe = load_pipeline_profile(p)
    assert geo.name == pipe.name == "mine"
    assert geo.n_pins == pipe.n_pins == 25
    assert pipe.pitch_px == 20.0 and pipe.match_gate_px == pytest.approx(8.0)
    assert np.allclose(geo.pins_px[0], [100.0, 100.0])
    for name in builtin_profiles():
        assert load_profile(name).n_pins == load_pipeline_profile(name).n_pins


def test_unknown_builtin_names_the_field_and_the_choices():
    with pytest.raises(ConfigError, match=r"sensor\.profile: unknown profile 'nope'.*roboskin"):
        load_profile("nope")
    with pytest.raises(ProfileError, match=r"profile: unknown profile 'nope'.*tactip331"):
        load_pipeline_profile("nope")
    with pytest.raises(ConfigError, match=r"scene: unknown scene 'x'; built-in scenes are \['roboskin'"):
        builtin_toml("x", PROFILE_DIR, "scene", "scene")
    assert builtin_toml("roboskin", PROFILE_DIR, "f", "profile") == PROFILE_DIR / "roboskin.toml"


def test_bad_profile_names_the_field(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text('[profile]\nname="x"\nwidth=200\nheight=200\ndome_centre_px=[100,100]\n'
                 'dome_radius_px=-3\npx_per_mm=5\ndome_radius_mm=15\npin_diameter_px=5\n'
                 '[layout]\nkind="hex"\nhex_rings=3\npitch_px=10\n')
    with pytest.raises(ConfigError, match=r"profile\.dome_radius_px .*-3"):
        load_profile(p)


def test_a_vision_only_profile_has_no_geometry(tmp_path):
    p = tmp_path / "cal.toml"
    p.write_text("[vision]\npitch_px=12.0\nn_pins=133\n")
    assert load_pipeline_profile(p).n_pins == 133
    with pytest.raises(ConfigError, match="profile"):
        load_profile(p)


def test_layouts_have_their_pin_counts_and_spacing():
    hexp = hex_layout(3, 10.0, (50.0, 60.0))
    assert hexp.shape == (1 + 3 * 3 * 4, 2)
    assert np.allclose(hexp[0], [50.0, 60.0])
    d = np.hypot(*(hexp[1:7] - hexp[0]).T)
    assert np.allclose(d, 10.0)
    rad = radial_layout([1, 6], [0.0, 5.0], [0.0, 90.0], (0.0, 0.0))
    assert rad.shape == (7, 2)
    assert np.allclose(rad[1], [0.0, 5.0], atol=1e-12)


def test_a_points_layout_loads_without_simulator_geometry(tmp_path):
    from device.profile import load_layout
    p = tmp_path / "cal.toml"
    p.write_text('[vision]\npitch_px = 10\nn_pins = 3\n\n[layout]\nkind = "points"\n'
                 'pins_px = [[1, 2], [3.5, 4], [5, 6]]\n')
    assert load_layout(p).tolist() == [[1, 2], [3.5, 4], [5, 6]]
    assert load_pipeline_profile(p).n_pins == 3


@pytest.mark.parametrize("layout,match", [
    ('kind = "points"\npins_px = [[1, 2, 3]]', "layout.pins_px must be a non-empty list"),
    ('kind = "points"\npins_px = []', "layout.pins_px must be a non-empty list"),
    ('kind = "points"\npins_px = "x"', "layout.pins_px must be a non-empty list"),
    ('kind = "grid"', "layout.kind"),
])
def test_a_bad_points_layout_is_one_clear_error(tmp_path, layout, match):
    from device.config import ConfigError
    from device.profile import load_layout
    p = tmp_path / "cal.toml"
    p.write_text(f"[vision]\npitch_px = 10\nn_pins = 3\n\n[layout]\n{layout}\n")
    with pytest.raises(ConfigError, match=match):
        load_layout(p)


def test_a_vision_only_profile_names_the_missing_layout(tmp_path):
    from device.config import ConfigError
    from device.profile import load_layout
    p = tmp_path / "old.toml"
    p.write_text("[vision]\npitch_px = 10\nn_pins = 3\n")
    with pytest.raises(ConfigError, match="layout.*host calibrate"):
        load_layout(p)


@pytest.mark.parametrize(
    "field, value",
    [
        ("block", 10), ("block", 1), ("block", 11.0), ("block", True),
        ("offset", float("nan")), ("offset", 1e6),
        ("blur_sigma_px", -1.0),
        ("min_area_px", 0), ("max_area_px", 5),  # max < default min 10
        ("roi_shrink", 0.0), ("roi_shrink", float("inf")),
        ("contrast_ref", 0.0), ("contrast_ref", -3.0), ("contrast_ref", float("nan")),
        ("contrast_ref", 300.0), ("contrast_ref", "30"),
    ],
)
def test_params_reject_bad_value_and_name_it(field, value):
    with pytest.raises(ValueError) as err:
        VisionParams(**{field: value})
    msg = str(err.value)
    assert field in msg
    assert repr(value) in msg or str(value) in msg


def test_vision_params_are_frozen():
    p = VisionParams()
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.block = 13  # type: ignore[misc]


@pytest.mark.parametrize("vision,match", [
    ({"block": 10, "pitch_px": 5, "n_pins": 5}, "vision.block must be odd"),
    ({"block": 11, "pitch_px": -1, "n_pins": 5}, "vision.pitch_px must be >= 0.5"),
    ({"pitch_px": 5}, "vision.n_pins is required"),
    ({"pitch_px": 5, "n_pins": 5, "colour": 1}, "vision.colour is not a known key"),
    ({"pitch_px": 5, "n_pins": 5, "dome_px": [1, 2]}, "vision.dome_px must be"),
    # a gate or contact threshold beyond the pin pitch makes rest read as contact, or
    # contact never read at all
    ({"pitch_px": 11.7, "n_pins": 5, "match_gate_px": 1e308},
     r"p\.toml: vision\.match_gate_px must be <= 11\.7, got 1e\+308"),
    ({"pitch_px": 11.7, "n_pins": 5, "match_gate_px": 0}, r"match_gate_px must be > 0"),
    ({"pitch_px": 11.7, "n_pins": 5, "contact_px": 1e9}, r"contact_px must be <= 11\.7"),
    ({"pitch_px": 5, "n_pins": 5, "contrast_ref": 0}, r"vision\.contrast_ref must be > 0, got 0"),
    ({"pitch_px": 5, "n_pins": 5, "contrast_ref": 256}, r"vision\.contrast_ref must be <= 255"),
    ({"pitch_px": 5, "n_pins": 5, "contrast_ref": "29"}, r"vision\.contrast_ref must be a number"),
])
def test_bad_profile_gets_one_clear_error(vision, match):
    with pytest.raises(ProfileError, match=match):
        parse_pipeline_profile({"vision": vision}, source="p.toml")



def test_contrast_ref_is_optional_and_absent_means_no_scaling():
    """[vision] contrast_ref: absent (every profile before it) is None, the pipeline's
    fixed offset; given, it is read as the calibration's contrast in gray levels."""
    base = {"pitch_px": 5, "n_pins": 5}
    assert parse_pipeline_profile({"vision": base}).vision.contrast_ref is None
    got = parse_pipeline_profile({"vision": dict(base, contrast_ref=29.7)}).vision
    assert got.contrast_ref == 29.7 and got.offset == 14.0
