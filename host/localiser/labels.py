"""Automatic labels of real clips for the pin localiser.

The profile's layout is fitted to a rest frame (similarity transform,
one-to-one ICP), then tracked frame to frame; every frame's labels are checked
(pins matched, duplicates, collapsed labels, neighbour consistency) and frames
that fail are rejected and listed with the reason.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from device.pi.vision.extract import PinDetector, VisionParams, find_dome, to_gray
from device.pi.vision.matching import mutual_match
from device.pi.vision.neighbours import layout_neighbours, layout_pitch_px, nearest_neighbour_px
from device.pi.vision.tracking import Tracker
from host.data.video import video_frames
from host.localiser.samples import Sample, progress_bar, sensor_geometry, vision_params_for

__all__ = [
    "REAL_CLIPS",
    "REAL_HOLDOUT_FRAC",
    "LabelChecks",
    "fit_layout",
    "check_labels",
    "read_clip",
    "label_clip",
    "real_samples",
]

#: roboskin clips of the seed paper's sensor used for real labels (flatSkin is another skin)
REAL_CLIPS = ("smooth", "concrete", "north", "east")
#: share of each real clip (its end) held out for the real-data metrics
REAL_HOLDOUT_FRAC = 0.2
#: matching gate of the rest-frame fit and of the tracking, in pin pitches
GATE_PITCH = 0.4


def _similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares scale, rotation (2x2) and translation with dst ~ s R src + t (Umeyama)."""
    ms, md = src.mean(0), dst.mean(0)
    a, b = src - ms, dst - md
    cov = b.T @ a / len(src)
    u, sv, vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(u @ vt))
    D = np.diag([1.0, d])
    R = u @ D @ vt
    var = (a * a).sum() / len(src)
    s = float((sv * np.diag(D)).sum() / var) if var > 0 else 1.0
    return s, R, md - s * (R @ ms)


def fit_layout(layout_px: np.ndarray, xy: np.ndarray, gate_px: float,
               iters: int = 15) -> dict:
    """Fit a similarity transform of the layout to detected pins (ICP, one to one).

    ``layout_px`` (N, 2) is the profile's rest layout already placed near
    the pins. Returns ``pins_px`` (N, 2) fitted layout, ``idx`` (N,) matched
    detection or -1, ``scale``, ``rotation_deg``, ``shift_px`` and
    ``residual_px`` (RMS over matched pins).
    """
    L = np.asarray(layout_px, np.float64)
    P = np.asarray(xy, np.float64).reshape(-1, 2)
    cur = L.copy()
    s, R, t = 1.0, np.eye(2), np.zeros(2)
    idx = mutual_match(cur, P, gate_px)
    for _ in range(iters):
        ok = idx >= 0
        if ok.sum() < 3:
            break
        s, R, t = _similarity(L[ok], P[idx[ok]])
        cur = (s * (R @ L.T)).T + t
        new = mutual_match(cur, P, gate_px)
        if np.array_equal(new, idx):
            break
        idx = new
    ok = idx >= 0
    res = float(np.sqrt(np.mean(((cur[ok] - P[idx[ok]]) ** 2).sum(1)))) if ok.any() else math.inf
    return {"pins_px": cur, "idx": idx, "scale": float(s),
            "rotation_deg": float(math.degrees(math.atan2(R[1, 0], R[0, 0]))),
            "shift_px": t, "residual_px": res}


@dataclass(frozen=True)
class LabelChecks:
    """Thresholds of the per-frame label check (see :func:`check_labels`)."""

    min_matched_frac: float = 0.75
    """Share of the N pins that must be matched to a detection."""
    max_inconsistent: int = 4
    """Most matched pins whose displacement may differ from the median of their
    layout neighbours' by more than ``inconsistent_pitch`` pitches."""
    inconsistent_pitch: float = 0.35
    max_residual_px: float = 1.0
    """With ``residual_per_disp``: the RMS (over matched pins) of that difference
    may be at most ``max_residual_px + residual_per_disp * D``, D the median
    displacement of the pins from rest (px): real strain makes neighbours differ
    more the more the skin is deformed (measured on the roboskin clips: RMS
    0.4 px at rest, about 0.25 D under drag)."""
    residual_per_disp: float = 0.35
    min_spacing_pitch: float = 0.4
    """Two labels closer than this many pitches are a collapse."""
    max_fit_residual_px: float = 1.5
    """The rest-frame layout fit must be at least this good, px."""


