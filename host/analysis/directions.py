"""Average-vector directions two ways: the tracked marker vectors and the
regression localiser's pins (the paper's figure 5 compares the two).

Both series come from ``host analyse --localiser`` JSON lines. The vector
method's average vector is the line's ``shear_x``, ``shear_y``. The localiser's
is the mean displacement of its pins (``localised_px``) from their positions in
the rest frame: the first frame that has a reference and a sound localisation.
Directions are in image axes (x right, y down), degrees in [0, 360).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from device.errors import InputError

#: below this average-vector length (px) a direction is noise: flagged ``weak``
MIN_DIRECTION_PX = 0.5


def read_lines(path: Path | str) -> list[dict]:
    """The frame lines of a ``host analyse`` JSON-lines file (the summary dropped)."""
    path = Path(path)
    lines = []
    with open(path) as fh:
        for n, text in enumerate(fh, 1):
            if not text.strip():
                continue
            try:
                d = json.loads(text)
            except json.JSONDecodeError:
                raise InputError(f"{path}:{n}: not a JSON line") from None
            if not isinstance(d, dict):
                raise InputError(f"{path}:{n}: expected a JSON object, got {text[:40]!r}")
            if not d.get("summary"):
                lines.append(d)
    return lines


def _sound(line: dict) -> bool:
    faults = line.get("faults") or []
    return (line.get("localised_px") is not None and "localiser" not in faults
            and "reference_not_set" not in faults and "no_dome" not in faults)


def direction_deg(xy: np.ndarray) -> np.ndarray:
    """Direction of each (x, y) vector in degrees [0, 360), image axes; 0 for a zero vector."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    return np.degrees(np.arctan2(xy[:, 1], xy[:, 0])) % 360.0


def angle_diff_deg(a_deg: np.ndarray, b_deg: np.ndarray) -> np.ndarray:
    """Signed smallest difference a - b in degrees, in [-180, 180)."""
    return (np.asarray(a_deg, np.float64) - np.asarray(b_deg, np.float64) + 180.0) % 360.0 - 180.0


def direction_series(lines: list[dict]) -> dict:
    """Per contact frame with a sound localisation: ``frame`` (n,), ``vectors_px``
    (n, 2) the tracked average vector, ``localised_px`` (n, 2) the mean pin
    displacement from the rest frame, and ``rest_frame``.

    Raises ValueError naming what is missing when no line has ``localised_px``
    (``host analyse`` was run without ``--localiser``) or no rest frame exists.
    """
    if not any("localised_px" in d for d in lines):
        raise InputError("no line has localised_px: run host analyse with --localiser")
    rest = next((d for d in lines if _sound(d)), None)
    if rest is None:
        raise InputError("no rest frame: no line has a reference and a sound localisation")
    rest_px = np.asarray(rest["localised_px"], np.float64)
    frames, vec, loc = [], [], []
    for d in lines:
        if not d.get("contact") or not _sound(d):
            continue
        pins = np.asarray(d["localised_px"], np.float64)
        if pins.shape != rest_px.shape:
            raise InputError(f"frame {d.get('frame')}: localised_px has shape {pins.shape}, "
                             f"the rest frame {rest_px.shape}")
        frames.append(int(d.get("frame", len(frames))))
        vec.append((float(d["shear_x"]), float(d["shear_y"])))
        loc.append((pins - rest_px).mean(axis=0))
    return {"frame": np.asarray(frames, int),
            "vectors_px": np.nan_to_num(np.asarray(vec, np.float64).reshape(-1, 2)),
            "localised_px": np.nan_to_num(np.asarray(loc, np.float64).reshape(-1, 2)),
            "rest_frame": int(rest.get("frame", 0))}


def compare_directions(series: dict, min_px: float = MIN_DIRECTION_PX) -> dict:
    """How well the two direction series agree.

    ``vectors_deg`` and ``localised_deg``: direction of each series' mean vector;
    ``median_abs_diff_deg``: median |angle difference| over the frames where both
    vectors are at least ``min_px`` long (``compared`` of ``frames``);
    ``within_30deg``: the share of those within 30 degrees; ``weak`` is True
    (and the figures 0) when no frame qualifies.
    """
    v, loc = series["vectors_px"], series["localised_px"]
    strong = ((np.hypot(v[:, 0], v[:, 1]) >= min_px)
              & (np.hypot(loc[:, 0], loc[:, 1]) >= min_px))
    diff = np.abs(angle_diff_deg(direction_deg(v[strong]), direction_deg(loc[strong])))
    mean_v = v.mean(axis=0) if len(v) else np.zeros(2)
    mean_l = loc.mean(axis=0) if len(loc) else np.zeros(2)
    weak = not bool(strong.any())
    return {"frames": int(len(v)), "compared": int(strong.sum()),
            "vectors_deg": round(float(direction_deg(mean_v)[0]), 2),
            "localised_deg": round(float(direction_deg(mean_l)[0]), 2),
            "median_abs_diff_deg": 0.0 if weak else round(float(np.median(diff)), 2),
            "within_30deg": 0.0 if weak else round(float(np.mean(diff <= 30.0)), 4),
            "weak": weak}
