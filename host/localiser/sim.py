"""Simulated training frames of the pin localiser, with their true pins.

Random scenes (depth, contact offset, drag direction and speed, surface) under
random image effects (glare, camera noise, exposure flicker, motion blur, pin
loss, lens distortion), thresholded by the very PinDetector the Pi uses.
"""

from __future__ import annotations

import numpy as np

from device.pi.vision.extract import PinDetector, VisionParams, find_dome
from device.sim import Simulator, parse_scene
from host.localiser.samples import Sample, progress_bar, vision_params_for

__all__ = ["random_scene_doc", "sim_frames"]

_SURFACES = ("hard", "soft", "wet", "smooth", "lego", "concrete")


def random_scene_doc(rng: np.random.Generator, profile: str = "roboskin",
                     max_depth_mm: float = 3.0) -> dict:
    """A random scene (as a TOML-like dict for :func:`device.sim.parse_scene`).

    Lower to a random depth (0.3 mm to ``max_depth_mm``) at a random contact
    offset, drag in a random direction at 5-30 mm/s, sometimes hold, lift; a
    random surface and a random subset of the image effects.
    """
    depth = float(rng.uniform(0.3, max(0.3, max_depth_mm)))
    off = rng.normal(0.0, 2.0, 2).clip(-5, 5)
    tl = [{"action": "lower", "depth_mm": round(depth, 3), "duration_s": 0.15,
           "offset_mm": [round(float(off[0]), 3), round(float(off[1]), 3)]}]
    for _ in range(int(rng.integers(1, 3))):
        tl.append({"action": "drag", "direction_deg": round(float(rng.uniform(0, 360)), 2),
                   "speed_mm_s": round(float(rng.uniform(5, 30)), 2),
                   "duration_s": round(float(rng.uniform(0.2, 0.6)), 3)})
    if rng.random() < 0.5:
        tl.append({"action": "hold", "duration_s": 0.1})
    tl.append({"action": "lift", "duration_s": 0.15})
    effects: list = []
    if rng.random() < 0.9:
        effects.append({"name": "glare", "peak": round(float(rng.uniform(40, 200)), 1),
                        "sigma_px": round(float(rng.uniform(10, 25)), 1)})
    if rng.random() < 0.8:
        effects.append({"name": "camera_noise", "sigma": round(float(rng.uniform(1, 6)), 2)})
    if rng.random() < 0.5:
        effects.append({"name": "exposure_flicker",
                        "amplitude": round(float(rng.uniform(0.02, 0.12)), 3)})
    if rng.random() < 0.3:
        effects.append({"name": "motion_blur", "exposure_ms": round(float(rng.uniform(2, 10)), 2)})
    if rng.random() < 0.15:
        effects.append({"name": "pin_loss", "fraction": round(float(rng.uniform(0.02, 0.1)), 3)})
    if rng.random() < 0.15:
        effects.append({"name": "lens_distortion", "k1": round(float(rng.uniform(-0.08, 0.08)), 4)})
    return {"name": "localiser-train", "hover_mm": 1.0,
            "sensor": {"profile": profile, "fps": 120},
            "surface": {"preset": str(rng.choice(_SURFACES))},
            "timeline": tl, "effects": effects}



def sim_frames(n_scenes: int, frames_per_scene: int, seed: int, profile: str = "roboskin",
               params: VisionParams | None = None, progress: bool = False,
               max_depth_mm: float = 3.0, favour_displacement: float = 0.0) -> list[Sample]:
    """Thresholded simulated frames with their true pins, from random scenes.

    Scene ``k`` uses simulator seed ``seed + k`` and a scene drawn from
    ``default_rng(seed + k)``; frames are drawn at random, two thirds from
    frames in contact (with ``favour_displacement`` > 0 px, weighted towards
    large pin displacements). The dome is found on the scene's first (rest) frame
    with :func:`find_dome`, as the Pi does at start-up.
    """
    if n_scenes < 0 or frames_per_scene < 1:
        raise ValueError(f"n_scenes must be >= 0 and frames_per_scene >= 1, got "
                         f"n_scenes={n_scenes!r}, frames_per_scene={frames_per_scene!r}")
    params = params or vision_params_for(profile)
    out: list[Sample] = []
    with progress_bar(n_scenes, "sim scenes", progress) as bar:
        for k in range(n_scenes):
            s = seed + k
            rng = np.random.default_rng(s)
            doc = random_scene_doc(rng, profile, max_depth_mm)
            sim = Simulator(parse_scene(doc, source="<random>"), seed=s)
            first = sim.render(0)
            dome = find_dome(first)
            if dome is None:
                p = sim.scene.profile
                dome = (*p.dome_centre_px, p.dome_radius_px)
            det = PinDetector(params, first.shape[:2], dome)
            contact = np.flatnonzero(sim.truth["contact"])
            rest = np.flatnonzero(~sim.truth["contact"])
            n_c = min(len(contact), int(round(frames_per_scene * 2 / 3)))
            pw = None
            if favour_displacement and n_c:
                # large deformations are rare in random scenes and the hardest
                # for a linear model: draw contact frames in proportion to
                # 1 + (median pin displacement) / favour_displacement px
                disp = np.median(np.hypot(*(sim.truth["pins_px"][contact] - sim.rest_pins_px)
                                          .transpose(2, 0, 1)), axis=1)
                pw = 1.0 + disp / favour_displacement
                pw /= pw.sum()
            picks = list(rng.choice(contact, n_c, replace=False, p=pw)) if n_c else []
            n_r = min(len(rest), frames_per_scene - n_c)
            picks += list(rng.choice(rest, n_r, replace=False)) if n_r else []
            for i in sorted(int(i) for i in picks):
                b = det.threshold(sim.render(i)).copy()
                pins = sim.truth["pins_px"][i].astype(np.float64)
                d = float(np.median(np.hypot(*(pins - sim.rest_pins_px).T)))
                out.append(Sample(b, det.box, dome, pins, np.ones(len(pins), bool), f"sim:{s}",
                                  i, d))
            bar.update(1)
    return out