def check_labels(labels_px: np.ndarray, matched: np.ndarray, idx: np.ndarray,
                 rest_px: np.ndarray, nbr: np.ndarray, pitch_px: float,
                 checks: LabelChecks = LabelChecks()) -> str | None:
    """Why one frame's labels are not to be trusted, or None when they pass.

    ``labels_px`` (N, 2) labelled pins; ``matched`` (N,) which are measured
    (a detection assigned); ``idx`` (N,) the assigned detection or -1;
    ``rest_px`` (N, 2) the rest layout; ``nbr`` (N, k) layout neighbours
    (:func:`device.pi.vision.tracking.layout_neighbours`).
    Checks, in order: enough pins matched; no detection assigned twice; all
    labels finite; no two labels collapsed together; displacement consistent
    with the neighbours' (count and RMS).
    """
    lab = np.asarray(labels_px, np.float64)
    n = len(lab)
    m = np.asarray(matched, bool)
    n_m = int(m.sum())
    if n_m < checks.min_matched_frac * n:
        return f"too few pins matched ({n_m}/{n} < {checks.min_matched_frac:.0%})"
    used = np.asarray(idx)[m]
    if len(np.unique(used)) != len(used):
        return f"duplicate assignment ({len(used) - len(np.unique(used))} detections used twice)"
    if not np.isfinite(lab).all():
        return "non-finite labels"
    dmin = float(nearest_neighbour_px(lab).min(initial=np.inf))
    if dmin < checks.min_spacing_pitch * pitch_px:
        return f"labels collapsed (two pins {dmin:.1f} px apart)"
    disp = lab - rest_px
    dev = np.full(n, np.nan)
    for i in np.flatnonzero(m):
        nb = nbr[i][m[nbr[i]]]
        if len(nb) >= 2:
            dev[i] = float(np.hypot(*(disp[i] - np.median(disp[nb], axis=0))))
    dv = dev[np.isfinite(dev)]
    n_bad = int((dv > checks.inconsistent_pitch * pitch_px).sum())
    if n_bad > checks.max_inconsistent:
        return f"{n_bad} pins inconsistent with their neighbours (> {checks.max_inconsistent})"
    rms = float(np.sqrt(np.mean(dv ** 2))) if dv.size else 0.0
    limit = checks.max_residual_px + checks.residual_per_disp * float(
        np.median(np.hypot(*disp[m].T)))
    if rms > limit:
        return f"neighbour residual {rms:.2f} px > {limit:.2f} px"
    return None


def read_clip(path: Path | str, limit: int | None = None) -> list[np.ndarray]:
    """Gray frames of a video file (ValueError naming the path if unreadable)."""
    frames = video_frames(path, limit, gray=True)
    if not frames:
        raise ValueError(f"no frames decoded from video: path={str(path)!r}")
    return frames


def _interp_weights(layout_px: np.ndarray, pitch_px: float) -> np.ndarray:
    L = np.asarray(layout_px, np.float64)
    d2 = ((L[:, None] - L[None]) ** 2).sum(-1)
    w = np.exp(-d2 / (2.0 * (1.2 * pitch_px) ** 2))
    np.fill_diagonal(w, 0.0)
    return w


