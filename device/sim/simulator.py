"""The scene simulator: per-frame ground truth up front, pins and frames on demand.

>>> sim = Simulator(load_scene("drag-0"), seed=0)
>>> frame = sim.render(10)            # uint8 (H, W)
>>> sim.truth["pins_px"][10]          # where every pin truly is in that frame

The per-frame scalars (contact, load, shear, IMU, ...) are computed when the
simulator is built: a few numbers per frame. Where every pin is (F x M x 2) is
computed in blocks of :data:`BLOCK` frames as frames are rendered, so rendering a
long scene holds one block, not the whole scene. ``truth["pins_px"]`` and
``truth["visible"]`` are built (block by block) on first access, for callers that
want the whole scene's pins.
"""
from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from .physics import simulate_contact, stream
from .render import Renderer, distort_points
from .scene import SURFACE_LABELS, TEXTURE_LABELS, Scene

#: frames whose pins are computed together when rendering
BLOCK = 256

#: per-frame ground-truth keys written to datasets (all have the frame count as
#: first dimension)
TRUTH_KEYS = ("t_s", "pins_px", "visible", "contact", "touch", "contact_centre_px", "load_n",
              "depth_mm", "depth_cmd_mm", "patch_radius_px", "shear_mm", "shear_px", "slip",
              "surface", "texture", "imu_true", "imu")


