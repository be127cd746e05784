"""Contact physics for the scene simulator: simple, but physically sensible.

Per frame, from the timeline:

* commanded depth ``d`` (mm into the surface; negative = in the air) and the
  sensor body's lateral position ``p`` (mm);
* the skin and the surface act as springs in series, so a soft surface takes
  part of the travel: ``d_eff = d * k_s / (k_s + k_skin)``;
* Hertz: contact-patch radius ``a = sqrt(R d_eff)``, normal load
  ``N = 4/3 E* sqrt(R) d_eff^1.5``;
* Coulomb: the patch sticks to the surface, so a body move ``dp`` adds
  ``-dp`` to the patch shear ``s`` until ``k_t |s|`` reaches ``mu N``; past
  that the patch slides (a slip frame) and the shear falls to the kinetic
  limit ``mu_k N / k_t``. With ``stick_slip`` the static limit is checked
  again after every slide, which gives the saw-tooth of stick-slip.
* pins inside the patch spread radially outward, in proportion to
  ``d_eff`` and to ``r / a``; outside they fall off as ``(a / r)^2``. Shear
  moves the patch pins along ``s`` with the same fall-off.
* textures jitter the patch pins while it slides: Lego periodically at
  ``slide speed / stud pitch``, concrete at random, smooth not at all; with
  ``pin_shake_mm`` each patch pin also shakes on its own, at random.

:class:`Physics` computes any range of frames, deterministic for a seed, holding
only that range: the state that carries from frame to frame lives in a
:class:`ContactStream`, so the memory a scene takes does not grow with its length.
"""
from __future__ import annotations

import math
import zlib

import numpy as np

from .scene import SURFACE_LABELS, TEXTURE_LABELS, Scene

G_MM_S2 = 9806.65
CONTACT_EPS_MM = 1e-3
#: ground-truth ``contact`` means the foot carries at least this load; lighter
#: touches (``touch``) are physically there but bear almost nothing (~50 g)
CONTACT_FLOOR_N = 0.5


def stream(seed: int, name: str) -> np.random.Generator:
    """An independent random stream per purpose, so that turning one effect on
    never changes the random numbers another one draws."""
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, zlib.crc32(name.encode())])


def timeline_frames(scene: Scene) -> int:
    """How many frames the scene's timeline lasts (each action at least one)."""
    return sum(max(1, int(round(act.duration_s * scene.fps))) for act in scene.timeline)


def _walk(scene: Scene):
    """The timeline one frame at a time: (commanded depth mm, body x, y mm, surface
    index, contact offset x, y mm) per frame."""
    fps = scene.fps
    names = list(scene.surfaces)
    d = -scene.hover_mm
    px = py = 0.0
    s_idx = names.index(scene.surface)
    ox = oy = 0.0
    for act in scene.timeline:
        n = max(1, int(round(act.duration_s * fps)))
        if act.surface is not None:
            s_idx = names.index(act.surface)
        start_d = d
        if act.kind == "lower":
            ox, oy = float(act.offset_mm[0]), float(act.offset_mm[1])
        sx = sy = 0.0
        if act.kind == "drag":
            th = math.radians(act.direction_deg)
            sx, sy = act.speed_mm_s / fps * math.cos(th), act.speed_mm_s / fps * math.sin(th)
        for k in range(1, n + 1):
            if act.kind == "lower":
                d = start_d + (act.depth_mm - start_d) * k / n
            elif act.kind == "lift":
                d = start_d + (-act.height_mm - start_d) * k / n
            px += sx
            py += sy
            yield d, px, py, s_idx, ox, oy


#: the per-frame arrays :class:`ContactStream` gives, and their dtypes
RAW_KEYS = {"depth_cmd_mm": float, "body_mm": (float, 2), "contact_offset_mm": (float, 2),
            "surf_idx": np.int16, "depth_mm": float, "load_n": float, "patch_radius_mm": float,
            "shear_mm": (float, 2), "jitter_mm": (float, 2), "bump_mm": float,
            "shake_mm": float, "slip": bool, "touch": bool, "slide_speed_mm_s": float}