def label_clip(frames: Sequence[np.ndarray], layout_px: np.ndarray, params: VisionParams,
               clip: str = "clip", dome: tuple | None = None,
               layout_dome: tuple | None = None,
               checks: LabelChecks = LabelChecks(), progress: bool = False) -> dict:
    """Label every frame of a real clip with the N layout pins, and check the labels.

    The layout (profile rest positions, placed by the clip's dome relative to
    ``layout_dome``) is fitted to the first frame's detections (similarity
    transform, one-to-one ICP), then tracked by the Pi's
    :class:`device.pi.vision.tracking.Tracker` (gate ``GATE_PITCH`` pitches),
    restarted from the rest layout when that explains more pins (the skin
    springs back). A tracked pin whose displacement disagrees with its layout
    neighbours' by more than the gate is counted as unmatched; unmatched pins
    (under glare, merged, lost) get the Gaussian-weighted displacement of
    matched pins nearby. Every frame is then checked with :func:`check_labels`.

    Returns ``labels_px`` (T, N, 2), ``matched`` (T, N) bool, ``ok`` (T,)
    bool, ``rejected`` (list of {clip, frame, reason}), ``dome``, ``box``,
    ``binaries`` (list of T thresholded crops), ``fit`` (rest fit summary).
    """
    if not len(frames):
        raise ValueError(f"frames must hold at least one frame, got 0 frames for clip={clip!r}")
    shape = frames[0].shape[:2]
    if dome is None:
        found = [d for d in (find_dome(f) for f in frames[:5]) if d is not None]
        if not found:
            T = len(frames)
            return {"labels_px": np.zeros((T, len(layout_px), 2)), "matched": np.zeros(
                (T, len(layout_px)), bool), "ok": np.zeros(T, bool),
                "rejected": [{"clip": clip, "frame": i, "reason": "no dome found in the clip"}
                             for i in range(T)], "dome": None, "box": None, "binaries": [],
                "fit": {}}
        dome = tuple(float(v) for v in np.median(np.asarray(found), axis=0))
    L0 = np.asarray(layout_px, np.float64)
    if layout_dome is not None:
        s = dome[2] / layout_dome[2]
        L0 = (L0 - layout_dome[:2]) * s + dome[:2]
    det = PinDetector(params, shape, dome)
    pitch = layout_pitch_px(L0)
    nbr, _ = layout_neighbours(L0, 6)
    W = _interp_weights(L0, pitch)
    T, N = len(frames), len(L0)
    labels = np.zeros((T, N, 2))
    matched = np.zeros((T, N), bool)
    ok_frames = np.zeros(T, bool)
    rejected: list[dict] = []
    binaries: list[np.ndarray] = []

    xy0, _ = det.detect(frames[0])
    fit = fit_layout(L0, xy0, GATE_PITCH * pitch)
    # the real rest layout: measured where a pin was found, the fitted layout elsewhere
    rest = fit["pins_px"].copy()
    m0 = fit["idx"] >= 0
    rest[m0] = xy0[fit["idx"][m0]]
    fit_summary = {"residual_px": round(fit["residual_px"], 3), "scale": round(fit["scale"], 4),
                   "rotation_deg": round(fit["rotation_deg"], 3),
                   "shift_px": [round(float(v), 3) for v in fit["shift_px"]],
                   "matched": int((fit["idx"] >= 0).sum())}
    bad_fit = None
    if not fit["residual_px"] <= checks.max_fit_residual_px:
        bad_fit = (f"layout fit to the rest frame failed (residual {fit['residual_px']:.2f} px "
                   f"> {checks.max_fit_residual_px} px)")
    gate_px = GATE_PITCH * pitch
    tracker = Tracker(pitch_px=pitch, gate_frac=GATE_PITCH, k=6)
    tracker.set_reference(rest)
    with progress_bar(T, f"label {clip}", progress) as bar:
        for t in range(T):
            xy, _ = det.detect(frames[t])
            binaries.append(det.binary.copy())
            vectors, lost = tracker.update(xy)
            if np.count_nonzero(mutual_match(rest, xy, gate_px) >= 0) > tracker.n_tracked:
                # the skin sprang back: the rest layout explains more pins
                tracker.set_reference(rest)
                vectors, lost = tracker.update(xy)
            m = ~lost
            # a pin that jumped to its neighbour's blob disagrees with its neighbours
            if m.sum() >= 3:
                local = np.median(vectors[nbr], axis=1)
                m &= np.hypot(*(vectors - local).T) <= gate_px
            new = rest + vectors
            # unmatched pins follow the matched pins around them
            if m.any():
                wm = W[:, m]
                ws = wm.sum(1)
                fill = (wm @ vectors[m]) / np.maximum(ws, 1e-12)[:, None]
                fill[ws < 1e-3] = np.median(vectors[m], axis=0)
                new[~m] = rest[~m] + fill[~m]
            idx = np.where(m, tracker.idx, -1)
            labels[t] = new
            matched[t] = m
            reason = bad_fit or check_labels(new, m, idx, rest, nbr, pitch, checks)
            if reason is None:
                ok_frames[t] = True
            else:
                rejected.append({"clip": clip, "frame": t, "reason": reason})
            bar.update(1)
    return {"labels_px": labels, "matched": matched, "ok": ok_frames, "rejected": rejected,
            "dome": dome, "box": det.box, "binaries": binaries, "fit": fit_summary}


