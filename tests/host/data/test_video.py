"""host/data/video.py: a whole video file into memory."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from host.data.video import video_frames


@pytest.fixture
def clip(tmp_path):
    path = tmp_path / "c.avi"
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (64, 48))
    for k in range(7):
        vw.write(np.full((48, 64, 3), 30 * k, np.uint8))
    vw.release()
    return path


def test_video_frames_reads_every_frame_or_the_first_few(clip):
    frames = video_frames(clip)
    assert len(frames) == 7 and frames[0].shape == (48, 64, 3)
    assert [round(f.mean() / 30) for f in frames] == list(range(7))   # in order (MJPG is lossy)
    assert len(video_frames(clip, limit=3)) == 3
    gray = video_frames(clip, limit=2, gray=True)
    assert gray[1].shape == (48, 64) and gray[1].dtype == np.uint8


def test_a_file_that_is_not_a_video_names_its_path(tmp_path):
    bad = tmp_path / "nope.avi"
    bad.write_bytes(b"not a video")
    with pytest.raises(ValueError, match="nope.avi"):
        video_frames(bad)
