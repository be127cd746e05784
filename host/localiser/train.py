"""Train the fixed-count pin localiser (stage 6 of the marker pipeline).

A Ridge regression (alpha 150 by default, as in the seed paper) from the
downscaled binary dome image to the positions of all N pins of a sensor
profile (133 for ``roboskin``). The Pi runs it through
:class:`device.pi.vision.localiser.Localiser`; this module makes the training data,
fits, checks and exports it as ONNX + JSON (``kind="localiser"``).

Training data
  * simulated frames with known true pins, from randomised scenes (depth,
    contact offset, drag direction and speed, surface) under randomised
    effects (glare, camera noise, exposure flicker, motion blur, pin loss,
    lens distortion), thresholded by the very PinDetector the Pi uses;
  * optionally real frames, labelled automatically (:func:`label_clip`): the
    profile's layout is fitted to a rest frame, then tracked frame to frame;
    every frame's labels are checked (pins matched, duplicates, collapsed
    labels, neighbour consistency) and frames that fail are rejected and
    listed with the reason.

Augmentation: every frame is cut several times around a perturbed dome
(shift and zoom), and its labels are normalised by the same perturbed dome, so
the image and the labels move together and an imperfect dome estimate does not
break the model.

Held-out checks: simulated scenes with unseen seeds (pressing deeper than the
training scenes), and the last 20 % of each real clip (never used for
training), each also per displacement bin.

Export: the Ridge is written as a plain ONNX MatMul + Add graph
(:func:`ridge_to_onnx`; float16 weights when float32 would pass 1 MB) through
:func:`host.learn.onnx_io.write_model`, with the localiser's manifest extras.

Limit: a linear map from the binary image cannot tell pins apart once they
have moved by more than about one pin pitch (~12 px on roboskin): there the
error grows to several px (see ``metrics.*.by_displacement``). The output is
still finite and plausible, and the fault flag stays clear.

Command line (the lead wires it into ``host``)::

    python -m host.localiser.train --out models/localiser-roboskin \
        --real-data ../shared/data [--json]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import cv2
import numpy as np

from device.pi.vision.localiser import (
    DEFAULT_CROP_FACTOR,
    KIND,
    effective_dome,
    localiser_input,
    to_normalised,
)
from device.pi.vision.matching import mutual_match
from device.pi.vision.extract import (
    ROBOSKIN_PARAMS,
    TACTIP_SHEAR_PARAMS,
    PinDetector,
    VisionParams,
    find_dome,
    to_gray,
)

__all__ = [
    "DEFAULT_SIZE",
    "DEFAULT_ALPHA",
    "REAL_CLIPS",
    "LabelChecks",
    "vision_params_for",
    "random_scene_doc",
    "sim_frames",
    "augment_rows",
    "fit_layout",
    "layout_neighbours",
    "check_labels",
    "label_clip",
    "real_samples",
    "Sample",
    "read_clip",
    "fit_ridge",
    "ridge_to_onnx",
    "pin_errors_px",
    "train_localiser",
    "main",
]

DEFAULT_SIZE = 32          # 32 x 32 inputs: 1024 x 266 weights, float16: 0.55 MB
DEFAULT_ALPHA = 150.0      # the seed paper's Ridge alpha
#: roboskin clips of the seed paper's sensor used for real labels (flatSkin is another skin)
REAL_CLIPS = ("smooth", "concrete", "north", "east")
#: share of each real clip (its end) held out for the real-data metrics
REAL_HOLDOUT_FRAC = 0.2
#: the Pi checks the input's foreground share per cell of this grid (see Localiser)
FILL_GRID = 4
#: simulated training scenes press at most this deep by default. Deeper presses
#: drag the pins by more than a pitch (> 12 px), where a linear map from the image
#: can hardly tell which pin is which; training on many of them costs accuracy
#: on the real clips (real held-out median 0.37 / 0.40 / 0.48 px for 2 / 2.5 / 3
#: mm), training on none loses the large-shear frames (median error there 7.3 /
#: 3.9 / 3.7 px). 2.5 mm is the compromise.
TRAIN_MAX_DEPTH_MM = 2.5
#: held-out simulated scenes press up to this deep
TEST_MAX_DEPTH_MM = 3.0

_PARAMS_BY_PROFILE = {"roboskin": ROBOSKIN_PARAMS, "tactip331": TACTIP_SHEAR_PARAMS}


def vision_params_for(profile: str) -> VisionParams:
    """The PinDetector parameters the Pi uses for a built-in profile."""
    try:
        return _PARAMS_BY_PROFILE[profile]
    except KeyError:
        raise ValueError(f"profile has no vision parameters: profile={profile!r} "
                         f"(known: {sorted(_PARAMS_BY_PROFILE)})") from None


def _progress(total: int, desc: str, enabled: bool):
    from tqdm import tqdm
    return tqdm(total=total, desc=desc, disable=not enabled or None, file=sys.stderr,
                leave=False)


# --------------------------------------------------------------------------
# Simulated frames
# --------------------------------------------------------------------------

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


@dataclass
class Sample:
    """One thresholded frame with its labels, before augmentation."""
    binary: np.ndarray        # thresholded dome crop (uint8)
    box: tuple                # its origin in the frame (x0, y0, x1, y1)
    dome: tuple               # (cx, cy, r) the detector used
    pins_px: np.ndarray       # (N, 2) labels in frame px
    measured: np.ndarray      # (N,) bool: label is a measurement (sim: all True)
    source: str               # "sim:<seed>" or "real:<clip>"
    frame: int
    disp_px: float = 0.0      # median pin displacement from rest, px


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
    from device.sim import Simulator, parse_scene

    if n_scenes < 0 or frames_per_scene < 1:
        raise ValueError(f"n_scenes must be >= 0 and frames_per_scene >= 1, got "
                         f"n_scenes={n_scenes!r}, frames_per_scene={frames_per_scene!r}")
    params = params or vision_params_for(profile)
    out: list[Sample] = []
    with _progress(n_scenes, "sim scenes", progress) as bar:
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


# --------------------------------------------------------------------------
# Augmentation and design matrix
# --------------------------------------------------------------------------


def augment_rows(samples: Sequence[Sample], size: int, crop_factor: float, n_aug: int,
                 shift_px: float, zoom: float, rng: np.random.Generator,
                 progress: bool = False, desc: str = "rows") -> tuple[np.ndarray, np.ndarray]:
    """Design matrix X (k, size*size) float32 and labels Y (k, 2N) float32.

    Each sample gives ``n_aug`` rows: the first around its own dome, the
    others around a perturbed dome (centre + N(0, shift_px) px, radius x
    (1 + N(0, zoom)), both clipped at 2.5 sigma). The crop and the
    normalisation of the labels use the same perturbed dome, so image and
    labels shift and zoom together.
    """
    if n_aug < 1:
        raise ValueError(f"n_aug must be >= 1, got n_aug={n_aug!r}")
    k = len(samples) * n_aug
    n_pins = len(samples[0].pins_px) if samples else 0
    X = np.empty((k, size * size), np.float32)
    Y = np.empty((k, 2 * n_pins), np.float32)
    scratch: dict = {}
    row = 0
    with _progress(len(samples), desc, progress) as bar:
        for s in samples:
            cx, cy, r = s.dome
            for a in range(n_aug):
                if a == 0:
                    d = (cx, cy, r)
                else:
                    dx, dy = np.clip(rng.normal(0.0, 1.0, 2), -2.5, 2.5) * shift_px
                    dz = float(np.clip(rng.normal(0.0, 1.0), -2.5, 2.5)) * zoom
                    d = (cx + dx, cy + dy, r * (1.0 + dz))
                localiser_input(s.binary, s.box, d, size, crop_factor, out=X[row], scratch=scratch)
                Y[row] = to_normalised(s.pins_px, d, crop_factor).reshape(-1)
                row += 1
            bar.update(1)
    return X, Y


def fit_ridge(X: np.ndarray, Y: np.ndarray, alpha: float = DEFAULT_ALPHA,
              sample_weight: np.ndarray | None = None):
    """scikit-learn Ridge (float64 solve) fitted on X -> Y."""
    from sklearn.linear_model import Ridge

    if isinstance(alpha, bool) or not isinstance(alpha, (int, float)) or not (
            math.isfinite(alpha) and alpha >= 0):
        raise ValueError(f"alpha must be a finite number >= 0, got alpha={alpha!r}")
    model = Ridge(alpha=float(alpha), fit_intercept=True, solver="cholesky")
    model.fit(X.astype(np.float64), Y.astype(np.float64), sample_weight=sample_weight)
    return model


#: above this many bytes of float32 weights, :func:`ridge_to_onnx` stores float16
MAX_FLOAT32_BYTES = 1_000_000


def ridge_to_onnx(model, n_features: int, weights: str = "auto", input_name: str = "x"):
    """A fitted linear model (``coef_`` (k, n), ``intercept_`` (k,)) as ONNX ``y = x W + b``.

    A plain MatMul + Add graph (opset 17): packed initializers take 4 bytes a
    weight where skl2onnx's LinearRegressor takes 5, and it runs on any
    onnxruntime. ``weights``: "float32", "float16" (stored half precision and
    cast once when the session is built; 0.001 px worst case on roboskin), or
    "auto" (float16 when float32 would exceed 1 MB). Output name ``y``.
    """
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    W = np.asarray(model.coef_, np.float64).reshape(-1, n_features).T   # (n, k)
    b = np.asarray(model.intercept_, np.float64).reshape(-1)
    if weights == "auto":
        weights = "float16" if W.size * 4 > MAX_FLOAT32_BYTES else "float32"
    if weights not in ("float32", "float16"):
        raise ValueError(f"weights must be 'auto', 'float32' or 'float16', got weights={weights!r}")
    k = W.shape[1]
    nodes, inits = [], [numpy_helper.from_array(b.astype(np.float32), "b")]
    if weights == "float16":
        inits.append(numpy_helper.from_array(W.astype(np.float16), "W16"))
        nodes.append(helper.make_node("Cast", ["W16"], ["W"], to=TensorProto.FLOAT))
    else:
        inits.append(numpy_helper.from_array(W.astype(np.float32), "W"))
    nodes += [helper.make_node("MatMul", [input_name, "W"], ["xw"]),
              helper.make_node("Add", ["xw", "b"], ["y"])]
    graph = helper.make_graph(
        nodes, "localiser",
        [helper.make_tensor_value_info(input_name, TensorProto.FLOAT, [None, n_features])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [None, k])], inits)
    onx = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)],
                            producer_name="tacfoot.host.localiser")
    onx.ir_version = 8
    onnx.checker.check_model(onx)
    return onx


def pin_errors_px(pred_norm: np.ndarray, true_norm: np.ndarray, r_px: np.ndarray,
                  mask: np.ndarray | None = None) -> np.ndarray:
    """Per-pin Euclidean error in px (flattened over the rows and selected pins)."""
    if len(pred_norm) == 0:
        return np.zeros(0)
    p = pred_norm.reshape(len(pred_norm), -1, 2)
    t = true_norm.reshape(len(true_norm), -1, 2)
    e = np.hypot(*(p - t).transpose(2, 0, 1)) * np.asarray(r_px, np.float64)[:, None]
    return e[mask] if mask is not None else e.reshape(-1)


def _err_stats(e: np.ndarray) -> dict:
    if e.size == 0:
        return {"n_pins": 0, "median_px": 0.0, "p90_px": 0.0, "mean_px": 0.0}
    return {"n_pins": int(e.size), "median_px": round(float(np.median(e)), 3),
            "p90_px": round(float(np.percentile(e, 90)), 3), "mean_px": round(float(e.mean()), 3)}


# --------------------------------------------------------------------------
# Automatic labels for real frames
# --------------------------------------------------------------------------


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


def layout_neighbours(layout_px: np.ndarray, k: int = 6) -> np.ndarray:
    """Indices (N, k) of each pin's k nearest other pins in the layout."""
    L = np.asarray(layout_px, np.float64)
    k = int(min(k, len(L) - 1))
    d2 = ((L[:, None] - L[None]) ** 2).sum(-1)
    np.fill_diagonal(d2, np.inf)
    return np.argsort(d2, axis=1)[:, :k]