def _real_clips(real_data, clips: Sequence[str]):
    """Yield ``(clip name, gray frames)`` from ``real_data`` (a folder of the roboskin
    clips named in ``clips``, or a mapping name -> frames), or with ``real_data``
    None from the clip files ``clips``.

    A folder's clips are checked up front and then read one at a time, so only
    one clip's frames are in memory at once.
    """
    if isinstance(real_data, Mapping):
        for k, v in real_data.items():
            yield str(k), [to_gray(f) for f in v]
        return
    if real_data is None:                # clips are paths to any sensor's recordings
        for p in clips:
            if not Path(p).is_file():
                raise ValueError(f"no such clip: {str(p)!r}")
        for p in clips:
            yield Path(p).stem, read_clip(p)
        return
    root = Path(real_data)
    if (root / "roboskin").is_dir():
        root = root / "roboskin"
    if not root.is_dir():
        raise ValueError(f"real_data must be a folder with the roboskin clips, got "
                         f"real_data={str(real_data)!r}")
    paths = []
    for name in clips:
        p = root / f"{name}.avi"
        if not p.is_file():
            raise ValueError(f"real_data lacks clip {name}.avi: real_data={str(real_data)!r}")
        paths.append((name, p))
    for name, p in paths:
        yield name, read_clip(p)


def real_samples(real_data, profile: str = "roboskin", params: VisionParams | None = None,
                 clips: Sequence[str] = REAL_CLIPS, holdout_frac: float = REAL_HOLDOUT_FRAC,
                 checks: LabelChecks = LabelChecks(), stride: int = 1,
                 progress: bool = False) -> dict:
    """Label real clips; split each into training frames and its held-out end.

    Returns ``train`` and ``test`` (lists of :class:`Sample`, accepted frames
    only; ``stride`` keeps every k-th training frame), ``rejected`` (all
    rejected frames: clip, frame, reason), ``labelled`` (accepted count per
    clip) and ``fits`` (rest fit per clip).
    """
    layout_px, layout_dome = sensor_geometry(profile)
    params = params or vision_params_for(profile)
    train, test, rejected, labelled, fits = [], [], [], {}, {}
    for name, frames in _real_clips(real_data, clips):
        lab = label_clip(frames, layout_px, params, clip=name, layout_dome=layout_dome,
                         checks=checks, progress=progress)
        rejected += lab["rejected"]
        labelled[name] = {"frames": len(frames), "accepted": int(lab["ok"].sum()),
                          "rejected": len(frames) - int(lab["ok"].sum())}
        fits[name] = lab["fit"]
        T = len(frames)
        split = int(round(T * (1.0 - holdout_frac)))
        for t in np.flatnonzero(lab["ok"]):
            d = float(np.median(np.hypot(*(lab["labels_px"][t] - lab["labels_px"][0]).T)))
            s = Sample(lab["binaries"][t], lab["box"], lab["dome"], lab["labels_px"][t],
                       lab["matched"][t], f"real:{name}", int(t), d)
            if t >= split:
                test.append(s)
            elif t % stride == 0:
                train.append(s)
    return {"train": train, "test": test, "rejected": rejected, "labelled": labelled,
            "fits": fits}
