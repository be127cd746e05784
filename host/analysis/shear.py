"""Pin tracking and shear / depth / tilt regression on the real ``tactip_shear`` set.

The set (see ``../shared/data/README.md``) is 400 binarised 445x440 images of a
331-pin TacTip pressed onto a flat surface at random depth, tilt and shear;
each image is an independent press. This module measures two things:

* **pins**: the reference layout is taken from ``image_1.png`` (the shallowest
  press); every image is tracked against it with
  :func:`device.pi.vision.tracking.track_with_neighbours` (deep presses move pins by
  more than their spacing). Per image: the share of layout pins found and
  assigned one to one.
* **regression**: Ridge regressions from the tracked displacements plus the
  lost-pin flags to ``pose_z``, ``shear_x``, ``shear_y``, ``pose_Rx`` and
  ``pose_Ry`` under shuffled 5-fold cross-validation (``KFold(shuffle=True,
  random_state=0)``); the alpha is chosen inside each training fold
  (``RidgeCV``, i.e. nested). Reported as the ratio of the MAE of predicting
  the training mean to the model's MAE (higher is better).

Features (:func:`shear_features`), per image, all from the tracked vectors
``d`` (m, 2) (lost pins carry their neighbour-predicted vector) and the lost
flags: ``d``; ``|d|``; ``d / (s + 1 px)`` and ``|d| / (s + 1 px)`` where
``s`` is the mean ``|d|`` of the image (the pattern of the deformation,
independent of how deep the press is: shear is then visible in shallow presses
too, which a linear model on raw vectors cannot scale); the lost flags.
:func:`evaluate_tactip_shear` also reports the ratios for the raw features
(``d`` and the lost flags only). The derived features and the tracker's
settings were chosen while looking at these same 400 images (there is no
separate hold-out set), so the ratios are somewhat optimistic.

>>> res = evaluate_tactip_shear("../shared/data")        # doctest: +SKIP
>>> res["ratios"]["shear_x"]["ratio"]                      # doctest: +SKIP
"""

from __future__ import annotations

import csv
import math
import time
from pathlib import Path

import cv2
import numpy as np

from device.pi.vision.neighbours import layout_neighbours, layout_pitch_px, track_with_neighbours
from device.pi.vision.extract import TACTIP_SHEAR_PARAMS, extract_pins, find_dome

TARGETS = ("pose_z", "shear_x", "shear_y", "pose_Rx", "pose_Ry")
REFERENCE_IMAGE = "image_1.png"
ALPHAS = tuple(float(a) for a in np.logspace(-1, 5, 13))
#: A reference blob is a layout pin when its area is within these factors of
#: the median area and its centre at least a quarter pitch inside the dome.
_AREA_FACTORS = (0.5, 2.0)
_RIM_MARGIN_PITCH = 0.25


# --------------------------------------------------------------------------
# Data
# --------------------------------------------------------------------------


def shear_dir(data_dir) -> Path:
    """The ``tactip_shear`` folder: ``data_dir`` itself or its ``tactip_shear`` child."""
    p = Path(data_dir)
    if (p / "targets_images.csv").is_file():
        return p
    if (p / "tactip_shear" / "targets_images.csv").is_file():
        return p / "tactip_shear"
    raise ValueError(f"data_dir must hold tactip_shear/targets_images.csv, got data_dir={str(data_dir)!r}")


