"""Contact physics (device/sim/physics.py) as the simulator's truth shows it: Hertz
patch, springs in series, Coulomb friction and slip, stick-slip, texture jitter, the
surface labels in contact and the IMU truth."""
from __future__ import annotations

import numpy as np
import pytest

from device.sim import Simulator, load_scene, parse_scene
from device.sim.physics import simulate_contact
from tests.device.sim.scene_docs import scene_doc, small


def test_hertz_patch_radius():
    sim = Simulator(load_scene("press-hard"))
    t, prof = sim.truth, sim.scene.profile
    d = t["depth_mm"]
    expect = np.sqrt(prof.dome_radius_mm * d) * prof.px_per_mm
    assert np.allclose(t["patch_radius_px"], expect)


def test_hertz_load_follows_depth_down_and_up():
    """N = 4/3 E* sqrt(R) d^1.5 of the depth at every frame: the load rises while the
    foot is lowered, holds while it holds and falls while it lifts (load is a function
    of depth, not of time), and no frame in the air carries a load."""
    sim = Simulator(load_scene("press-hard"))
    t, prof = sim.truth, sim.scene.profile
    d, load = t["depth_mm"], t["load_n"]
    hertz = 4.0 / 3.0 * prof.modulus_n_per_mm2 * np.sqrt(prof.dome_radius_mm) * d ** 1.5
    assert np.allclose(load, np.where(d > 1e-3, hertz, 0.0))
    assert load.max() > 5.0
    by_depth = np.argsort(d, kind="stable")
    assert np.all(np.diff(load[by_depth]) >= 0)
    dd, dl = np.diff(d), np.diff(load)
    pressed = (d[1:] > 1e-3) & (d[:-1] > 1e-3)
    assert np.all(dl[pressed & (dd > 0)] > 0) and np.all(dl[pressed & (dd < 0)] < 0)
    assert np.all(dl[pressed & (dd == 0)] == 0)
    assert (pressed & (dd > 0)).sum() > 10 and (pressed & (dd < 0)).sum() > 10


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


def test_drag_directions_point_opposite_the_drag():
    for d in range(0, 360, 45):
        t = Simulator(small(f"drag-{d}")).truth
        s = t["shear_px"][np.argmax(np.hypot(*t["shear_px"].T))]
        ang = np.degrees(np.arctan2(s[1], s[0]))
        err = (ang - (d + 180) + 180) % 360 - 180
        assert abs(err) < 1e-6

