"""Model inputs from windows, and rotated copies of windows for training.

Every model's input is built by :mod:`device.pi.models.window`, the encoders the Pi
runs: (N, D) float32 for the ``vectors`` and ``grids`` layouts, (N, T, S, S) for
``frames`` (the CNN's).
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from device.pi.models.window import encode_frames, encode_grids, encode_vectors
from host.data.extract import layout_for_profile
from host.learn.tasks import TrainError, check_choice, check_int

__all__ = ["model_inputs", "layout_rotations", "rotate_windows", "augment_rotations"]


def model_inputs(ws, layout: str, uses_imu: bool = False) -> np.ndarray:
    """Model inputs of a WindowSet, built by the Pi's encoders: (N, D) float32 for
    ``vectors`` and ``grids``, (N, T, S, S) for ``frames`` (the CNN's)."""
    check_choice("input_layout", layout, ("vectors", "grids", "frames"))
    if layout == "frames":
        if ws.frames is None:
            raise TrainError("input_layout frames needs the binary crops; these windows have "
                             "none (load them with a frame_size)")
        return encode_frames(ws.frames)
    if layout == "grids":
        if ws.grids is None:
            raise TrainError("input_layout grids needs contact grids; these windows have none "
                             "(an .npz of vectors carries no grids): use --model fnn")
        return encode_grids(ws.grids)
    if uses_imu and ws.imu is None:
        raise TrainError("uses_imu=True but the windows carry no IMU rows")
    return encode_vectors(ws.vectors, ws.imu if uses_imu else None)



def layout_rotations(layout_px, tol_px: float = 0.5) -> list[tuple[int, np.ndarray]]:
    """The rotations (whole degrees, 1..359) about the layout's centre that map the
    pin layout onto itself, each with its permutation: pin i lands on pin perm[i].
    For the roboskin layout (rings of 12 and 24 on common spokes) these are the
    multiples of 30 degrees."""
    p = np.asarray(layout_px, np.float64).reshape(-1, 2)
    q = p - p.mean(axis=0)
    out = []
    for deg in range(1, 360):
        th = math.radians(deg)
        R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
        r = q @ R.T
        d = np.hypot(r[:, None, 0] - q[None, :, 0], r[:, None, 1] - q[None, :, 1])
        perm = d.argmin(axis=1)
        if d[np.arange(len(q)), perm].max() <= tol_px and len(np.unique(perm)) == len(q):
            out.append((deg, perm))
    return out


def rotate_windows(ws, deg: float, perm: np.ndarray):
    """The windows as if every stimulus had come ``deg`` degrees rotated (image
    axes): pin vectors rotated and moved to the pins ``perm`` says, the IMU's x/y
    accelerations and x/y rates rotated (z unchanged). Grids and frames are dropped
    (None): they are not rotated."""
    perm = np.asarray(perm, np.int64)
    if perm.shape != (ws.n_pins,):
        raise TrainError(f"rotation permutation has {perm.size} pins, the windows {ws.n_pins}")
    th = math.radians(deg)
    R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]], np.float32)
    v = np.empty_like(ws.vectors)
    v[:, :, perm] = ws.vectors @ R.T
    lost = np.empty_like(ws.lost)
    lost[:, :, perm] = ws.lost
    imu = None
    if ws.imu is not None:
        imu = ws.imu.copy()
        imu[..., 0:2] = ws.imu[..., 0:2] @ R.T
        imu[..., 3:5] = ws.imu[..., 3:5] @ R.T
    return replace(ws, vectors=v, lost=lost, imu=imu, grids=None, frames=None,
                   source=dict(ws.source, rotated_deg=deg))


def augment_rotations(ws, copies: int, profile: str = "roboskin"):
    """``ws`` plus ``copies`` rotated copies of it (:func:`rotate_windows`), at
    rotations spread evenly over the layout's symmetries; labels, targets and
    groups are kept (a rotated window stays in its trial). For the ``vectors``
    layout only (grids are not rotated)."""
    copies = check_int("augment", copies, 0)
    if copies == 0:
        return ws
    lay = layout_for_profile(profile)
    if len(lay) != ws.n_pins:
        raise TrainError(f"augment: profile {profile!r} has {len(lay)} pins, the windows "
                         f"{ws.n_pins}")
    rots = layout_rotations(lay)
    if not rots:
        raise TrainError(f"augment: the pin layout of profile {profile!r} has no rotational "
                         f"symmetry to augment with")
    pick = np.unique(np.linspace(0, len(rots), copies + 1, endpoint=False)[1:].astype(int)
                     ) if copies < len(rots) else np.arange(len(rots))
    parts = [replace(ws, grids=None, frames=None)] + [rotate_windows(ws, *rots[i]) for i in pick]
    cat = {}
    for k in ("vectors", "lost", "imu", "contact", "labels", "targets", "groups", "t_index",
              "trial_len"):
        vals = [getattr(p, k) for p in parts]
        cat[k] = None if vals[0] is None else np.concatenate(vals)
    return replace(ws, **cat, grids=None, frames=None,
                   source=dict(ws.source, augmented_deg=[0] + [rots[i][0] for i in pick]))

