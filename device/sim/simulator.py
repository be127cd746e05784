"""The scene simulator: ground truth up front, frames on demand.

>>> sim = Simulator(load_scene("drag-0"), seed=0)
>>> frame = sim.render(10)            # uint8 (H, W)
>>> sim.truth["pins_px"][10]          # where every pin truly is in that frame
"""
from __future__ import annotations

import numpy as np

from .physics import simulate_contact, stream
from .render import Renderer, distort_points
from .scene import SURFACE_LABELS, TEXTURE_LABELS, Scene

#: per-frame ground-truth keys written to datasets (all have the frame count as
#: first dimension)
TRUTH_KEYS = ("t_s", "pins_px", "visible", "contact", "touch", "contact_centre_px", "load_n",
              "depth_mm", "depth_cmd_mm", "patch_radius_px", "shear_mm", "shear_px", "slip",
              "surface", "texture", "imu_true", "imu")


class Simulator:
    def __init__(self, scene: Scene, seed: int = 0):
        self.scene = scene
        self.seed = int(seed)
        self.fps = scene.fps
        self.width, self.height = scene.width, scene.height
        effects = {e.name: e.params for e in scene.effects}
        phys = simulate_contact(scene, self.seed)
        self.n_frames = int(phys["t_s"].shape[0])
        self.renderer = Renderer(scene.profile, self.width, self.height, effects,
                                 self.n_frames, self.seed)
        self.truth = self._pins_truth(phys, effects)
        self._out = np.empty((self.height, self.width), np.uint8)

    def _pins_truth(self, phys: dict, effects: dict) -> dict:
        prof = self.scene.profile
        r = self.renderer
        sx, sy = self.width / prof.width, self.height / prof.height
        ppm = prof.px_per_mm * r.scale
        rest = prof.pins_px * (sx, sy)
        if "pitch" in effects:
            # the pin pattern as a whole is larger or smaller (another skin print)
            c = rest.mean(axis=0)
            rest = c + (rest - c) * effects["pitch"]["scale"]
        centre = r.centre + phys["contact_offset_mm"] * ppm                     # (F, 2)
        a = phys["patch_radius_mm"] * ppm                                        # (F,)
        contact = phys["contact"]
        u_n = prof.normal_gain * (phys["depth_mm"] + phys["bump_mm"]) * ppm * phys["touch"]
        shear_px = prof.shear_gain * phys["shear_mm"] * ppm
        move = shear_px + prof.shear_gain * phys["jitter_mm"] * ppm              # (F, 2)

        rel = rest[None, :, :] - centre[:, None, :]                              # (F, M, 2)
        dist = np.hypot(rel[..., 0], rel[..., 1])
        safe_d = np.maximum(dist, 1e-9)
        safe_a = np.maximum(a, 1e-9)[:, None]
        inside = dist < safe_a
        # normal spread falls off as (a/r)^2 outside the patch; shear carries
        # further, since the skin is one membrane: 1 / (1 + ((r - a) / a)^2)
        spread = np.where(inside, dist / safe_a, (safe_a / safe_d) ** 2)
        carry = np.where(inside, 1.0, 1.0 / (1.0 + ((dist - safe_a) / safe_a) ** 2))
        pins = (rest[None] + (u_n[:, None] * spread / safe_d)[..., None] * rel
                + carry[..., None] * move[:, None, :])
        if phys["shake_mm"].any():
            # each pin in the sliding patch shakes on its own (falls off as the shear)
            amp = prof.shear_gain * phys["shake_mm"] * ppm                       # (F,)
            noise = stream(self.seed, "pin_shake").standard_normal(pins.shape)
            pins = pins + (carry * amp[:, None])[..., None] * noise
        self.rest_pins_px = rest.astype(np.float32)
        if "lens_distortion" in effects:
            self.rest_pins_px = distort_points(rest, self.width, self.height,
                                               effects["lens_distortion"]["k1"]).astype(np.float32)
            pins = distort_points(pins, self.width, self.height, effects["lens_distortion"]["k1"])
            centre = distort_points(centre, self.width, self.height,
                                    effects["lens_distortion"]["k1"])
        visible = (np.hypot(*(pins - r.centre).transpose(2, 0, 1)) <= r.dome_r - r.pin_r)
        visible &= r.drawable(pins)
        if "pin_loss" in effects:
            M = rest.shape[0]
            n_dead = int(round(effects["pin_loss"]["fraction"] * M))
            dead = stream(self.seed, "pin_loss").choice(M, size=n_dead, replace=False)
            visible[:, dead] = False
        # pin motion in the image drives motion blur: per frame the mean velocity
        # vector (px/s) and the mean speed (px/s) of all pins
        vel = np.zeros((pins.shape[0], 3))
        if pins.shape[0] > 1:
            v = np.diff(pins, axis=0) * self.fps
            vel[1:, :2] = v.mean(axis=1)
            vel[1:, 2] = np.hypot(v[..., 0], v[..., 1]).mean(axis=1)
        imu = phys["imu_true"].copy()
        if "imu_noise" in effects:
            rng = stream(self.seed, "imu_noise")
            p = effects["imu_noise"]
            imu[:, :3] += p["accel_g"] * rng.standard_normal((imu.shape[0], 3))
            imu[:, 3:] += p["gyro_dps"] * rng.standard_normal((imu.shape[0], 3))
        truth = {
            "t_s": phys["t_s"],
            "pins_px": pins.astype(np.float32),
            "visible": visible,
            "contact": contact,
            "touch": phys["touch"],
            "contact_centre_px": centre.astype(np.float32),
            "load_n": phys["load_n"],
            "depth_mm": phys["depth_mm"],
            "depth_cmd_mm": phys["depth_cmd_mm"],
            "patch_radius_px": a,
            "shear_mm": phys["shear_mm"],
            "shear_px": shear_px,
            "slip": phys["slip"],
            "surface": phys["surface"],
            "texture": phys["texture"],
            "imu_true": phys["imu_true"],
            "imu": imu,
        }
        self._pin_motion = vel
        return truth

    # -- frames ----------------------------------------------------------------
    def render(self, i: int, out: np.ndarray | None = None) -> np.ndarray:
        """Frame ``i`` as uint8 (H, W). Pass ``out`` to render without allocating;
        without it a fresh array is returned."""
        if not 0 <= i < self.n_frames:
            raise IndexError(f"frame index {i} out of range 0..{self.n_frames - 1}")
        t = self.truth
        return self.renderer.render(i, t["pins_px"][i], t["visible"][i], self._pin_motion[i],
                                    out=out)

    def frames(self):
        """Yield (index, frame) with one reused buffer: copy a frame to keep it."""
        for i in range(self.n_frames):
            yield i, self.render(i, self._out)

    def labels(self, i: int) -> dict:
        t = self.truth
        return {"surface": SURFACE_LABELS[int(t["surface"][i])],
                "texture": TEXTURE_LABELS[int(t["texture"][i])],
                "contact": bool(t["contact"][i]), "slip": bool(t["slip"][i])}
