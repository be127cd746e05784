"""Frame rendering for the scene simulator.

The static parts (dome, surround, glare layer, noise bank, sprite bank) are
built once. Per frame the renderer copies the background, stamps every visible
pin from a bank of sub-pixel sprites in one vectorised write, then applies only
the effects the scene names, in a fixed order:
glare -> motion blur -> exposure -> exposure flicker -> camera noise.
Effects that are not named cost nothing and leave no trace.
"""
from __future__ import annotations

import math

import cv2
import numpy as np

from .physics import stream
from device.profile import SensorProfile

SUBPIXEL = 4          # sprite phases per pixel and axis
NOISE_BANK = 16       # pre-drawn noise frames
DRAW_BLOCK = 256      # frames whose random draws (flicker, noise pick) are made together


def distort_points(xy: np.ndarray, width: int, height: int, k1: float) -> np.ndarray:
    """One-term radial lens distortion about the image centre (r normalised
    by the half-diagonal): ``x_d = c + (x - c)(1 + k1 r^2)``."""
    c = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
    norm = math.hypot(width, height) / 2.0
    rel = (xy - c) / norm
    r2 = np.sum(rel * rel, axis=-1, keepdims=True)
    return c + rel * (1.0 + k1 * r2) * norm


class BlockDraws:
    """Per-frame random draws (``draws[i]``) made a block of :data:`DRAW_BLOCK` frames
    at a time, each block from its own stream: a scene of any length holds one
    block, and frame i's draw does not depend on the scene's length."""

    def __init__(self, seed: int, name: str, n_frames: int, draw):
        self.seed, self.name, self.n_frames, self._draw = int(seed), name, int(n_frames), draw
        self._b, self._values = -1, None

    def __getitem__(self, i: int):
        b = int(i) // DRAW_BLOCK
        if b != self._b:
            n = min(DRAW_BLOCK, self.n_frames - b * DRAW_BLOCK)
            self._values = self._draw(stream(self.seed, f"{self.name}/{b}"), max(n, 1))
            self._b = b
        return self._values[int(i) - b * DRAW_BLOCK]

    def __len__(self) -> int:
        return self.n_frames


