"""The scene simulator: ground truth, pins and frames on demand, in blocks.

>>> sim = Simulator(load_scene("drag-0"), seed=0)
>>> frame = sim.render(10)            # uint8 (H, W)
>>> sim.labels(10)                    # that frame's labels, from its block
>>> sim.truth["pins_px"][10]          # where every pin truly is in that frame

Everything per frame (contact, load, shear, IMU, where every pin is) is computed in
blocks of :data:`BLOCK` frames as frames are rendered (:class:`device.sim.physics.Physics`
carries the state from block to block), so rendering a scene of any length holds
one block: building the simulator and rendering from it take the same memory for a
minute as for an hour. ``sim.truth[key]`` is built for the whole scene (block by
block) on first access, for callers that want the whole scene at once.
"""
from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from .physics import Physics, stream
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
    """The ground-truth dict of the whole scene: each key is built (block by block)
    on first access, for callers that want the whole scene at once."""

    def __init__(self, build: dict):
        self._ready: dict = {}
        self._build = build           # key -> () -> {key: array, ...}

    def __getitem__(self, k):
        if k not in self._ready and k in self._build:
            self._ready.update(self._build[k]())
        return self._ready[k]

    def __iter__(self):
        return iter([k for k in TRUTH_KEYS if k in self] +
                    [k for k in self._ready if k not in TRUTH_KEYS])

    def __len__(self) -> int:
        return len(set(self._ready) | set(self._build))

    def __contains__(self, k) -> bool:
        return k in self._ready or k in self._build


class _Block:
    """BLOCK frames of a scene: their ground truth (``truth``, TRUTH_KEYS without the
    pins), pins (float32), visibility and pin motion."""
    __slots__ = ("lo", "hi", "truth", "pins", "visible", "motion")

    def __init__(self, lo, hi, truth, pins, visible, motion):
        self.lo, self.hi, self.truth = lo, hi, truth
        self.pins, self.visible, self.motion = pins, visible, motion


#: the ground-truth keys held per block (all but the pins)
_BLOCK_KEYS = tuple(k for k in TRUTH_KEYS if k not in ("pins_px", "visible"))