class _Truth(Mapping):
    """The ground-truth dict: ready keys, and ``pins_px`` / ``visible`` built on
    first access."""

    def __init__(self, ready: dict, lazy: dict):
        self._ready = ready
        self._lazy = lazy             # key -> () -> array
        self._order = list(TRUTH_KEYS)

    def __getitem__(self, k):
        if k not in self._ready and k in self._lazy:
            self._ready[k] = self._lazy.pop(k)()
        return self._ready[k]

    def __iter__(self):
        return iter([k for k in self._order if k in self] +
                    [k for k in self._ready if k not in self._order])

    def __len__(self) -> int:
        return len(set(self._ready) | set(self._lazy))

    def __contains__(self, k) -> bool:
        return k in self._ready or k in self._lazy


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
        self._effects = effects
        self.truth = self._make_truth(phys, effects)
        self._out = np.empty((self.height, self.width), np.uint8)
        self._block: tuple[int, np.ndarray, np.ndarray, np.ndarray] | None = None

    def _make_truth(self, phys: dict, effects: dict) -> _Truth:
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
        u_n = prof.normal_gain * (phys["depth_mm"] + phys["bump_mm"]) * ppm * phys["touch"]
        shear_px = prof.shear_gain * phys["shear_mm"] * ppm
        move = shear_px + prof.shear_gain * phys["jitter_mm"] * ppm              # (F, 2)
        # what the per-block pin computation needs
        self._rest, self._centre, self._a, self._u_n, self._move = rest, centre, a, u_n, move
        # each pin in the sliding patch shakes on its own (falls off as the shear);
        # drawn per frame in _pins, so a frame's shake does not depend on its block
        shake = prof.shear_gain * phys["shake_mm"] * ppm                        # (F,)
        self._shake = shake if np.any(shake) else None
        self.rest_pins_px = rest.astype(np.float32)
        k1 = effects["lens_distortion"]["k1"] if "lens_distortion" in effects else None
        self._k1 = k1
        if k1 is not None:
            self.rest_pins_px = distort_points(rest, self.width, self.height, k1).astype(np.float32)
            centre = distort_points(centre, self.width, self.height, k1)
        self._dead = None
        if "pin_loss" in effects:
            M = rest.shape[0]
            n_dead = int(round(effects["pin_loss"]["fraction"] * M))
            self._dead = stream(self.seed, "pin_loss").choice(M, size=n_dead, replace=False)
        imu = phys["imu_true"].copy()
        if "imu_noise" in effects:
            rng = stream(self.seed, "imu_noise")
            p = effects["imu_noise"]
            imu[:, :3] += p["accel_g"] * rng.standard_normal((imu.shape[0], 3))
            imu[:, 3:] += p["gyro_dps"] * rng.standard_normal((imu.shape[0], 3))
        ready = {
            "t_s": phys["t_s"],
            "contact": phys["contact"],
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
        return _Truth(ready, {"pins_px": lambda: self._whole()[0],
                              "visible": lambda: self._whole()[1]})

    def _pins(self, lo: int, hi: int) -> tuple[np.ndarray, np.ndarray]:
        """Pin centres (float64, distorted when the scene says so) and visibility of
        frames lo..hi-1."""
        r = self.renderer
        rest = self._rest
        centre, a = self._centre[lo:hi], self._a[lo:hi]
        rel = rest[None, :, :] - centre[:, None, :]                              # (n, M, 2)
        dist = np.hypot(rel[..., 0], rel[..., 1])
        safe_d = np.maximum(dist, 1e-9)
        safe_a = np.maximum(a, 1e-9)[:, None]
        inside = dist < safe_a
        # normal spread falls off as (a/r)^2 outside the patch; shear carries
        # further, since the skin is one membrane: 1 / (1 + ((r - a) / a)^2)
        spread = np.where(inside, dist / safe_a, (safe_a / safe_d) ** 2)
        carry = np.where(inside, 1.0, 1.0 / (1.0 + ((dist - safe_a) / safe_a) ** 2))
        pins = (rest[None] + (self._u_n[lo:hi, None] * spread / safe_d)[..., None] * rel
                + carry[..., None] * self._move[lo:hi, None, :])
        if self._shake is not None:
            amp = self._shake[lo:hi]
            for k in np.flatnonzero(amp):
                noise = stream(self.seed, f"pin_shake/{lo + k}").standard_normal(rest.shape)
                pins[k] += (carry[k] * amp[k])[:, None] * noise
        if self._k1 is not None:
            pins = distort_points(pins, self.width, self.height, self._k1)
        visible = (np.hypot(*(pins - r.centre).transpose(2, 0, 1)) <= r.dome_r - r.pin_r)
        visible &= r.drawable(pins)
        if self._dead is not None:
            visible[:, self._dead] = False
        return pins, visible

    def _motion(self, pins: np.ndarray, first: int) -> np.ndarray:
        """Per frame the mean pin velocity (px/s, x and y) and mean pin speed (px/s),
        from consecutive rows of ``pins``; ``first``: the block starts at frame 0
        (no frame before it: zero motion)."""
        v = np.diff(pins, axis=0) * self.fps
        vel = np.zeros((pins.shape[0] - 1 + first, 3))
        if v.shape[0]:
            vel[first:, :2] = v.mean(axis=1)
            vel[first:, 2] = np.hypot(v[..., 0], v[..., 1]).mean(axis=1)
        return vel

    def _load_block(self, i: int) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
        """The block holding frame ``i``: (first frame, pins float32, visible, motion)."""
        b = self._block
        if b is not None and b[0] <= i < b[0] + b[1].shape[0]:
            return b
        lo = (int(i) // BLOCK) * BLOCK
        hi = min(lo + BLOCK, self.n_frames)
        start = max(lo - 1, 0)                 # one frame before: motion at ``lo``
        pins, visible = self._pins(start, hi)
        motion = self._motion(pins, first=int(lo == 0))
        k = lo - start
        self._block = (lo, pins[k:].astype(np.float32), visible[k:], motion)
        return self._block

    def _whole(self) -> tuple[np.ndarray, np.ndarray]:
        """pins_px (F, M, 2) float32 and visible (F, M) for the whole scene."""
        M = self._rest.shape[0]
        pins = np.empty((self.n_frames, M, 2), np.float32)
        vis = np.empty((self.n_frames, M), bool)
        for lo in range(0, self.n_frames, BLOCK):
            hi = min(lo + BLOCK, self.n_frames)
            p, v = self._pins(lo, hi)
            pins[lo:hi], vis[lo:hi] = p, v
        for k, arr in (("pins_px", pins), ("visible", vis)):
            self.truth._ready.setdefault(k, arr)
            self.truth._lazy.pop(k, None)
        return pins, vis

    # -- frames ----------------------------------------------------------------
    def render(self, i: int, out: np.ndarray | None = None) -> np.ndarray:
        """Frame ``i`` as uint8 (H, W). Pass ``out`` to render without allocating;
        without it a fresh array is returned."""
        if not 0 <= i < self.n_frames:
            raise IndexError(f"frame index {i} out of range 0..{self.n_frames - 1}")
        lo, pins, visible, motion = self._load_block(i)
        k = i - lo
        return self.renderer.render(i, pins[k], visible[k], motion[k], out=out)

    def frames(self):
        """Yield (index, frame) with one reused buffer: copy a frame to keep it."""
        for i in range(self.n_frames):
            yield i, self.render(i, self._out)

    def labels(self, i: int) -> dict:
        t = self.truth
        return {"surface": SURFACE_LABELS[int(t["surface"][i])],
                "texture": TEXTURE_LABELS[int(t["texture"][i])],
                "contact": bool(t["contact"][i]), "slip": bool(t["slip"][i])}
