"""The scene simulator: physics, effects, determinism, bad input, extremes."""
from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from device.config import ConfigError
from device.profile import load_profile
from device.sim import EFFECTS, PRESETS, Simulator, builtin_scenes, load_scene, parse_scene

SMALL = dict(width=160, height=120)


def small(name: str, **kw):
    return replace(load_scene(name), **{**SMALL, **kw})


def scene_doc(**over):
    doc = {"sensor": {"profile": "roboskin", "fps": 60, "width": 160, "height": 120},
           "surface": {"preset": "hard"},
           "timeline": [{"action": "lower", "depth_mm": 2.0, "duration_s": 0.1},
                        {"action": "drag", "direction_deg": 0.0, "speed_mm_s": 20.0,
                         "duration_s": 0.3},
                        {"action": "lift", "duration_s": 0.1}]}
    doc.update(over)
    return doc


def all_frames(sim):
    return np.stack([sim.render(i) for i in range(sim.n_frames)])


# -- profiles ---------------------------------------------------------------------

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


# -- determinism and rendering ------------------------------------------------------

def test_same_seed_same_output_and_other_seed_differs():
    sc = small("walk")
    a, b, c = Simulator(sc, seed=5), Simulator(sc, seed=5), Simulator(sc, seed=6)
    for i in (0, 50, 200):
        assert np.array_equal(a.render(i), b.render(i))
    assert np.array_equal(a.truth["imu"], b.truth["imu"])
    assert not np.array_equal(a.truth["imu"], c.truth["imu"])       # imu_noise is seeded
    assert any(not np.array_equal(a.render(i), c.render(i)) for i in (0, 50))


def test_render_out_of_order_matches_in_order():
    sim = Simulator(small("walk"), seed=1)
    fwd = [sim.render(i).copy() for i in range(0, 40)]
    for i in reversed(range(0, 40)):
        assert np.array_equal(sim.render(i), fwd[i])


def test_rendered_pins_sit_where_truth_says():
    """Blob centroids of an effect-free frame match the true pin positions."""
    sim = Simulator(load_scene("drag-45"), seed=0)
    i = int(np.argmax(np.hypot(*sim.truth["shear_px"].T)))
    frame = sim.render(i)
    _, binary = cv2.threshold(frame, 130, 255, cv2.THRESH_BINARY)
    binary[frame > 200] = 0   # the bright surround is not a pin
    n, _, stats, cent = cv2.connectedComponentsWithStats(binary)
    cent = cent[1:][(stats[1:, 4] > 10) & (stats[1:, 4] < 80)]
    pins = sim.truth["pins_px"][i][sim.truth["visible"][i]]
    # pins that stand apart from their neighbours render as separate blobs
    pp = np.linalg.norm(pins[:, None] - pins[None], axis=-1)
    np.fill_diagonal(pp, np.inf)
    apart = pins[pp.min(axis=1) > sim.scene.profile.pin_diameter_px + 3]
    nearest = np.linalg.norm(apart[:, None] - cent[None], axis=-1).min(axis=1)
    assert len(apart) > 40
    assert np.mean(nearest < 1.0) > 0.95
    assert np.median(nearest) < 0.25


# -- effects ---------------------------------------------------------------------------

# which outputs each effect is allowed to touch
TOUCHES = {"glare": {"frames"}, "camera_noise": {"frames"}, "exposure_flicker": {"frames"},
           "motion_blur": {"frames"}, "lens_distortion": {"frames", "pins"},
           "pin_loss": {"frames", "visible"}, "imu_noise": {"imu"}}


def outputs(sim):
    return {"frames": all_frames(sim), "pins": sim.truth["pins_px"],
            "visible": sim.truth["visible"], "imu": sim.truth["imu"]}


def fx_scene(*effects):
    """A fast foot strike, then a Lego drag: every effect has something to act on."""
    doc = scene_doc(surface={"preset": "lego"})
    doc["sensor"].update(width=320, height=240)
    doc["timeline"][0]["duration_s"] = 0.05
    doc["timeline"][0]["depth_mm"] = 3.0
    fx = [{"name": "motion_blur", "exposure_ms": 30.0} if e == "motion_blur" else e
          for e in effects]
    return parse_scene({**doc, "effects": fx})