def _pitch_px(layout_px: np.ndarray) -> float:
    L = np.asarray(layout_px, np.float64)
    d2 = ((L[:, None] - L[None]) ** 2).sum(-1)
    np.fill_diagonal(d2, np.inf)
    return float(np.median(np.sqrt(d2.min(1))))


@dataclass(frozen=True)
class LabelChecks:
    """Thresholds of the per-frame label check (see :func:`check_labels`).

    min_matched_frac: share of the N pins that must be matched to a detection.
    max_inconsistent: most matched pins whose displacement may differ from
        the median of their layout neighbours' by more than
        ``inconsistent_pitch`` pitches.
    max_residual_px, residual_per_disp: the RMS (over matched pins) of that
        difference may be at most ``max_residual_px + residual_per_disp * D``,
        D the median displacement of the pins from rest (px): real strain makes
        neighbours differ more the more the skin is deformed (measured on the
        roboskin clips: RMS 0.4 px at rest, about 0.25 D under drag).
    min_spacing_pitch: two labels closer than this many pitches are a collapse.
    max_fit_residual_px: the rest-frame layout fit must be at least this good.
    """
    min_matched_frac: float = 0.75
    max_inconsistent: int = 4
    inconsistent_pitch: float = 0.35
    max_residual_px: float = 1.0
    residual_per_disp: float = 0.35
    min_spacing_pitch: float = 0.4
    max_fit_residual_px: float = 1.5


