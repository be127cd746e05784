"""Training samples of the pin localiser: thresholded frames with their labels,
and the augmented design matrix built from them.

A :class:`Sample` is one thresholded dome crop with the positions of all N pins
(simulated truth or automatic real labels). :func:`augment_rows` cuts every
sample several times around a perturbed dome (shift and zoom) and normalises
its labels by the same perturbed dome, so the image and the labels move
together and an imperfect dome estimate does not break the model.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from device.config import ConfigError
from device.pi.vision.extract import ROBOSKIN_PARAMS, TACTIP_SHEAR_PARAMS, VisionParams
from device.profile import has_sim_geometry, load_layout, load_pipeline_profile, load_profile
from device.pi.models.localiser import localiser_input, to_normalised
from host.extras import need

__all__ = ["Sample", "vision_params_for", "sensor_geometry", "progress_bar", "augment_rows"]

_PARAMS_BY_PROFILE = {"roboskin": ROBOSKIN_PARAMS, "tactip331": TACTIP_SHEAR_PARAMS}


def vision_params_for(profile: str) -> VisionParams:
    """The PinDetector parameters the Pi uses for a built-in profile, or the
    ``[vision]`` section of a profile TOML (such as one from ``host calibrate``)."""
    if str(profile).endswith(".toml"):
        try:
            return load_pipeline_profile(profile).vision
        except ConfigError as exc:
            raise ValueError(str(exc)) from None
    try:
        return _PARAMS_BY_PROFILE[profile]
    except KeyError:
        raise ValueError(f"profile has no vision parameters: profile={profile!r} "
                         f"(known: {sorted(_PARAMS_BY_PROFILE)}, or a .toml path)") from None


def sensor_geometry(profile: str) -> tuple[np.ndarray, tuple | None]:
    """(rest pin layout (N, 2) px, dome (cx, cy, r) px or None) of a built-in profile
    or a profile TOML: the simulator's geometry when the profile has it, else the
    ``[layout]`` and ``[vision] dome_px`` that ``host calibrate`` writes."""
    try:
        layout = load_layout(profile)
        if str(profile).endswith(".toml") and not has_sim_geometry(profile):
            dome = load_pipeline_profile(profile).dome_px
        else:
            prof = load_profile(profile)
            dome = (*prof.dome_centre_px, prof.dome_radius_px)
    except ConfigError as exc:
        raise ValueError(str(exc)) from None
    return np.asarray(layout, np.float64), dome


def progress_bar(total: int, desc: str, enabled: bool):
    """A tqdm bar on stderr (disabled when ``enabled`` is false)."""
    tqdm = need("tqdm").tqdm
    return tqdm(total=total, desc=desc, disable=not enabled or None, file=sys.stderr,
                leave=False)


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
    with progress_bar(len(samples), desc, progress) as bar:
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
