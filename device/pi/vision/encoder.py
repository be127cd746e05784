"""The one frame encoder: a camera frame -> what the models read.

The leg runtime and the host's dataset loader both turn frames into model inputs
through :class:`FrameEncoder`, so training and the Pi cannot drift apart. One
encoder owns the three steps that must agree:

* the marker pipeline (:class:`~device.pi.vision.pipeline.MarkerStream`): per-pin
  vectors against the reference frame, the contact grid, faults;
* the layout mapper (:class:`~device.pi.vision.layout.LayoutMapper`): those vectors
  on the profile's fixed M-pin layout, in the fixed order every model reads;
* the binary dome crop (:func:`~device.pi.vision.layout.binary_crop`): the CNN's
  input frame, ``crop_px`` square (none when ``crop_px`` is ``None``).

The layout arrays it returns are preallocated and reused frame to frame; copy them
to keep them past the next :meth:`FrameEncoder.encode`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from device.pi.vision.layout import LayoutMapper, binary_crop, layout_for_profile
from device.pi.vision.pipeline import FrameFeatures, MarkerStream

__all__ = ["EncodedFrame", "FrameEncoder"]


@dataclass
class EncodedFrame:
    """One frame, encoded. ``vectors`` (M, 2) float32 px and ``lost`` (M,) bool are
    on the fixed layout; ``crop`` is (crop_px, crop_px) uint8 or None."""

    features: FrameFeatures
    vectors: np.ndarray
    lost: np.ndarray
    crop: np.ndarray | None

    @property
    def grid(self) -> np.ndarray:
        return self.features.grid


class FrameEncoder:
    """Frames in, fixed-layout model inputs out (see the module docstring).

    ``profile`` is a built-in sensor profile name or a TOML path; ``layout_px`` is
    the fixed pin layout (default: the profile's own); ``localiser`` is an optional
    fixed-count localiser handed to the marker stream; ``reacquire`` where the
    tracker's coarse search runs (:class:`device.pi.vision.tracking.Tracker`).
    """

    def __init__(self, profile: str = "roboskin", *, crop_px: int | None = 32,
                 layout_px: np.ndarray | None = None, localiser=None, reacquire: str = "inline"):
        self.stream = MarkerStream(profile, localiser=localiser, reacquire=reacquire)
        layout = layout_for_profile(profile) if layout_px is None else layout_px
        self.mapper = LayoutMapper(layout, self.stream.profile.match_gate_px)
        if crop_px is not None and int(crop_px) < 1:
            raise ValueError(f"crop_px must be >= 1 or None, got crop_px={crop_px!r}")
        self.crop_px = None if crop_px is None else int(crop_px)
        self._vectors = np.zeros((self.n_pins, 2), np.float32)
        self._lost = np.ones(self.n_pins, bool)

    @property
    def n_pins(self) -> int:
        """M, the number of pins on the fixed layout."""
        return self.mapper.n_pins

    @property
    def profile(self):
        """The marker pipeline's profile (``grid_n``, ``match_gate_px``, ...)."""
        return self.stream.profile

    def encode(self, image: np.ndarray, t_s: float | None = None, steps: int = 1) -> EncodedFrame:
        """Run the marker pipeline on one frame and map it onto the layout
        (``steps``: frames since the last one encoded, see ``MarkerStream.process``)."""
        ff = self.stream.process(image, t_s, steps)
        v, lost = self.mapper(self.stream, ff, self._vectors, self._lost)
        crop = binary_crop(self.stream, self.crop_px) if self.crop_px else None
        return EncodedFrame(features=ff, vectors=v, lost=lost, crop=crop)

    def rezero(self) -> None:
        """Take the next frame as the new reference (no contact)."""
        self.stream.rezero()