class Renderer:
    def __init__(self, profile: SensorProfile, width: int, height: int, effects: dict,
                 n_frames: int, seed: int = 0):
        self.profile = profile
        self.width, self.height = width, height
        self.effects = effects
        sx, sy = width / profile.width, height / profile.height
        self.scale = 0.5 * (sx + sy)
        self.centre = np.array(profile.dome_centre_px) * (sx, sy)
        self.dome_r = profile.dome_radius_px * self.scale
        self.pin_r = max(0.5, 0.5 * profile.pin_diameter_px * self.scale)
        self.binary = profile.style == "binary"
        self.background = self._background()
        if "lens_distortion" in effects:
            self.background = self._distort_image(self.background,
                                                  effects["lens_distortion"]["k1"])
        self._bg_flat = self.background.reshape(-1).astype(np.float32)
        self._build_sprites()
        self.box_half = self._sprite_c
        self.box = self._sprite_size
        if "glare" in effects:
            self.glare = self._glare_layer(effects["glare"])
        if "motion_blur" in effects:
            yy, xx = np.mgrid[0:height, 0:width]
            self._outside = (np.hypot(xx - self.centre[0], yy - self.centre[1])
                             > self.dome_r)
        if "exposure_flicker" in effects:
            amp = effects["exposure_flicker"]["amplitude"]
            self.gains = BlockDraws(seed, "exposure_flicker", n_frames, lambda rng, n: np.clip(
                1.0 + amp * rng.standard_normal(n), 0.05, 4.0))
        if "camera_noise" in effects:
            rng = stream(seed, "camera_noise")
            sigma = effects["camera_noise"]["sigma"]
            bank = np.rint(rng.standard_normal((NOISE_BANK, height, width), dtype=np.float32)
                           * sigma)
            bank = np.clip(bank, -255, 255)
            self.noise_pos = np.maximum(bank, 0).astype(np.uint8)
            self.noise_neg = np.maximum(-bank, 0).astype(np.uint8)
            self.noise_pick = BlockDraws(seed, "camera_noise/pick", n_frames,
                                         lambda rng, n: rng.integers(0, NOISE_BANK, size=n))

    # -- static layers -------------------------------------------------------
    def _background(self) -> np.ndarray:
        p = self.profile
        h, w = self.height, self.width
        if self.binary:
            return np.full((h, w), p.dome_level if p.dome_level else 0, np.uint8)
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        r = np.hypot(xx - self.centre[0], yy - self.centre[1])
        rim = (p.rim_radius_px or p.dome_radius_px) * self.scale
        img = np.full((h, w), p.surround_level, np.float32)
        # the surround dims towards the frame corners, as a wide-angle lens does
        far = np.clip((r - 1.6 * self.dome_r) / (2.2 * self.dome_r), 0, 1)
        img -= far ** 2 * 0.6 * p.surround_level
        inner = p.dome_level * (1.0 - p.vignette * np.clip(r / rim, 0, 1) ** 2)
        # the dome wall: darkest at the rim radius, dark out to the dome's edge
        wall = 0.45 * p.dome_level
        dip = np.exp(-((r - rim) / max(1.0, 5.0 * self.scale)) ** 2)
        inner = inner * (1.0 - dip) + wall * dip
        inner = np.where(r > rim, wall, inner)
        img = np.where(r <= self.dome_r, inner, img)
        k = max(3, int(2 * round(2 * self.scale) + 1))
        img = cv2.GaussianBlur(img, (k, k), 0)
        return np.clip(img, 0, 255).astype(np.uint8)

    def _distort_image(self, img: np.ndarray, k1: float) -> np.ndarray:
        h, w = img.shape
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
        # the inverse of distort_points to first order is the same map with -k1
        src = distort_points(np.stack([xx, yy], axis=-1), w, h, -k1).astype(np.float32)
        return cv2.remap(img, src[..., 0], src[..., 1], cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE)

    def _glare_layer(self, params: dict) -> np.ndarray:
        g = self.profile.glare
        sx, sy = self.width / self.profile.width, self.height / self.profile.height
        count = int(params["count"]) if params["count"] >= 0 else (g.count or 6)
        peak = params["peak"] if params["peak"] >= 0 else (g.peak or 70.0)
        ring = g.ring_radius_px * self.scale if g.count else 0.45 * self.dome_r
        sigma = (g.sigma_px * self.scale) if g.count else 0.08 * self.dome_r
        if params["sigma_px"] > 0:
            sigma = params["sigma_px"] * self.scale
        centre = (np.array(g.centre_px) * (sx, sy) if g.centre_px is not None
                  else self.centre)
        blobs = [(centre[0] + ring * math.cos(th), centre[1] + ring * math.sin(th), peak)
                 for th in (math.radians(g.phase_deg) + 2 * math.pi * k / max(count, 1)
                            for k in range(count))]
        if g.centre_peak > 0:
            off = np.array(g.centre_offset_px) * (sx, sy)
            blobs.append((self.centre[0] + off[0], self.centre[1] + off[1],
                          g.centre_peak * peak / max(g.peak, 1e-9)))
        h, w = self.height, self.width
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        layer = np.zeros((h, w), np.float32)
        for cx, cy, amp in blobs:
            layer += amp * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * sigma * sigma))
        # glare lights the dome, not the already-white surround
        layer *= np.hypot(xx - self.centre[0], yy - self.centre[1]) <= self.dome_r
        layer = np.clip(layer, 0, 255)
        if self.binary:
            layer = np.where(layer > 0.5 * peak, 255.0, 0.0)
        return layer.astype(np.uint8)

    def _build_sprites(self):
        rp = self.pin_r
        # camera pins have a soft, Gaussian-like profile (sigma ~ diameter / 2.8,
        # as measured on the real clips); binary pins are hard discs
        sigma = 2.0 * rp / 2.8
        c = int(math.ceil(rp)) + 1 if self.binary else int(math.ceil(2.5 * sigma))
        size = 2 * c + 1
        q = SUBPIXEL
        alphas, offsets = [], []
        yy, xx = np.mgrid[0:size, 0:size].astype(np.float64)
        for fy in range(q):
            for fx in range(q):
                d = np.hypot(xx - c - fx / q, yy - c - fy / q)
                if self.binary:
                    a = (d <= rp).astype(np.float64)
                else:
                    a = np.exp(-0.5 * (d / sigma) ** 2)
                    a[a < 0.03] = 0.0
                ys, xs = np.nonzero(a > 0)
                if ys.size == 0:
                    ys, xs = np.array([c]), np.array([c])
                alphas.append(a[ys, xs])
                offsets.append(ys * self.width + xs)
        k = max(len(a) for a in alphas)
        self._alpha = np.zeros((q * q, k), np.float32)
        self._offs = np.zeros((q * q, k), np.int64)
        for v, (a, o) in enumerate(zip(alphas, offsets)):
            # pad by repeating the first pixel: rewriting it is harmless
            self._alpha[v, :a.size], self._alpha[v, a.size:] = a, a[0]
            self._offs[v, :o.size], self._offs[v, o.size:] = o, o[0]
        self._sprite_c = c
        self._sprite_size = size

    def drawable(self, pins: np.ndarray) -> np.ndarray:
        """Which pins' sprite boxes lie fully inside the frame (pins: (..., 2))."""
        c = self._sprite_c
        x, y = pins[..., 0], pins[..., 1]
        return ((x >= c) & (y >= c) & (x < self.width - c - 1) & (y < self.height - c - 1)
                & np.isfinite(x) & np.isfinite(y))

    # -- per frame -------------------------------------------------------------
    def render(self, i: int, pins: np.ndarray, visible: np.ndarray, pin_motion: np.ndarray,
               out: np.ndarray | None = None) -> np.ndarray:
        if out is None:
            out = np.empty((self.height, self.width), np.uint8)
        np.copyto(out, self.background)
        p = pins[visible]
        if p.shape[0]:
            q = SUBPIXEL
            pq = np.floor(p * q + 0.5).astype(np.int64)
            ix, iy = pq[:, 0] // q, pq[:, 1] // q
            var = (pq[:, 1] - iy * q) * q + (pq[:, 0] - ix * q)
            base = (iy - self._sprite_c) * self.width + (ix - self._sprite_c)
            idx = base[:, None] + self._offs[var]
            a = self._alpha[var]
            bg = self._bg_flat[idx]
            out.reshape(-1)[idx] = (bg + a * (self.profile.pin_level - bg) + 0.5).astype(np.uint8)
        fx = self.effects
        if "glare" in fx:
            cv2.add(out, self.glare, dst=out)
        if "motion_blur" in fx:
            self._motion_blur(out, pin_motion)
        if "exposure" in fx:
            cv2.convertScaleAbs(out, dst=out, alpha=float(fx["exposure"]["gain"]))
        if "exposure_flicker" in fx:
            cv2.convertScaleAbs(out, dst=out, alpha=float(self.gains[i]))
        if "camera_noise" in fx:
            k = self.noise_pick[i]
            cv2.add(out, self.noise_pos[k], dst=out)
            cv2.subtract(out, self.noise_neg[k], dst=out)
        if self.binary and ("camera_noise" in fx or "motion_blur" in fx
                            or "exposure_flicker" in fx or "exposure" in fx):
            cv2.threshold(out, 127, 255, cv2.THRESH_BINARY, dst=out)
        return out

    def _motion_blur(self, out: np.ndarray, pin_motion: np.ndarray):
        """Blur the dome by how far pins travel during the exposure: along the
        mean pin velocity when the pins move together (shear), isotropically
        when they spread (a press)."""
        exposure_s = self.effects["motion_blur"]["exposure_ms"] / 1000.0
        v = np.asarray(pin_motion[:2], dtype=np.float64) * exposure_s
        speed = float(pin_motion[2]) * exposure_s
        length = float(np.hypot(*v))
        if speed < 0.5:
            return
        n = int(min(64, math.ceil(speed))) | 1
        c = n // 2
        if length >= 0.5 * speed:
            kern = np.zeros((n, n), np.float32)
            ux, uy = v / length
            for t in np.linspace(-c, c, 4 * n):
                kern[int(round(c + t * uy)), int(round(c + t * ux))] = 1.0
        else:
            kern = np.ones((n, n), np.float32)
        kern /= kern.sum()
        blurred = cv2.filter2D(out, -1, kern, borderType=cv2.BORDER_REPLICATE)
        np.copyto(blurred, self.background, where=self._outside)
        np.copyto(out, blurred)