def check_labels(labels_px: np.ndarray, matched: np.ndarray, idx: np.ndarray,
                 rest_px: np.ndarray, nbr: np.ndarray, pitch_px: float,
                 checks: LabelChecks = LabelChecks()) -> str | None:
    """Why one frame's labels are not to be trusted, or None when they pass.

    ``labels_px`` (N, 2) labelled pins; ``matched`` (N,) which are measured
    (a detection assigned); ``idx`` (N,) the assigned detection or -1;
    ``rest_px`` (N, 2) the rest layout; ``nbr`` (N, k) layout neighbours.
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
    d2 = ((lab[:, None] - lab[None]) ** 2).sum(-1)
    np.fill_diagonal(d2, np.inf)
    dmin = float(np.sqrt(d2.min()))
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
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise ValueError(f"cannot open video: path={str(path)!r}")
    frames = []
    try:
        while limit is None or len(frames) < limit:
            ok, f = cap.read()
            if not ok:
                break
            frames.append(to_gray(f))
    finally:
        cap.release()
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
    transform, one-to-one ICP), then tracked: each frame the pins are
    predicted (last position + last motion), the field's common shift is
    estimated on a loose gate and the pins are matched mutual-nearest on a
    tight one (or against the rest layout when that explains more pins, as
    the skin springs back). A matched pin whose displacement disagrees with
    its layout neighbours' is dropped; unmatched pins (under glare, merged,
    lost) get the Gaussian-weighted displacement of matched pins nearby.
    Every frame is then checked with :func:`check_labels`.

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
    pitch = _pitch_px(L0)
    nbr = layout_neighbours(L0, 6)
    W = _interp_weights(L0, pitch)
    gate_loose, gate_tight = 0.5 * pitch, 0.4 * pitch
    T, N = len(frames), len(L0)
    labels = np.zeros((T, N, 2))
    matched = np.zeros((T, N), bool)
    ok_frames = np.zeros(T, bool)
    rejected: list[dict] = []
    binaries: list[np.ndarray] = []

    xy0, _ = det.detect(frames[0])
    fit = fit_layout(L0, xy0, gate_tight)
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
    cur = rest.copy()
    vel = np.zeros(2)
    with _progress(T, f"label {clip}", progress) as bar:
        for t in range(T):
            xy, _ = det.detect(frames[t])
            binaries.append(det.binary.copy())
            xy = xy.astype(np.float64)
            pred = cur + vel
            idx = mutual_match(pred, xy, gate_loose)
            m = idx >= 0
            shift = np.median(xy[idx[m]] - pred[m], axis=0) if m.sum() >= 10 else np.zeros(2)
            pred = pred + shift
            idx = mutual_match(pred, xy, gate_tight)
            idx_rest = mutual_match(rest, xy, gate_tight)
            if (idx_rest >= 0).sum() > (idx >= 0).sum():
                pred, idx = rest.copy(), idx_rest
            m = idx >= 0
            new = pred.copy()
            new[m] = xy[idx[m]]
            # a pin that jumped to its neighbour's blob disagrees with its neighbours
            if m.sum() >= 3:
                disp = new - rest
                local = np.median(disp[nbr], axis=1)
                jumped = m & (np.hypot(*(disp - local).T) > gate_tight)
                m &= ~jumped
                idx[jumped] = -1
            # unmatched pins follow the matched pins around them
            disp = new - rest
            if m.any():
                wm = W[:, m]
                ws = wm.sum(1)
                fill = (wm @ disp[m]) / np.maximum(ws, 1e-12)[:, None]
                far = ws < 1e-3
                fill[far] = np.median(disp[m], axis=0)
                new[~m] = rest[~m] + fill[~m]
            vel = np.median(new[m] - cur[m], axis=0) if m.sum() >= 10 else np.zeros(2)
            cur = new
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
    """Yield ``(clip name, gray frames)`` from ``real_data`` (a folder or a mapping).

    A folder's clips are checked up front and then read one at a time, so only
    one clip's frames are in memory at once.
    """
    if isinstance(real_data, Mapping):
        for k, v in real_data.items():
            yield str(k), [to_gray(f) for f in v]
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
    from device.profile import load_profile

    prof = load_profile(profile)
    params = params or vision_params_for(profile)
    train, test, rejected, labelled, fits = [], [], [], {}, {}
    layout_dome = (*prof.dome_centre_px, prof.dome_radius_px)
    for name, frames in _real_clips(real_data, clips):
        lab = label_clip(frames, prof.pins_px, params, clip=name, layout_dome=layout_dome,
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


# --------------------------------------------------------------------------
# Evaluation
# --------------------------------------------------------------------------


#: displacement bins (median pin displacement from rest, px) of the held-out metrics
DISP_BINS_PX = (0.0, 6.0, 12.0, math.inf)


def _evaluate(model, samples: Sequence[Sample], size: int, crop_factor: float,
              measured_only: bool) -> dict:
    """Pin error stats, plus the same per displacement bin (``by_displacement``)."""
    if not samples:
        return _err_stats(np.zeros(0))
    X, Y = augment_rows(samples, size, crop_factor, 1, 0.0, 0.0, np.random.default_rng(0))
    pred = model.predict(X)
    r = np.array([effective_dome(s.dome, crop_factor)[2] for s in samples])
    mask = np.stack([s.measured for s in samples]) if measured_only else \
        np.ones((len(samples), len(samples[0].pins_px)), bool)
    out = _err_stats(pin_errors_px(pred, Y, r, mask))
    disp = np.array([s.disp_px for s in samples])
    bins = {}
    for lo, hi in zip(DISP_BINS_PX[:-1], DISP_BINS_PX[1:]):
        sel = (disp >= lo) & (disp < hi)
        name = f"{lo:g}-{hi:g}px" if math.isfinite(hi) else f">={lo:g}px"
        bins[name] = {"frames": int(sel.sum()),
                      **_err_stats(pin_errors_px(pred[sel], Y[sel], r[sel], mask[sel]))}
    out["by_displacement"] = bins
    return out


def _evaluate_perturbed(model, samples, size, crop_factor, shift_px, zoom, seed) -> dict:
    if not samples:
        return _err_stats(np.zeros(0))
    rng = np.random.default_rng(seed)
    X, Y = augment_rows(samples, size, crop_factor, 2, shift_px, zoom, rng)
    X, Y = X[1::2], Y[1::2]
    pred = model.predict(X)
    # the error in px is measured in the (perturbed) crop's own scale; close enough
    r = np.array([effective_dome(s.dome, crop_factor)[2] for s in samples])
    mask = np.stack([s.measured for s in samples])
    return _err_stats(pin_errors_px(pred, Y, r, mask))


# --------------------------------------------------------------------------
# Training
# --------------------------------------------------------------------------


def _check_args(size, alpha, crop_factor, n_aug) -> None:
    if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or not 8 <= size <= 128:
        raise ValueError(f"size must be an integer in [8, 128], got size={size!r}")
    if isinstance(alpha, bool) or not isinstance(alpha, (int, float)) or not (
            math.isfinite(alpha) and alpha >= 0):
        raise ValueError(f"alpha must be a finite number >= 0, got alpha={alpha!r}")
    if isinstance(crop_factor, bool) or not isinstance(crop_factor, (int, float)) or not (
            0.3 <= crop_factor <= 2.0):
        raise ValueError(f"crop_factor must be in [0.3, 2.0], got crop_factor={crop_factor!r}")
    if isinstance(n_aug, bool) or not isinstance(n_aug, int) or n_aug < 1:
        raise ValueError(f"n_aug must be an integer >= 1, got n_aug={n_aug!r}")


def train_localiser(
    out_dir: Path | str,
    profile: str = "roboskin",
    real_data=None,
    seed: int = 0,
    alpha: float = DEFAULT_ALPHA,
    size: int = DEFAULT_SIZE,
    progress: bool = True,
    crop_factor: float = DEFAULT_CROP_FACTOR,
    n_sim_scenes: int = 120,
    frames_per_scene: int = 30,
    n_test_scenes: int = 20,
    n_aug: int = 3,
    shift_px: float = 2.0,
    zoom: float = 0.02,
    real_clips: Sequence[str] = REAL_CLIPS,
    real_stride: int = 1,
    real_weight: float = 2.0,
    max_depth_mm: float = TRAIN_MAX_DEPTH_MM,
    weights: str = "auto",
    checks: LabelChecks = LabelChecks(),
) -> dict:
    """Train, check and export a localiser; returns the summary (and the estimator).

    ``real_data``: None (simulated frames only), a folder holding the
    roboskin clips (``<dir>/roboskin/<clip>.avi`` or ``<dir>/<clip>.avi``),
    or a mapping clip name -> list of frames. Training scenes use seeds
    ``seed .. seed + n_sim_scenes - 1``; held-out scenes the seeds from
    ``seed + 100000`` on; the last 20 % of each real clip is held out.
    Real rows weigh ``real_weight`` times a simulated row in the fit (the
    simulator's pins are an ideal layout; the real ones are the target).
    Simulated training scenes press at most ``max_depth_mm`` deep, held-out
    ones up to 3 mm; the held-out metrics are also given per displacement bin.

    The result dict holds ``out_dir``, ``size_bytes``, ``train_s`` (and
    ``stage_s`` per stage), ``training`` (counts, the rejected real frames
    with clip, frame and reason), ``metrics`` (held-out pin errors, px) and
    ``estimator`` (the fitted scikit-learn Ridge; it is not written
    anywhere: the artefact is model.onnx + manifest.json).
    """
    from device.profile import load_profile
    from host.learn.onnx_io import write_model

    _check_args(size, alpha, crop_factor, n_aug)
    params = vision_params_for(profile)
    if real_data is not None and not isinstance(real_data, Mapping) and not (
            Path(real_data).is_dir()):
        raise ValueError(f"real_data must be a folder with the roboskin clips or a mapping "
                         f"clip -> frames, got real_data={str(real_data)!r}")
    if isinstance(real_weight, bool) or not isinstance(real_weight, (int, float)) or not (
            math.isfinite(real_weight) and real_weight > 0):
        raise ValueError(f"real_weight must be a finite number > 0, "
                         f"got real_weight={real_weight!r}")
    t0 = time.perf_counter()
    stage_s: dict = {}
    prof = load_profile(profile)
    n_pins = prof.n_pins
    rng = np.random.default_rng(seed)

    sim_train = sim_frames(n_sim_scenes, frames_per_scene, seed, profile, params, progress,
                           max_depth_mm)
    # held out: unseen seeds, and deeper presses than in training (up to 3 mm)
    sim_test = sim_frames(n_test_scenes, max(4, frames_per_scene // 2), seed + 100000, profile,
                          params, progress, TEST_MAX_DEPTH_MM)
    stage_s["simulate"] = round(time.perf_counter() - t0, 1)
    t1 = time.perf_counter()
    real = {"train": [], "test": [], "rejected": [], "labelled": {}, "fits": {}}
    if real_data is not None:
        real = real_samples(real_data, profile, params, real_clips, REAL_HOLDOUT_FRAC, checks,
                            real_stride, progress)
    stage_s["label_real"] = round(time.perf_counter() - t1, 1)
    train = sim_train + real["train"]
    if not train:
        raise ValueError("no training frames: n_sim_scenes=0 and no accepted real frames")
    t1 = time.perf_counter()
    X, Y = augment_rows(train, size, crop_factor, n_aug, shift_px, zoom, rng, progress,
                        "augment")
    w = np.ones(len(X))
    w[len(sim_train) * n_aug:] = real_weight
    model = fit_ridge(X, Y, alpha, sample_weight=w)
    fit_pred = model.predict(X)
    stage_s["fit"] = round(time.perf_counter() - t1, 1)

    # the fallback layout and the plausibility limits the Pi checks at run time
    mean_layout = np.average(Y.astype(np.float64), axis=0, weights=w)
    dev = max(float(np.abs(fit_pred - mean_layout).max()), float(np.abs(Y - mean_layout).max()))
    max_dev_norm = 2.0 * dev
    fill = X.mean(1)
    fill_range = [0.5 * float(fill.min()), min(1.0, 1.5 * float(fill.max()))]
    grid = FILL_GRID if size % FILL_GRID == 0 else 0
    cells_range = [[0.0], [1.0]]
    if grid:
        c = X.reshape(len(X), grid, size // grid, grid, size // grid).mean(axis=(2, 4))
        c = c.reshape(len(X), -1).astype(np.float64)
        cells_range = [np.round(0.5 * c.min(0), 6).tolist(),
                       np.round(np.minimum(1.0, 1.5 * c.max(0) + 0.02), 6).tolist()]

    t1 = time.perf_counter()
    r_train = np.array([effective_dome(s.dome, crop_factor)[2] for s in train])
    metrics = {
        "sim_heldout": _evaluate(model, sim_test, size, crop_factor, False),
        "sim_heldout_perturbed_dome": _evaluate_perturbed(model, sim_test, size, crop_factor,
                                                          shift_px, zoom, seed + 7),
        "train_fit": _err_stats(pin_errors_px(fit_pred[::n_aug], Y[::n_aug], r_train)),
    }
    if real_data is not None:
        metrics["real_heldout_measured"] = _evaluate(model, real["test"], size, crop_factor, True)
        metrics["real_heldout_all_labels"] = _evaluate(model, real["test"], size, crop_factor,
                                                       False)
        metrics["real_heldout_perturbed_dome"] = _evaluate_perturbed(
            model, real["test"], size, crop_factor, shift_px, zoom, seed + 11)

    onx = ridge_to_onnx(model, size * size, weights)
    onnx_diff = _onnx_vs_sklearn(onx, model, X[:: max(1, len(X) // 256)])
    weights_dtype = "float16" if any(i.name == "W16" for i in onx.graph.initializer) else "float32"
    metrics["onnx_vs_sklearn_max_abs_norm"] = onnx_diff
    stage_s["evaluate_export"] = round(time.perf_counter() - t1, 1)
    training = {
        "sim_frames": len(sim_train), "sim_scenes": n_sim_scenes,
        "sim_max_depth_mm": max_depth_mm, "sim_test_max_depth_mm": TEST_MAX_DEPTH_MM,
        "sim_seeds": [seed, seed + n_sim_scenes - 1],
        "sim_test_frames": len(sim_test),
        "sim_test_seeds": [seed + 100000, seed + 100000 + n_test_scenes - 1],
        "real_frames": len(real["train"]), "real_test_frames": len(real["test"]),
        "real_weight": float(real_weight),
        "real_labelled": real["labelled"], "real_layout_fit": real["fits"],
        "real_holdout": f"last {REAL_HOLDOUT_FRAC:.0%} of each clip",
        "label_checks": {k: getattr(checks, k) for k in checks.__dataclass_fields__},
        "rows": int(len(X)),
        "augment": {"copies": n_aug, "shift_px_sigma": shift_px, "zoom_sigma": zoom},
        "rejected": real["rejected"],
    }
    train_s = round(time.perf_counter() - t0, 1)
    extra = {
        "profile": profile, "n_pins": n_pins, "size": size, "crop_factor": crop_factor,
        "output": "y (1, 2N): u0, v0, u1, v1, ... with u = (x - cx) / r, v = (y - cy) / r "
                  "for the effective dome of the crop",
        "weights_dtype": weights_dtype,
        "mean_layout_norm": np.round(mean_layout.reshape(-1, 2), 6).tolist(),
        "fill_range": [round(v, 6) for v in fill_range], "fill_grid": grid,
        "fill_cells_range": cells_range, "max_dev_norm": round(max_dev_norm, 6),
        "alpha": float(alpha), "vision_params": {k: getattr(params, k) for k in (
            "block", "offset", "blur_sigma_px", "min_area_px", "max_area_px", "roi_shrink")},
        "seed": seed, "train_s": train_s, "training": training, "metrics": metrics,
    }
    out = write_model(onx, out_dir, KIND, size * size, extra=extra)
    size_bytes = (Path(out) / "model.onnx").stat().st_size
    return {"out_dir": str(out), "size_bytes": int(size_bytes), "weights_dtype": weights_dtype,
            "train_s": train_s, "stage_s": stage_s, "n_pins": n_pins, "size": size,
            "crop_factor": crop_factor, "alpha": float(alpha), "training": training,
            "metrics": metrics, "estimator": model}


def _onnx_vs_sklearn(onx, model, X: np.ndarray) -> float:
    """Largest |ONNX - scikit-learn| output on rows X (normalised units)."""
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    so.log_severity_level = 3
    sess = ort.InferenceSession(onx.SerializeToString(), so, providers=["CPUExecutionProvider"])
    got = sess.run(None, {sess.get_inputs()[0].name: X.astype(np.float32)})[0]
    return float(np.abs(got - model.predict(X)).max())


# --------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m host.localiser.train",
                                 description="train the fixed-count pin localiser (ONNX + JSON)")
    ap.add_argument("--out", required=True, type=Path, help="model folder to write")
    ap.add_argument("--profile", default="roboskin")
    ap.add_argument("--real-data", type=Path, default=None,
                    help="folder with the real roboskin clips (e.g. ../shared/data)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--alpha", type=float, default=DEFAULT_ALPHA)
    ap.add_argument("--size", type=int, default=DEFAULT_SIZE)
    ap.add_argument("--sim-scenes", type=int, default=120)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--quiet", action="store_true", help="no progress bars")
    args = ap.parse_args(argv)
    try:
        res = train_localiser(args.out, profile=args.profile, real_data=args.real_data,
                              seed=args.seed, alpha=args.alpha, size=args.size,
                              n_sim_scenes=args.sim_scenes, progress=not args.quiet)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    res.pop("estimator", None)
    if args.json:
        print(json.dumps(res, default=lambda o: o.item() if isinstance(o, np.generic) else str(o)))
    else:
        m = res["metrics"]
        print(f"wrote {res['out_dir']} ({res['size_bytes'] / 1e6:.2f} MB) in {res['train_s']} s")
        for k, v in m.items():
            if not isinstance(v, dict):
                print(f"  {k:<30} {v:.3g}")
                continue
            print(f"  {k:<30} median {v['median_px']:.2f} px  p90 {v['p90_px']:.2f} px  "
                  f"({v['n_pins']} pins)")
        rej = res["training"]["rejected"]
        print(f"  real frames: {res['training']['real_frames']} train, "
              f"{res['training']['real_test_frames']} held out, {len(rej)} rejected")
    return 0


if __name__ == "__main__":
    sys.exit(main())
