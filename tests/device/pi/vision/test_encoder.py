"""The one frame encoder (device/pi/vision/encoder.py): buffers reused, crops only when
asked. That the dataset loader sees the same numbers is tested in
tests/host/data/test_extract.py."""
from __future__ import annotations

import pytest

from device.pi.vision.encoder import FrameEncoder


def test_encoder_reuses_its_buffers_and_crops_only_when_asked(drag_frames):
    enc = FrameEncoder("roboskin", crop_px=None)
    a = enc.encode(drag_frames[0])
    b = enc.encode(drag_frames[1])
    assert a.vectors is b.vectors and a.crop is None and b.crop is None


@pytest.mark.parametrize("bad", [0, -3])
def test_encoder_refuses_a_crop_size_below_one(bad):
    with pytest.raises(ValueError, match="crop_px"):
        FrameEncoder("roboskin", crop_px=bad)
