"""Where the real TacTip recordings are, for tests that need them.

The recordings are never part of the repository. They are found at the path in
the environment variable ``TACFOOT_REAL_DATA`` or else at ``../shared/data``
from the repository root. When neither holds what a test needs, the test is
skipped with a reason that says where it looked.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

ENV_VAR = "TACFOOT_REAL_DATA"
from tests import REPO_ROOT
DEFAULT_DIR = REPO_ROOT.parent / "shared" / "data"


def real_data_dir(*required: str) -> Path:
    """The real-data folder, or ``pytest.skip`` when it (or a required entry) is absent.

    ``required`` are paths relative to the folder (e.g. ``"roboskin/smooth.avi"``)
    that the calling test needs.
    """
    tried = []
    env = os.environ.get(ENV_VAR)
    candidates = ([Path(env).expanduser()] if env else []) + [DEFAULT_DIR]
    for cand in candidates:
        tried.append(str(cand))
        if cand.is_dir() and all((cand / r).exists() for r in required):
            return cand
    need = f" with {', '.join(required)}" if required else ""
    pytest.skip(
        f"real TacTip recordings not found{need}: looked in {', '.join(tried)} "
        f"(set {ENV_VAR} to the folder holding roboskin/ and tactip_shear/)"
    )


def read_video(path: Path, start: int = 0, count: int | None = None) -> list[np.ndarray]:
    """BGR frames ``start`` .. ``start+count`` of a video file (skips if unreadable)."""
    import cv2

    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        pytest.skip(f"OpenCV cannot open {path} (no video backend for this codec?)")
    frames = []
    i = 0
    try:
        while count is None or len(frames) < count:
            ok, frame = cap.read()
            if not ok:
                break
            if i >= start:
                frames.append(frame)
            i += 1
    finally:
        cap.release()
    if not frames:
        pytest.skip(f"no frames decoded from {path}")
    return frames