@pytest.fixture(scope="module")
def base_outputs():
    return outputs(Simulator(fx_scene(), seed=3))


def test_every_effect_has_a_touch_list():
    assert set(TOUCHES) == set(EFFECTS)


@pytest.mark.parametrize("effect", sorted(EFFECTS))
def test_named_effect_changes_output_measurably(effect, base_outputs):
    sim = Simulator(fx_scene(effect), seed=3)
    got = outputs(sim)
    for key in TOUCHES[effect]:
        a, b = base_outputs[key].astype(np.float64), got[key].astype(np.float64)
        if key == "frames":
            assert np.mean(np.abs(a - b)) > 0.05, f"{effect} left the frames unchanged"
        else:
            assert not np.array_equal(a, b), f"{effect} left {key} unchanged"


@pytest.mark.parametrize("effect", sorted(EFFECTS))
def test_unnamed_effect_leaves_no_trace(effect, base_outputs):
    """Adding effect E leaves bit-identical every output E does not touch, with
    or without other effects alongside (each effect draws from its own stream)."""
    sim = Simulator(fx_scene(effect), seed=3)
    got = outputs(sim)
    for key in set(base_outputs) - TOUCHES[effect]:
        assert np.array_equal(base_outputs[key], got[key]), f"{effect} changed {key}"
    others = [e for e in sorted(EFFECTS) if e != effect and not (TOUCHES[e] & TOUCHES[effect])]
    if others:
        with_e = outputs(Simulator(fx_scene(*others, effect), seed=3))
        without = outputs(Simulator(fx_scene(*others), seed=3))
        for key in set(base_outputs) - TOUCHES[effect]:
            assert np.array_equal(with_e[key], without[key])


@pytest.mark.parametrize("effect,attr", [("camera_noise", "noise_pos"), ("glare", "glare"),
                                         ("exposure_flicker", "gains")])
def test_unnamed_effect_builds_no_layer(effect, attr):
    r = Simulator(small("no-touch")).renderer
    assert not hasattr(r, attr)
    assert hasattr(Simulator(small("no-touch").with_effects(effect)).renderer, attr)


def test_motion_blur_acts_inside_the_dome_only():
    blurred, plain = Simulator(fx_scene("motion_blur"), seed=3), Simulator(fx_scene(), seed=3)
    r = blurred.renderer
    yy, xx = np.mgrid[0:r.height, 0:r.width]
    outside = np.hypot(xx - r.centre[0], yy - r.centre[1]) > r.dome_r
    changed = 0
    for i in range(blurred.n_frames):
        a = blurred.render(i)
        assert np.array_equal(a[outside], r.background[outside])
        changed += not np.array_equal(a, plain.render(i))
    assert changed > 0


# -- contact physics -----------------------------------------------------------------

def test_hertz_patch_radius():
    sim = Simulator(load_scene("press-hard"))
    t, prof = sim.truth, sim.scene.profile
    d = t["depth_mm"]
    expect = np.sqrt(prof.dome_radius_mm * d) * prof.px_per_mm
    assert np.allclose(t["patch_radius_px"], expect)
    assert t["load_n"].max() > 0 and np.all(np.diff(t["load_n"][d > 0]) >= -1e-9) is not None


def test_press_spreads_patch_pins_radially_outward():
    sim = Simulator(load_scene("press-hard"))
    t = sim.truth
    i = int(np.argmax(t["depth_mm"]))
    rel = sim.rest_pins_px - t["contact_centre_px"][i]
    disp = t["pins_px"][i] - sim.rest_pins_px
    r = np.hypot(*rel.T)
    inside = (r < t["patch_radius_px"][i]) & (r > 1)
    radial = np.sum(disp[inside] * rel[inside], axis=1) / r[inside]
    assert inside.sum() > 10
    assert np.all(radial > 0)
    # deeper press -> larger spread
    j = np.flatnonzero(t["contact"])[2]
    assert np.abs(t["pins_px"][j] - sim.rest_pins_px).max() < np.abs(disp).max()


def test_soft_surface_indents_less_and_loads_less():
    hard = Simulator(load_scene("press-hard")).truth
    soft = Simulator(load_scene("press-soft")).truth
    assert np.allclose(hard["depth_cmd_mm"], soft["depth_cmd_mm"])
    assert soft["depth_mm"].max() < 0.6 * hard["depth_mm"].max()
    assert soft["load_n"].max() < 0.5 * hard["load_n"].max()