def load_targets(data_dir) -> tuple[list[str], dict[str, np.ndarray]]:
    """Image file names (CSV order) and every numeric target column."""
    d = shear_dir(data_dir)
    with open(d / "targets_images.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        raise ValueError(f"targets_images.csv is empty in {d}")
    names = [r["sensor_image"] for r in rows]
    targets = {}
    for key in rows[0]:
        if key == "sensor_image":
            continue
        targets[key] = np.array([float(r[key]) for r in rows])
    return names, targets


def read_binary(path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise ValueError(f"cannot read image {str(path)!r}")
    return img


def detect_pins(binary: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pin centroids (n, 2) x, y px and areas of an already binarised image."""
    b = (binary > 127).astype(np.uint8) * 255
    p = TACTIP_SHEAR_PARAMS
    return extract_pins(b, p.min_area_px, p.max_area_px)


def reference_layout(binary: np.ndarray) -> np.ndarray:
    """The layout pins of a reference image (float64 (m, 2)).

    All blobs of pin size, minus the fragments along the edge of the circular
    mask: a layout pin has a typical area (0.5 to 2 x the median) and lies at
    least a quarter pitch inside the dome found by
    :func:`device.pi.vision.extract.find_dome`.
    """
    xy, area = detect_pins(binary)
    if xy.shape[0] < 3:
        raise ValueError(f"reference image has too few pins ({xy.shape[0]})")
    med = float(np.median(area))
    keep = (area >= _AREA_FACTORS[0] * med) & (area <= _AREA_FACTORS[1] * med)
    dome = find_dome(binary)
    if dome is not None:
        cx, cy, r = dome
        pitch = layout_pitch_px(xy[keep])
        keep &= np.hypot(xy[:, 0] - cx, xy[:, 1] - cy) <= r - _RIM_MARGIN_PITCH * pitch
    return xy[keep].astype(np.float64)


# --------------------------------------------------------------------------
# Tracking
# --------------------------------------------------------------------------


def track_tactip_shear(data_dir, **track_kw) -> dict:
    """Track every image against the reference layout of ``image_1.png``.

    Returns ``names``, ``targets``, ``reference`` (m, 2), ``pitch_px``,
    ``disp_px`` (N, m, 2) float32, ``lost`` (N, m) bool, ``assigned_frac``
    (N,) and ``track_s`` (seconds spent tracking).
    """
    d = shear_dir(data_dir)
    names, targets = load_targets(d)
    if REFERENCE_IMAGE not in names:
        raise ValueError(f"{REFERENCE_IMAGE} is not listed in {d / 'targets_images.csv'}")
    ref = reference_layout(read_binary(d / "images" / REFERENCE_IMAGE))
    pitch = layout_pitch_px(ref)
    nb = layout_neighbours(ref)
    m = ref.shape[0]
    disp = np.zeros((len(names), m, 2), np.float32)
    lost = np.zeros((len(names), m), bool)
    t_track = 0.0
    for i, name in enumerate(names):
        cur, _ = detect_pins(read_binary(d / "images" / name))
        t0 = time.perf_counter()
        idx, dsp = track_with_neighbours(ref, cur, pitch, neighbours=nb, **track_kw)
        t_track += time.perf_counter() - t0
        disp[i] = dsp
        lost[i] = idx < 0
    return {
        "names": names,
        "targets": targets,
        "reference": ref,
        "pitch_px": pitch,
        "disp_px": disp,
        "lost": lost,
        "assigned_frac": 1.0 - lost.mean(axis=1),
        "track_s": t_track,
    }


# --------------------------------------------------------------------------
# Regression
# --------------------------------------------------------------------------


def shear_features(disp_px: np.ndarray, lost: np.ndarray, scale_floor_px: float = 1.0) -> np.ndarray:
    """Regression features per image (N, 7 m): d, |d|, d/(s+c), |d|/(s+c), lost.

    ``s`` is the image's mean |d| and ``c = scale_floor_px``.
    """
    d = np.nan_to_num(np.asarray(disp_px, np.float64))
    if d.ndim != 3 or d.shape[2] != 2:
        raise ValueError(f"disp_px must be (N, m, 2), got disp_px.shape={d.shape!r}")
    n = d.shape[0]
    mag = np.hypot(d[..., 0], d[..., 1])
    s = mag.mean(axis=1, keepdims=True) + float(scale_floor_px)
    flat = d.reshape(n, -1)
    return np.hstack([flat, mag, flat / s, mag / s, np.asarray(lost, np.float64).reshape(n, -1)])


def raw_features(disp_px: np.ndarray, lost: np.ndarray) -> np.ndarray:
    """The plain features: all vectors, then the lost flags (N, 3 m)."""
    d = np.nan_to_num(np.asarray(disp_px, np.float64))
    n = d.shape[0]
    return np.hstack([d.reshape(n, -1), np.asarray(lost, np.float64).reshape(n, -1)])


def cv_ratios(X: np.ndarray, Y: np.ndarray, n_splits: int = 5, seed: int = 0,
              alphas=ALPHAS) -> list[dict]:
    """Shuffled K-fold MAE of StandardScaler + RidgeCV (alpha chosen per target
    inside each training fold, by efficient leave-one-out) against the MAE of
    predicting the training-fold mean, for every column of ``Y`` (n, t).

    Returns one dict per target: ``mae``, ``mae_predict_mean``, ``ratio``
    (the second over the first; higher is better) and the chosen ``alphas``.
    """
    from sklearn.linear_model import RidgeCV
    from sklearn.model_selection import KFold
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    X = np.asarray(X, np.float64)
    Y = np.asarray(Y, np.float64)
    if Y.ndim == 1:
        Y = Y[:, None]
    if X.ndim != 2 or X.shape[0] != Y.shape[0]:
        raise ValueError(f"X must be (n, features) with one row per target row, got X.shape={X.shape!r}, "
                         f"Y.shape={Y.shape!r}")
    if not (np.isfinite(X).all() and np.isfinite(Y).all()):
        raise ValueError("X and Y must be finite")
    pred = np.zeros_like(Y)
    base = np.zeros_like(Y)
    chosen = []
    for tr, te in KFold(n_splits=n_splits, shuffle=True, random_state=seed).split(X):
        model = make_pipeline(StandardScaler(), RidgeCV(alphas=alphas, alpha_per_target=True))
        model.fit(X[tr], Y[tr])
        pred[te] = model.predict(X[te]).reshape(len(te), -1)
        base[te] = Y[tr].mean(axis=0)
        chosen.append(np.atleast_1d(model[-1].alpha_).astype(float))
    out = []
    for j in range(Y.shape[1]):
        mae = float(np.abs(pred[:, j] - Y[:, j]).mean())
        mae_mean = float(np.abs(base[:, j] - Y[:, j]).mean())
        out.append({"mae": mae, "mae_predict_mean": mae_mean,
                    "ratio": mae_mean / mae if mae > 0 else math.inf,
                    "alphas": [float(a[j]) for a in chosen]})
    return out


def cv_ratio(X: np.ndarray, y: np.ndarray, n_splits: int = 5, seed: int = 0, alphas=ALPHAS) -> dict:
    """:func:`cv_ratios` for one target."""
    return cv_ratios(X, np.asarray(y, np.float64)[:, None], n_splits, seed, alphas)[0]


def evaluate_tactip_shear(data_dir, targets=TARGETS, tracked: dict | None = None) -> dict:
    """Pin-assignment statistics and cross-validated regression ratios.

    ``data_dir`` is the real-data folder (holding ``tactip_shear/``) or the
    ``tactip_shear`` folder. Pass ``tracked`` (the output of
    :func:`track_tactip_shear`) to skip the tracking. Returns a JSON-ready
    dict: ``n_images``, ``n_reference_pins``, ``pitch_px``,
    ``assigned_frac`` (per image), ``assigned_frac_p5``,
    ``frac_images_95`` (share of images with at least 95% of the layout
    assigned), ``track_ms_per_image``, ``ratios`` (per target: ``mae``,
    ``mae_predict_mean``, ``ratio``, chosen ``alphas``) and
    ``ratios_raw_features`` (the same with vectors + lost flags only).
    """
    tr = tracked if tracked is not None else track_tactip_shear(data_dir)
    frac = np.asarray(tr["assigned_frac"], np.float64)
    X = shear_features(tr["disp_px"], tr["lost"])
    X_raw = raw_features(tr["disp_px"], tr["lost"])
    for key in targets:
        if key not in tr["targets"]:
            raise ValueError(f"targets must be columns of targets_images.csv, got {key!r}")
    Y = np.stack([tr["targets"][key] for key in targets], axis=1)
    ratios = dict(zip(targets, cv_ratios(X, Y)))
    ratios_raw = dict(zip(targets, cv_ratios(X_raw, Y)))
    n = len(tr["names"])
    return {
        "n_images": n,
        "n_reference_pins": int(tr["reference"].shape[0]),
        "pitch_px": float(tr["pitch_px"]),
        "assigned_frac": [round(float(f), 4) for f in frac],
        "assigned_frac_p5": float(np.percentile(frac, 5)),
        "frac_images_95": float(np.mean(frac >= 0.95)),
        "track_ms_per_image": 1e3 * float(tr["track_s"]) / max(n, 1),
        "ratios": ratios,
        "ratios_raw_features": ratios_raw,
    }
