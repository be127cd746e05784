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

Everything is computed for the whole timeline up front, deterministic for a
seed; rendering then only draws.
"""
from __future__ import annotations

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


def expand_timeline(scene: Scene):
    """Per-frame commanded depth, body position, surface index and drag velocity."""
    fps = scene.fps
    names = list(scene.surfaces)
    depth, pos, surf, offset = [], [], [], []
    d = -scene.hover_mm
    p = np.zeros(2)
    s_idx = names.index(scene.surface)
    off = np.zeros(2)
    for act in scene.timeline:
        n = max(1, int(round(act.duration_s * fps)))
        if act.surface is not None:
            s_idx = names.index(act.surface)
        start_d = d
        if act.kind == "lower":
            off = np.asarray(act.offset_mm, dtype=float)
        step = np.zeros(2)
        if act.kind == "drag":
            th = np.deg2rad(act.direction_deg)
            step = act.speed_mm_s / fps * np.array([np.cos(th), np.sin(th)])
        for k in range(1, n + 1):
            if act.kind == "lower":
                d = start_d + (act.depth_mm - start_d) * k / n
            elif act.kind == "lift":
                d = start_d + (-act.height_mm - start_d) * k / n
            p = p + step
            depth.append(d)
            pos.append(p.copy())
            surf.append(s_idx)
            offset.append(off.copy())
    return (np.asarray(depth), np.asarray(pos).reshape(-1, 2), np.asarray(surf, dtype=np.int16),
            np.asarray(offset).reshape(-1, 2))


def simulate_contact(scene: Scene, seed: int = 0) -> dict:
    """Ground truth for every frame of ``scene`` (all arrays have F rows)."""
    prof = scene.profile
    depth_cmd, body, surf_idx, offset = expand_timeline(scene)
    F = depth_cmd.shape[0]
    surfaces = list(scene.surfaces.values())
    R = prof.dome_radius_mm
    E = prof.modulus_n_per_mm2
    k_skin = prof.skin_stiffness_n_per_mm
    k_t = prof.tangential_stiffness_n_per_mm
    tex_rng = stream(seed, "texture")

    d_eff = np.zeros(F)
    load = np.zeros(F)
    a_mm = np.zeros(F)
    shear = np.zeros((F, 2))
    jitter = np.zeros((F, 2))
    bump = np.zeros(F)                 # extra indentation from Lego studs
    shake = np.zeros(F)                # per-pin shake amplitude (mm) while sliding
    slip = np.zeros(F, dtype=bool)
    touch = np.zeros(F, dtype=bool)
    slide_speed = np.zeros(F)          # mm/s of skin sliding over the surface
    s = np.zeros(2)
    sliding = False
    slid = 0.0                         # distance slid so far (texture phase)
    prev = body[0] - (body[1] - body[0] if F > 1 else 0.0)
    for i in range(F):
        sf = surfaces[surf_idx[i]]
        dp = body[i] - prev
        prev = body[i]
        d = max(depth_cmd[i], 0.0) * sf.stiffness_n_per_mm / (sf.stiffness_n_per_mm + k_skin)
        d_eff[i] = d
        if d <= CONTACT_EPS_MM:
            s[:] = 0.0
            sliding = False
            continue
        touch[i] = True
        N = 4.0 / 3.0 * E * np.sqrt(R) * d ** 1.5
        load[i] = N
        a_mm[i] = np.sqrt(R * d)
        lim_static = sf.mu * N / k_t
        lim_kinetic = sf.mu * sf.mu_kinetic_ratio * N / k_t
        s_new = s - dp
        mag = float(np.hypot(*s_new))
        limit = lim_kinetic if (sliding and not sf.stick_slip) else lim_static
        if mag > limit:
            slipped = mag - lim_kinetic
            s = s_new * (lim_kinetic / mag)
            sliding = True
            slip[i] = True
            slid += slipped
            slide_speed[i] = slipped * scene.fps
            direction = -s_new / mag
            shake[i] = sf.pin_shake_mm
            if sf.texture == "lego" and sf.texture_amplitude_mm > 0:
                ph = 2 * np.pi * slid / sf.stud_pitch_mm
                jitter[i] = sf.texture_amplitude_mm * np.sin(ph) * direction
                bump[i] = 0.5 * sf.texture_amplitude_mm * (1 + np.cos(ph))
            elif sf.texture == "concrete" and sf.texture_amplitude_mm > 0:
                jitter[i] = sf.texture_amplitude_mm * tex_rng.standard_normal(2)
                bump[i] = 0.5 * sf.texture_amplitude_mm * abs(tex_rng.standard_normal())
        else:
            s = s_new
            sliding = False
        shear[i] = s

    label_code = np.array([SURFACE_LABELS.index(x.label) for x in surfaces], dtype=np.int8)
    tex_code = np.array([TEXTURE_LABELS.index(x.texture) for x in surfaces], dtype=np.int8)
    contact = touch & (load >= CONTACT_FLOOR_N)
    surface_code = np.where(contact, label_code[surf_idx], 0).astype(np.int8)
    texture_code = np.where(contact, tex_code[surf_idx], 0).astype(np.int8)
    imu = imu_truth(scene, depth_cmd, body, touch, slip, shear, jitter, bump, seed)
    return {
        "t_s": np.arange(F) / scene.fps,
        "depth_cmd_mm": depth_cmd,
        "depth_mm": d_eff,
        "body_mm": body,
        "contact_offset_mm": offset,
        "load_n": load,
        "patch_radius_mm": a_mm,
        "shear_mm": shear,
        "jitter_mm": jitter,
        "bump_mm": bump,
        "shake_mm": shake,
        "slip": slip,
        "slide_speed_mm_s": slide_speed,
        "contact": contact,
        "touch": touch,
        "surface": surface_code,
        "texture": texture_code,
        "imu_true": imu,
    }


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
    decay = np.exp(-np.arange(max(1, int(0.02 * fps) + 1)) / max(1.0, 0.005 * fps))
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
