"""Reading a whole video file into memory, for the host's offline work (the Pi
reads frames one at a time through :mod:`device.pi.sources.camera`)."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def video_frames(path, limit: int | None = None, gray: bool = False) -> list[np.ndarray]:
    """The frames of a video file, the first ``limit`` of them when given, as
    decoded (BGR) or, with ``gray``, as 2-D uint8. A file OpenCV cannot open is a
    ValueError naming the path."""
    import cv2

    from device.pi.vision.extract import to_gray

    cap = cv2.VideoCapture(str(Path(path)))
    if not cap.isOpened():
        raise ValueError(f"cannot open video: path={str(path)!r}")
    frames: list[np.ndarray] = []
    try:
        while limit is None or len(frames) < limit:
            ok, img = cap.read()
            if not ok:
                break
            frames.append(to_gray(img) if gray else img)
    finally:
        cap.release()
    return frames
