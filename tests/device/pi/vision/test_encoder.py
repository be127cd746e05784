"""The one frame encoder: the dataset loader and the leg runtime see the same numbers."""
from __future__ import annotations

import numpy as np
import pytest

from device.pi.vision.encoder import FrameEncoder
from device.sim import Simulator, load_scene
from host.data.extract import extract_features


@pytest.fixture(scope="module")
def drag_frames():
    sim = Simulator(load_scene("drag-0"), seed=3)
    return [sim.render(i) for i in range(0, min(sim.n_frames, 40))]


def test_loader_features_equal_the_encoders(drag_frames):
    enc = FrameEncoder("roboskin", crop_px=16)
    vecs, losts, crops = [], [], []
    for im in drag_frames:
        ef = enc.encode(im)
        vecs.append(ef.vectors.copy())
        losts.append(ef.lost.copy())
        crops.append(ef.crop)
    clip = extract_features(drag_frames, "roboskin", frame_size=16, progress=False)
    np.testing.assert_array_equal(clip.vectors, np.stack(vecs))
    np.testing.assert_array_equal(clip.lost, np.stack(losts))
    np.testing.assert_array_equal(clip.frames, np.stack(crops))
    assert clip.vectors.shape == (len(drag_frames), enc.n_pins, 2)
    # the drag moves the pins: the encoding is not all zeros once in contact
    assert np.abs(clip.vectors[-1]).max() > 0.5


def test_encoder_reuses_its_buffers_and_crops_only_when_asked(drag_frames):
    enc = FrameEncoder("roboskin", crop_px=None)
    a = enc.encode(drag_frames[0])
    b = enc.encode(drag_frames[1])
    assert a.vectors is b.vectors and a.crop is None and b.crop is None


@pytest.mark.parametrize("bad", [0, -3])
def test_encoder_refuses_a_crop_size_below_one(bad):
    with pytest.raises(ValueError, match="crop_px"):
        FrameEncoder("roboskin", crop_px=bad)