class ContactStream:
    """The contact physics of a scene, frame after frame from frame 0: the state
    that carries from one frame to the next (the stored shear, sliding, the
    distance slid, the texture's random stream) lives here, so the scene is
    computed in chunks of any size with the same result as in one piece."""

    def __init__(self, scene: Scene, seed: int = 0):
        self.scene = scene
        prof = scene.profile
        self._surfaces = list(scene.surfaces.values())
        self._sqrt_r = math.sqrt(prof.dome_radius_mm)
        self._r = prof.dome_radius_mm
        self._e = prof.modulus_n_per_mm2
        self._k_skin = prof.skin_stiffness_n_per_mm
        self._k_t = prof.tangential_stiffness_n_per_mm
        self._tex_rng = stream(seed, "texture")
        self._walk = _walk(scene)
        first = [row[1:3] for _, row in zip(range(2), _walk(scene))]
        (x0, y0), (x1, y1) = first[0], first[-1]
        self._prev = (x0 - (x1 - x0), y0 - (y1 - y0))     # one step before frame 0
        self._s = (0.0, 0.0)
        self._sliding = False
        self._slid = 0.0
        self.frame = 0                      # the frame next() starts at

    def next(self, n: int) -> dict:
        """The next ``n`` frames (fewer at the end of the scene): RAW_KEYS arrays."""
        out = {k: np.zeros((n, t[1]) if isinstance(t, tuple) else n,
                           t[0] if isinstance(t, tuple) else t) for k, t in RAW_KEYS.items()}
        fps = self.scene.fps
        k_skin, k_t, e, sqrt_r, r = self._k_skin, self._k_t, self._e, self._sqrt_r, self._r
        (sx, sy), (qx, qy) = self._s, self._prev
        sliding, slid = self._sliding, self._slid
        depth_cmd, body, off, surf = (out["depth_cmd_mm"], out["body_mm"],
                                      out["contact_offset_mm"], out["surf_idx"])
        d_eff, load, a_mm, shear = out["depth_mm"], out["load_n"], out["patch_radius_mm"], out["shear_mm"]
        jitter, bump, shake, slip = out["jitter_mm"], out["bump_mm"], out["shake_mm"], out["slip"]
        touch, slide_speed = out["touch"], out["slide_speed_mm_s"]
        i = 0
        for i, (dc, px, py, s_idx, ox, oy) in zip(range(n), self._walk):
            depth_cmd[i], body[i], off[i], surf[i] = dc, (px, py), (ox, oy), s_idx
            sf = self._surfaces[s_idx]
            dpx, dpy = px - qx, py - qy
            qx, qy = px, py
            d = max(dc, 0.0) * sf.stiffness_n_per_mm / (sf.stiffness_n_per_mm + k_skin)
            d_eff[i] = d
            if d <= CONTACT_EPS_MM:
                sx = sy = 0.0
                sliding = False
                continue
            touch[i] = True
            big_n = 4.0 / 3.0 * e * sqrt_r * d ** 1.5
            load[i] = big_n
            a_mm[i] = math.sqrt(r * d)
            lim_static = sf.mu * big_n / k_t
            lim_kinetic = sf.mu * sf.mu_kinetic_ratio * big_n / k_t
            nx, ny = sx - dpx, sy - dpy
            mag = math.hypot(nx, ny)
            limit = lim_kinetic if (sliding and not sf.stick_slip) else lim_static
            if mag > limit:
                slipped = mag - lim_kinetic
                sx, sy = nx * (lim_kinetic / mag), ny * (lim_kinetic / mag)
                sliding = True
                slip[i] = True
                slid += slipped
                slide_speed[i] = slipped * fps
                ux, uy = -nx / mag, -ny / mag
                shake[i] = sf.pin_shake_mm
                amp = sf.texture_amplitude_mm
                if sf.texture == "lego" and amp > 0:
                    ph = 2 * math.pi * slid / sf.stud_pitch_mm
                    jitter[i] = (amp * math.sin(ph) * ux, amp * math.sin(ph) * uy)
                    bump[i] = 0.5 * amp * (1 + math.cos(ph))
                elif sf.texture == "concrete" and amp > 0:
                    jitter[i] = amp * self._tex_rng.standard_normal(2)
                    bump[i] = 0.5 * amp * abs(self._tex_rng.standard_normal())
            else:
                sx, sy = nx, ny
                sliding = False
            shear[i] = (sx, sy)
        else:
            i = -1 if n == 0 else i
        got = i + 1 if n else 0
        if got < n:         # the scene ended
            out = {k: v[:got] for k, v in out.items()}
        self._s, self._prev, self._sliding, self._slid = (sx, sy), (qx, qy), sliding, slid
        self.frame += got
        return out


def impact_frames(fps: float) -> int:
    """Frames a touchdown impact lasts in the IMU (about 20 ms)."""
    return max(1, int(0.02 * fps) + 1)