def test_shear_saturates_at_coulomb_limit_then_slips():
    sc = load_scene("drag-0")
    sim = Simulator(sc)
    t = sim.truth
    surf = sc.surfaces["scene"]
    k_t = sc.profile.tangential_stiffness_n_per_mm
    lim = surf.mu * t["load_n"] / k_t
    s = np.hypot(*t["shear_mm"].T)
    assert np.all(s <= lim + 1e-9)
    assert t["slip"].any()
    first = np.flatnonzero(t["slip"])[0]
    assert s[first - 1] > 0.9 * lim[first - 1]          # it stuck until the limit
    assert not t["slip"][:first].any()
    # pins trail the drag: the body moves +x, the patch shear points -x
    assert t["shear_px"][first, 0] < 0 and abs(t["shear_px"][first, 1]) < 1e-9


def test_wet_slips_sooner_than_hard():
    def first_slip(preset):
        sc = parse_scene(scene_doc(surface={"preset": preset}))
        slip = Simulator(sc).truth["slip"]
        return np.flatnonzero(slip)[0]
    assert first_slip("wet") < first_slip("hard")


def test_stick_slip_gives_repeated_onsets():
    doc = scene_doc(surface={"preset": "hard", "mu": 0.5, "mu_kinetic_ratio": 0.3,
                             "stick_slip": True})
    doc["timeline"][1]["duration_s"] = 1.0
    slip = Simulator(parse_scene(doc)).truth["slip"]
    onsets = np.flatnonzero(slip[1:] & ~slip[:-1])
    assert len(onsets) >= 3
    doc["surface"]["stick_slip"] = False
    slip2 = Simulator(parse_scene(doc)).truth["slip"]
    assert len(np.flatnonzero(slip2[1:] & ~slip2[:-1])) == 1


def test_lego_jitter_period_is_stud_pitch_over_speed():
    sc = load_scene("lego-drag")
    from device.sim.physics import simulate_contact
    ph = simulate_contact(sc)
    sliding = ph["slip"]
    j = ph["jitter_mm"][sliding][:, 1]               # drag is along +y (90 deg)
    speed = sc.timeline[1].speed_mm_s
    spec = np.abs(np.fft.rfft(j - j.mean()))
    freqs = np.fft.rfftfreq(len(j), 1 / sc.fps)
    peak = freqs[np.argmax(spec)]
    assert peak == pytest.approx(speed / 8.0, rel=0.25)
    smooth = simulate_contact(load_scene("smooth-drag"))
    assert np.all(smooth["jitter_mm"] == 0)
    concrete = simulate_contact(load_scene("concrete-drag"))
    cj = concrete["jitter_mm"][concrete["slip"]]
    assert cj.std() > 0.05


def test_no_touch_gives_the_rest_image():
    sim = Simulator(load_scene("no-touch"))
    t = sim.truth
    assert not t["contact"].any() and not t["slip"].any()
    assert np.allclose(t["pins_px"], sim.rest_pins_px[None])
    assert np.array_equal(sim.render(0), sim.render(sim.n_frames - 1))
    assert (t["surface"] == 0).all()                  # no-touch label


def test_labels_follow_the_surface_in_contact():
    sim = Simulator(load_scene("walk"))
    labels = {sim.labels(i)["surface"] for i in range(sim.n_frames)}
    assert labels == {"no-touch", "hard", "soft", "slippery"}
    textures = {sim.labels(i)["texture"] for i in range(sim.n_frames)}
    assert textures == {"none", "smooth", "lego", "concrete"}


def test_imu_sees_gravity_touchdown_and_slip_jerk():
    sim = Simulator(load_scene("slip-onset"))
    t = sim.truth
    imu = t["imu_true"]
    air = ~t["contact"]
    assert np.median(imu[air, 2]) == pytest.approx(1.0, abs=0.05)
    touch = np.flatnonzero(t["touch"][1:] & ~t["touch"][:-1]) + 1
    assert imu[touch[0], 2] > 1.05
    onset = np.flatnonzero(t["slip"][1:] & ~t["slip"][:-1]) + 1
    assert np.abs(imu[onset[0], 5]) > 10


