"""The scene simulator (device/sim/simulator.py): the same seed gives the same frames
and truth, frames render in any order, and extreme legal scenes stay finite."""
from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from device.sim import EFFECTS, Simulator, parse_scene
from tests.device.sim.scene_docs import scene_doc, small


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


# -- extremes stay finite (property tests) -------------------------------------------------

@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(depth=st.floats(0, 100), speed=st.floats(0, 1e5), mu=st.floats(0, 20),
       stiff=st.floats(1e-3, 1e6), direction=st.floats(-360, 360),
       loss=st.floats(0, 1), texture=st.sampled_from(["smooth", "lego", "concrete"]),
       fx=st.sets(st.sampled_from(sorted(EFFECTS))))
def test_extreme_legal_values_stay_finite(depth, speed, mu, stiff, direction, loss, texture, fx):
    doc = scene_doc(surface={"preset": "hard", "mu": mu, "stiffness_n_per_mm": stiff,
                             "texture": texture, "texture_amplitude_mm": 0.3,
                             "pin_shake_mm": 0.5})
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


def test_a_long_scene_renders_without_holding_the_whole_scene():
    """Two minutes at 120 fps (14,400 frames): building the simulator and rendering
    stays within a few MB; the pins of every frame (F x M x 2) are not held."""
    import tracemalloc
    doc = scene_doc(timeline=[{"action": "lower", "depth_mm": 2.0, "duration_s": 1.0},
                              {"action": "drag", "direction_deg": 0.0, "speed_mm_s": 5.0,
                               "duration_s": 119.0}])
    doc["sensor"].update(fps=120)
    sc = parse_scene(doc)
    tracemalloc.start()
    try:
        sim = Simulator(sc, seed=0)
        frames = [sim.render(i).copy() for i in (0, 5000, 5001, 14_399)]
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert sim.n_frames == 14_400
    pins_bytes = sim.n_frames * sc.profile.n_pins * 2 * 8
    assert peak < 25e6 < pins_bytes, f"peak {peak / 1e6:.0f} MB"
    # the frames rendered lazily are the frames of the whole-scene truth
    for i, f in zip((0, 5000, 5001, 14_399), frames):
        assert np.array_equal(f, sim.renderer.render(
            i, sim.truth["pins_px"][i], sim.truth["visible"][i],
            _motion(sim.truth["pins_px"], i, sim.fps)))


def _timed_scene(seconds: float, **sensor):
    drags = []
    left = seconds - 1.0
    while left > 0:
        drags.append({"action": "drag", "direction_deg": 0.0, "speed_mm_s": 5.0,
                      "duration_s": min(left, 3600.0)})
        left -= drags[-1]["duration_s"]
    doc = scene_doc(timeline=[{"action": "lower", "depth_mm": 2.0, "duration_s": 1.0}, *drags],
                    effects=["camera_noise", "exposure_flicker", "imu_noise"])
    doc["sensor"].update(fps=120, **sensor)
    return parse_scene(doc)


def test_memory_does_not_grow_with_the_length_of_the_scene():
    """Issue 21, item 14: sim:// peak memory grew with the scene (159 MB at 6 s, 231 MB
    at 22 minutes): its ground truth was computed for every frame up front. Building
    the camera's and the IMU's simulators and reading 600 frames of a 30-minute scene
    (216,000 frames) takes what a 10-second one takes."""
    import tracemalloc

    from device.sim.fake_mpu6050 import FakeMPU6050

    def measure(seconds):
        sc = _timed_scene(seconds, width=64, height=48)
        out = np.empty((48, 64), np.uint8)
        tracemalloc.start()
        try:
            sim = Simulator(sc, seed=0)
            imu = FakeMPU6050.from_scene(sc, clock=None)
            for i in range(600):
                sim.render(i, out)
                sim.labels(i)
                imu.motion[i]
            held, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
        return sim.n_frames, imu.n_frames, held, peak

    n_short, m_short, held_short, peak_short = measure(10.0)
    n_long, m_long, held_long, peak_long = measure(1800.0)
    assert (n_short, m_short, n_long, m_long) == (1200, 1200, 216_000, 216_000)
    assert peak_long < peak_short + 0.2e6, f"{peak_short / 1e6:.2f} -> {peak_long / 1e6:.2f} MB"
    assert held_long < held_short + 0.2e6, f"{held_short / 1e6:.2f} -> {held_long / 1e6:.2f} MB"


def test_blocks_give_the_whole_scenes_truth_and_frames():
    """The truth read block by block (labels, the IMU rows, the frames) is the
    whole-scene truth, however the frames are visited."""
    sc = _timed_scene(6.0, width=64, height=48)
    whole = Simulator(sc, seed=4)
    imu = whole.truth["imu"]
    sim = Simulator(sc, seed=4)
    for i in (700, 5, 255, 256, 257, 719, 0, 512):
        lo, t = sim.truth_block(i)
        for k in t:
            assert np.array_equal(t[k][i - lo], whole.truth[k][i]), (k, i)
        assert np.array_equal(sim.render(i), whole.render(i))
    from device.sim.fake_mpu6050 import FakeMPU6050
    motion = FakeMPU6050.from_scene(sc, seed=4, clock=None).motion
    assert np.array_equal(np.stack([motion[i] for i in range(whole.n_frames)]), imu)


def _motion(pins, i, fps):
    if i == 0:
        return np.zeros(3)
    v = (pins[i].astype(np.float64) - pins[i - 1]) * fps
    return np.array([*v.mean(axis=0), np.hypot(v[:, 0], v[:, 1]).mean()])


def test_pin_shake_moves_pins_only_while_the_patch_slides():
    doc = scene_doc(surface={"preset": "hard", "mu": 0.3})
    still = Simulator(parse_scene(doc), seed=2)
    doc["surface"]["pin_shake_mm"] = 0.1
    shaken = Simulator(parse_scene(doc), seed=2)
    moved = np.abs(shaken.truth["pins_px"] - still.truth["pins_px"]).max(axis=(1, 2))
    slip = still.truth["slip"]
    assert slip.any() and (~slip).any()
    assert np.all(moved[~slip] == 0)
    assert np.all(moved[slip] > 0.05)
    # the shake is each pin's own: neighbouring pins move differently
    d = (shaken.truth["pins_px"] - still.truth["pins_px"])[slip]
    assert np.std(d[:, :, 0], axis=1).mean() > 0.1


def test_pitch_effect_scales_the_pin_pattern():
    doc = scene_doc()
    base = Simulator(parse_scene(doc), seed=0).rest_pins_px
    big = Simulator(parse_scene({**doc, "effects": [{"name": "pitch", "scale": 1.1}]}),
                    seed=0).rest_pins_px
    spread = np.linalg.norm(big - big.mean(0), axis=1) / np.linalg.norm(base - base.mean(0),
                                                                        axis=1).clip(1e-9)
    assert np.allclose(spread[np.linalg.norm(base - base.mean(0), axis=1) > 1], 1.1)