class Physics:
    """A scene's ground truth (what :func:`simulate_contact` gives) for any range of
    frames, holding at most that range and a few frames around it.

    Ranges asked in increasing order (rendering a scene) cost one pass over the
    scene; a range before the last one starts the pass again from frame 0."""

    def __init__(self, scene: Scene, seed: int = 0):
        self.scene, self.seed = scene, int(seed)
        self.n_frames = timeline_frames(scene)
        # the IMU of a frame needs the frame after it and the touchdowns before it
        self.margin = impact_frames(scene.fps) + 1
        surfaces = list(scene.surfaces.values())
        self._label_code = np.array([SURFACE_LABELS.index(x.label) for x in surfaces], np.int8)
        self._tex_code = np.array([TEXTURE_LABELS.index(x.texture) for x in surfaces], np.int8)
        self._restart()

    def _restart(self) -> None:
        self._stream = ContactStream(self.scene, self.seed)
        self._buf: dict | None = None
        self._lo = self._hi = 0             # the buffer holds frames lo..hi-1

    def _raw(self, a: int, b: int) -> dict:
        if a < self._lo:
            self._restart()
        if self._hi <= a:                   # skip ahead: run the physics, keep nothing
            while self._hi < a:
                self._hi += len(self._stream.next(min(1024, a - self._hi))["slip"])
            self._buf, self._lo = None, a
        elif self._buf is not None:
            self._buf = {k: v[a - self._lo:] for k, v in self._buf.items()}
            self._lo = a
        if b > self._hi:
            new = self._stream.next(b - self._hi)
            self._buf = new if self._buf is None else {
                k: np.concatenate([v, new[k]]) for k, v in self._buf.items()}
            self._hi = b
        return {k: v[:b - a] for k, v in self._buf.items()}

    def frames(self, lo: int, hi: int) -> dict:
        """Ground truth of frames ``lo..hi-1`` (all arrays have ``hi - lo`` rows)."""
        lo, hi = max(0, int(lo)), min(self.n_frames, int(hi))
        a, b = max(0, lo - self.margin), min(self.n_frames, hi + 1)
        r = self._raw(a, b)
        imu = imu_truth(self.scene, r["depth_cmd_mm"], r["body_mm"], r["touch"], r["slip"],
                        r["shear_mm"], r["jitter_mm"], r["bump_mm"], self.seed)
        k = slice(lo - a, hi - a)
        out = {key: r[key][k].copy() for key in RAW_KEYS if key != "surf_idx"}
        surf_idx = r["surf_idx"][k]
        contact = out["touch"] & (out["load_n"] >= CONTACT_FLOOR_N)
        out.update(t_s=np.arange(lo, hi) / self.scene.fps, contact=contact,
                   surface=np.where(contact, self._label_code[surf_idx], 0).astype(np.int8),
                   texture=np.where(contact, self._tex_code[surf_idx], 0).astype(np.int8),
                   imu_true=imu[k].copy())
        return out


def simulate_contact(scene: Scene, seed: int = 0) -> dict:
    """Ground truth for every frame of ``scene`` (all arrays have F rows)."""
    ph = Physics(scene, seed)
    return ph.frames(0, ph.n_frames)


def imu_truth(scene: Scene, depth_cmd, body, contact, slip, shear, jitter, bump, seed) -> np.ndarray:
    """The foot's true IMU motion: ax, ay, az [g], gx, gy, gz [deg/s] per frame.

    Kinematic acceleration of the body, gravity on z, a touchdown impact, the
    drag vibration a texture causes (from its jitter), and a jerk at slip onset.
    """
    F = depth_cmd.shape[0]
    fps = scene.fps
    out = np.zeros((F, 6))
    if F == 0:
        return out
    pos = np.column_stack([body, -depth_cmd])            # z up, mm
    if F >= 3:
        acc = np.zeros_like(pos)
        acc[1:-1] = (pos[2:] - 2 * pos[1:-1] + pos[:-2]) * fps * fps
        out[:, :3] = acc / G_MM_S2
    out[:, 2] += 1.0
    # touchdown impact: proportional to the descent speed, decaying over ~20 ms
    touch = np.flatnonzero(contact[1:] & ~contact[:-1]) + 1
    vz = np.zeros(F)
    vz[1:] = np.diff(depth_cmd) * fps                      # mm/s downward
    decay = np.exp(-np.arange(impact_frames(fps)) / max(1.0, 0.005 * fps))
    for i in touch:
        n = min(decay.size, F - i)
        out[i:i + n, 2] += 0.004 * max(vz[i], 0.0) * decay[:n]
    # texture vibration felt through the foot (jitter mm -> g at frame rate)
    vib = np.zeros((F, 2))
    vib[1:] = np.diff(jitter, axis=0)
    out[:, :2] += vib * fps * fps / G_MM_S2 * 0.05
    dbump = np.zeros(F)
    dbump[1:] = np.diff(bump)
    out[:, 2] += dbump * fps * fps / G_MM_S2 * 0.05
    out[:, 3] += 40.0 * vib[:, 1]
    out[:, 4] -= 40.0 * vib[:, 0]
    # slip onset: a jerk along the release of the stored shear
    onset = np.flatnonzero(slip & ~np.concatenate([[False], slip[:-1]]))
    for i in onset:
        s = shear[i - 1] if i > 0 else shear[i]
        n = np.hypot(*s)
        if n > 0:
            out[i, :2] += 0.3 * s / n
            out[i, 5] += 15.0
    return out