def test_every_builtin_scene_loads_and_runs():
    names = builtin_scenes()
    for need in ["press-hard", "press-soft", "press-wet", "slip-onset", "lego-drag",
                 "concrete-drag", "smooth-drag", "no-touch", "walk"]:
        assert need in names
    assert sum(n.startswith("drag-") for n in names) == 8
    for n in names:
        sim = Simulator(replace(load_scene(n), **SMALL))
        assert sim.n_frames > 0 and np.isfinite(sim.truth["pins_px"]).all()


def test_drag_directions_point_opposite_the_drag():
    for d in range(0, 360, 45):
        t = Simulator(small(f"drag-{d}")).truth
        s = t["shear_px"][np.argmax(np.hypot(*t["shear_px"].T))]
        ang = np.degrees(np.arctan2(s[1], s[0]))
        err = (ang - (d + 180) + 180) % 360 - 180
        assert abs(err) < 1e-6


# -- bad input ---------------------------------------------------------------------------

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
    (lambda d: d.update(timeline=[]), r"timeline must be a non-empty list"),
    (lambda d: d["timeline"][0].update(surface="lava"), r"timeline\[0\]\.surface must name"),
    (lambda d: d["sensor"].update(profile="nope"), r"unknown profile 'nope'"),
])
def test_bad_scene_gets_one_clear_error(mutate, match):
    doc = scene_doc()
    mutate(doc)
    with pytest.raises(ConfigError, match=match):
        parse_scene(doc, source="bad.toml")


def test_cli_bad_scene_exit_2_no_traceback(tmp_path, capsys):
    from host.cli import main
    p = tmp_path / "bad.toml"
    p.write_text('[surface]\nmu = -0.5\n[[timeline]]\naction = "hold"\nduration_s = 0.1\n')
    rc = main(["simulate", str(p), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2
    assert "surface.mu" in err and "-0.5" in err and "Traceback" not in err
    rc = main(["simulate", "no-such-scene", "--out", str(tmp_path / "o")])
    assert rc == 2 and "unknown scene" in capsys.readouterr().err


# -- extremes stay finite (property tests) -------------------------------------------------

@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(depth=st.floats(0, 100), speed=st.floats(0, 1e5), mu=st.floats(0, 20),
       stiff=st.floats(1e-3, 1e6), direction=st.floats(-360, 360),
       loss=st.floats(0, 1), texture=st.sampled_from(["smooth", "lego", "concrete"]),
       fx=st.sets(st.sampled_from(sorted(EFFECTS))))
def test_extreme_legal_values_stay_finite(depth, speed, mu, stiff, direction, loss, texture, fx):
    doc = scene_doc(surface={"preset": "hard", "mu": mu, "stiffness_n_per_mm": stiff,
                             "texture": texture, "texture_amplitude_mm": 0.3})
    doc["sensor"].update(width=64, height=48, fps=30)
    doc["timeline"][0]["depth_mm"] = depth
    doc["timeline"][1].update(speed_mm_s=speed, direction_deg=direction)
    effects = [{"name": "pin_loss", "fraction": loss} if e == "pin_loss" else e for e in fx]
    sim = Simulator(parse_scene({**doc, "effects": effects}), seed=1)
    for key, arr in sim.truth.items():
        assert np.isfinite(np.asarray(arr, dtype=np.float64)).all(), key
    for i in range(0, sim.n_frames, 3):
        f = sim.render(i)
        assert f.dtype == np.uint8 and f.shape == (48, 64)


def test_all_pins_lost_is_legal_and_finite():
    sc = small("drag-0").with_effects(*[e for e in []])
    sc = parse_scene({**scene_doc(), "effects": [{"name": "pin_loss", "fraction": 1.0}]})
    sim = Simulator(sc)
    assert not sim.truth["visible"].any()
    f = sim.render(5)
    assert np.array_equal(f, sim.renderer.background)


def test_presets_are_physical():
    for name, s in PRESETS.items():
        assert s.mu >= 0 and s.stiffness_n_per_mm > 0, name
    assert PRESETS["wet"].mu < 0.2 < PRESETS["hard"].mu
    assert PRESETS["soft"].stiffness_n_per_mm < PRESETS["hard"].stiffness_n_per_mm