class Simulator:
    def __init__(self, scene: Scene, seed: int = 0):
        self.scene = scene
        self.seed = int(seed)
        self.fps = scene.fps
        self.width, self.height = scene.width, scene.height
        effects = {e.name: e.params for e in scene.effects}
        self.physics = Physics(scene, self.seed)
        self.n_frames = int(self.physics.n_frames)
        self.renderer = Renderer(scene.profile, self.width, self.height, effects,
                                 self.n_frames, self.seed)
        self._effects = effects
        self._setup(effects)
        self.truth = _Truth({**{k: self._whole_truth for k in _BLOCK_KEYS},
                             "pins_px": self._whole_pins, "visible": self._whole_pins})
        self._out = np.empty((self.height, self.width), np.uint8)
        self._block: _Block | None = None
        self._truth_block: tuple[int, dict] | None = None

    def _setup(self, effects: dict) -> None:
        """What every frame shares: the rest pins, the lens, the lost pins."""
        prof = self.scene.profile
        r = self.renderer
        sx, sy = self.width / prof.width, self.height / prof.height
        self._ppm = prof.px_per_mm * r.scale
        rest = prof.pins_px * (sx, sy)
        if "pitch" in effects:
            # the pin pattern as a whole is larger or smaller (another skin print)
            c = rest.mean(axis=0)
            rest = c + (rest - c) * effects["pitch"]["scale"]
        self._rest = rest
        self.rest_pins_px = rest.astype(np.float32)
        k1 = effects["lens_distortion"]["k1"] if "lens_distortion" in effects else None
        self._k1 = k1
        if k1 is not None:
            self.rest_pins_px = distort_points(rest, self.width, self.height, k1).astype(np.float32)
        self._dead = None
        if "pin_loss" in effects:
            M = rest.shape[0]
            n_dead = int(round(effects["pin_loss"]["fraction"] * M))
            self._dead = stream(self.seed, "pin_loss").choice(M, size=n_dead, replace=False)

    def _derive(self, phys: dict, lo: int) -> tuple[dict, dict]:
        """From the physics of the block starting at frame ``lo`` (and of the frame
        before it, if ``phys`` starts there), what the pins need (undistorted patch
        centre ``centre``, radius ``a``, normal push ``u_n``, shear move ``move``,
        per-pin ``shake``, px) and the ground truth (TRUTH_KEYS but the pins; the
        IMU noise is the block's, drawn for the last ``hi - lo`` rows)."""
        prof, r, ppm = self.scene.profile, self.renderer, self._ppm
        centre = r.centre + phys["contact_offset_mm"] * ppm                     # (n, 2)
        a = phys["patch_radius_mm"] * ppm                                        # (n,)
        u_n = prof.normal_gain * (phys["depth_mm"] + phys["bump_mm"]) * ppm * phys["touch"]
        shear_px = prof.shear_gain * phys["shear_mm"] * ppm
        move = shear_px + prof.shear_gain * phys["jitter_mm"] * ppm              # (n, 2)
        # each pin in the sliding patch shakes on its own (falls off as the shear);
        # drawn per frame in _pins, so a frame's shake does not depend on its block
        shake = prof.shear_gain * phys["shake_mm"] * ppm                        # (n,)
        pin_in = {"centre": centre, "a": a, "u_n": u_n, "move": move, "shake": shake}
        seen = distort_points(centre, self.width, self.height, self._k1) if self._k1 is not None \
            else centre
        imu = phys["imu_true"].copy()
        if "imu_noise" in self._effects:
            # one stream per block: a frame's noise does not depend on the scene's length
            rng = stream(self.seed, f"imu_noise/{lo // BLOCK}")
            p = self._effects["imu_noise"]
            n = min(BLOCK, self.n_frames - lo)
            imu[-n:, :3] += p["accel_g"] * rng.standard_normal((n, 3))
            imu[-n:, 3:] += p["gyro_dps"] * rng.standard_normal((n, 3))
        truth = {"t_s": phys["t_s"], "contact": phys["contact"], "touch": phys["touch"],
                 "contact_centre_px": seen.astype(np.float32), "load_n": phys["load_n"],
                 "depth_mm": phys["depth_mm"], "depth_cmd_mm": phys["depth_cmd_mm"],
                 "patch_radius_px": a, "shear_mm": phys["shear_mm"], "shear_px": shear_px,
                 "slip": phys["slip"], "surface": phys["surface"], "texture": phys["texture"],
                 "imu_true": phys["imu_true"], "imu": imu}
        return pin_in, truth

    def _pins(self, d: dict, lo: int) -> tuple[np.ndarray, np.ndarray]:
        """Pin centres (float64, distorted when the scene says so) and visibility of
        the frames of ``d`` (from :meth:`_derive`), the first of which is ``lo``."""
        r = self.renderer
        rest = self._rest
        centre, a = d["centre"], d["a"]
        rel = rest[None, :, :] - centre[:, None, :]                              # (n, M, 2)
        dist = np.hypot(rel[..., 0], rel[..., 1])
        safe_d = np.maximum(dist, 1e-9)
        safe_a = np.maximum(a, 1e-9)[:, None]
        inside = dist < safe_a
        # normal spread falls off as (a/r)^2 outside the patch; shear carries
        # further, since the skin is one membrane: 1 / (1 + ((r - a) / a)^2)
        spread = np.where(inside, dist / safe_a, (safe_a / safe_d) ** 2)
        carry = np.where(inside, 1.0, 1.0 / (1.0 + ((dist - safe_a) / safe_a) ** 2))
        pins = (rest[None] + (d["u_n"][:, None] * spread / safe_d)[..., None] * rel
                + carry[..., None] * d["move"][:, None, :])
        amp = d["shake"]
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

    def _load_block(self, i: int) -> _Block:
        """The block holding frame ``i``: its truth, pins, visibility and motion."""
        b = self._block
        if b is not None and b.lo <= i < b.hi:
            return b
        lo = (int(i) // BLOCK) * BLOCK
        hi = min(lo + BLOCK, self.n_frames)
        start = max(lo - 1, 0)                 # one frame before: motion at ``lo``
        pin_in, truth = self._derive(self.physics.frames(start, hi), lo)
        k = lo - start
        if k:
            truth = {key: v[k:] for key, v in truth.items()}
        pins, visible = self._pins(pin_in, start)
        motion = self._motion(pins, first=int(lo == 0))
        self._block = _Block(lo, hi, truth, pins[k:].astype(np.float32), visible[k:], motion)
        return self._block

    def truth_block(self, i: int) -> tuple[int, dict]:
        """The first frame and the ground truth (TRUTH_KEYS but the pins) of the
        block of :data:`BLOCK` frames that holds frame ``i``; no pin is computed."""
        if not 0 <= i < self.n_frames:
            raise IndexError(f"frame index {i} out of range 0..{self.n_frames - 1}")
        b = self._block
        if b is not None and b.lo <= i < b.hi:
            return b.lo, b.truth
        t = self._truth_block
        if t is not None and t[0] <= i < t[0] + t[1]["t_s"].shape[0]:
            return t
        lo = (int(i) // BLOCK) * BLOCK
        hi = min(lo + BLOCK, self.n_frames)
        self._truth_block = (lo, self._derive(self.physics.frames(lo, hi), lo)[1])
        return self._truth_block

    def _whole_truth(self) -> dict:
        """TRUTH_KEYS but the pins, for the whole scene."""
        parts = [self.truth_block(lo)[1] for lo in range(0, self.n_frames, BLOCK)]
        return {k: np.concatenate([p[k] for p in parts]) for k in _BLOCK_KEYS}

    def _whole_pins(self) -> dict:
        """pins_px (F, M, 2) float32 and visible (F, M) for the whole scene."""
        M = self._rest.shape[0]
        pins = np.empty((self.n_frames, M, 2), np.float32)
        vis = np.empty((self.n_frames, M), bool)
        for lo in range(0, self.n_frames, BLOCK):
            b = self._load_block(lo)
            pins[b.lo:b.hi], vis[b.lo:b.hi] = b.pins, b.visible
        return {"pins_px": pins, "visible": vis}

    # -- frames ----------------------------------------------------------------
    def render(self, i: int, out: np.ndarray | None = None) -> np.ndarray:
        """Frame ``i`` as uint8 (H, W). Pass ``out`` to render without allocating;
        without it a fresh array is returned."""
        if not 0 <= i < self.n_frames:
            raise IndexError(f"frame index {i} out of range 0..{self.n_frames - 1}")
        b = self._load_block(i)
        k = i - b.lo
        return self.renderer.render(i, b.pins[k], b.visible[k], b.motion[k], out=out)

    def frames(self):
        """Yield (index, frame) with one reused buffer: copy a frame to keep it."""
        for i in range(self.n_frames):
            yield i, self.render(i, self._out)

    def labels(self, i: int) -> dict:
        """Frame ``i``'s labels, from its block (not the whole scene's truth)."""
        lo, t = self.truth_block(i)
        k = i - lo
        return {"surface": SURFACE_LABELS[int(t["surface"][k])],
                "texture": TEXTURE_LABELS[int(t["texture"][k])],
                "contact": bool(t["contact"][k]), "slip": bool(t["slip"][k])}
