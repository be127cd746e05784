"""Rendering (device/sim/render.py): pins drawn where the truth says, and the effects:
each named one changes what it may touch, an unnamed one leaves no trace and builds
nothing."""
from __future__ import annotations

import tracemalloc

import cv2
import numpy as np
import pytest

from device.sim import EFFECTS, Simulator, load_scene, parse_scene
from device.sim.render import NOISE_BANK
from tests.device.sim.scene_docs import all_frames, scene_doc, small


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


# which outputs each effect is allowed to touch
TOUCHES = {"glare": {"frames"}, "camera_noise": {"frames"}, "exposure_flicker": {"frames"},
           "motion_blur": {"frames"}, "lens_distortion": {"frames", "pins"},
           "pin_loss": {"frames", "visible"}, "imu_noise": {"imu"}, "exposure": {"frames"},
           "pitch": {"frames", "pins"}}


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


def _kept_bytes(scene) -> tuple[int, int]:
    """(bytes a renderer of ``scene`` keeps, as tracemalloc counts numpy's buffers,
    width * height of its frames)."""
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        r = Simulator(scene).renderer
        kept = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    return kept, r.width * r.height


@pytest.mark.parametrize("effect,frames_of_memory", [("camera_noise", 2 * NOISE_BANK),
                                                    ("glare", 1), ("motion_blur", 1)])
def test_an_unnamed_effect_costs_no_memory(effect, frames_of_memory):
    """A named effect keeps its layer (the noise bank, the glare image, the dome
    mask: at least that many frames of bytes, on top of the other effects'); left
    unnamed, it is not built."""
    _kept_bytes(small("no-touch"))                       # warm the caches
    _, frame = _kept_bytes(small("no-touch"))
    others = [e for e in ("camera_noise", "glare", "motion_blur") if e != effect]
    without, _ = _kept_bytes(small("no-touch").with_effects(*others))
    with_e, _ = _kept_bytes(small("no-touch").with_effects(*others, effect))
    assert with_e - without >= 0.9 * frames_of_memory * frame


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

