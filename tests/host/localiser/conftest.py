"""The localiser trained once for all tests in this folder.

One small model (simulated scenes, plus the first 300 frames of the real
north.avi and east.avi when the recordings are there, plus a copy of north.avi's
start with two deliberately corrupted frames).
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from device.pi.vision.extract import find_dome
from device.pi.models.localiser import Localiser
from host.localiser.labels import read_clip
from host.localiser.train import train_localiser
from tests.realdata import real_data_dir

#: the corrupted copy of north.avi's start: clip name, the frame with half the
#: dome painted over (pins missing), the frame rotated by 15 degrees (every ring
#: moves to wrong identities)
CORRUPT = {"clip": "north-corrupted", "half": 30, "rot": 40}


def _real_dir_or_none():
    try:
        return real_data_dir("roboskin/north.avi", "roboskin/east.avi")
    except pytest.skip.Exception:
        return None


def _corrupt(frames: list[np.ndarray], dome) -> list[np.ndarray]:
    out = [f.copy() for f in frames]
    cx, cy, r = dome
    # half the dome painted with the dome's own background grey: about 60 pins gone
    f = out[CORRUPT["half"]]
    bg = int(np.median(f[int(cy) - 5:int(cy) + 5, int(cx) - 120:int(cx) - 100]))
    cv2.rectangle(f, (int(cx) - int(r), int(cy) - int(r)), (int(cx), int(cy) + int(r)), bg, -1)
    # the whole image rotated about the dome centre: pins land between layout sites
    m = cv2.getRotationMatrix2D((cx, cy), 15.0, 1.0)
    rot = CORRUPT["rot"]
    out[rot] = cv2.warpAffine(out[rot], m, out[rot].shape[::-1], borderMode=cv2.BORDER_REPLICATE)
    return out


@pytest.fixture(scope="session")
def trained(tmp_path_factory):
    real_dir = _real_dir_or_none()
    real = None
    if real_dir is not None:
        rb = real_dir / "roboskin"
        north = read_clip(rb / "north.avi", limit=300)
        east = read_clip(rb / "east.avi", limit=300)
        dome = find_dome(north[0])
        real = {"north": north[::2], "east": east[::2],
                CORRUPT["clip"]: _corrupt(north[:60], dome)}
    out = tmp_path_factory.mktemp("localiser")
    res = train_localiser(out, real_data=real, n_sim_scenes=80, frames_per_scene=20,
                          n_test_scenes=6, progress=False)
    return {"res": res, "dir": out, "loc": Localiser.load(out), "real": real is not None,
            "corrupt": CORRUPT}

