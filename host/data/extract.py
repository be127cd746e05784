"""Per-frame features of one recording: frames -> the Pi's own frame encoder
(:class:`device.pi.vision.encoder.FrameEncoder`) -> :class:`ClipFeatures` on the
profile's fixed pin layout."""
from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from typing import Iterable

import numpy as np

from device.pi.vision.encoder import FrameEncoder
from device.pi.vision.layout import LayoutError, LayoutMapper
from device.pi.vision.layout import layout_for_profile as _layout_for_profile
from device.pi.faults import FAULT_NO_REFERENCE
from host.data.errors import DataError
from host.extras import need


def layout_for_profile(profile: str) -> np.ndarray:
    """The fixed pin layout (M, 2) px of a sensor profile (:mod:`device.pi.vision.layout`)."""
    try:
        return _layout_for_profile(profile)
    except LayoutError as exc:
        raise DataError(str(exc)) from None


# ----------------------------------------------------------------------------
# Per-frame features of one recording
# ----------------------------------------------------------------------------

#: the per-frame session statistics of :attr:`ClipFeatures.session`: the image's mean
#: gray level, its standard deviation (both over every 4th pixel and row) and the
#: time since the previous frame in seconds (the first frame: the next interval; 0
#: with no frame times)
SESSION_STATS = ("brightness", "contrast", "interval_s")


def frame_stats(image: np.ndarray) -> tuple[float, float]:
    """(mean, standard deviation) of an image's values, over every 4th pixel and row."""
    a = np.asarray(image)[::4, ::4].astype(np.float32)
    return float(a.mean()), float(a.std())


def frame_intervals(t_s: list) -> np.ndarray:
    """(F,) seconds between frames from their times (None: unknown -> 0); the first
    frame takes the second's interval."""
    t = np.array([np.nan if x is None else float(x) for x in t_s], np.float64)
    dt = np.diff(t)
    dt = np.concatenate([dt[:1], dt]) if len(dt) else np.zeros(len(t))
    return np.nan_to_num(dt, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32)

@dataclass
class ClipFeatures:
    """Per-frame features of one recording, frame 0 .. n_frames-1."""

    vectors: np.ndarray           # (F, M, 2) float32 on the fixed layout
    lost: np.ndarray              # (F, M) bool
    grids: np.ndarray             # (F, g, g) float32
    frames: np.ndarray | None     # (F, S, S) uint8
    contact: np.ndarray           # (F,) bool, the pipeline's contact flag
    ready: np.ndarray             # (F,) bool, a reference frame was set
    faults: np.ndarray            # (F,) int32 fault bits
    fps: float | None
    seconds: float = 0.0          # time spent extracting
    imu: np.ndarray | None = None  # (F, 6) from the simulator's truth, sim:// only
    #: (F, 3) float32 per-frame statistics that carry a recording session, not the
    #: surface: :data:`SESSION_STATS` (the recording-identity check reads them)
    session: np.ndarray | None = None

    @property
    def n_frames(self) -> int:
        return int(self.vectors.shape[0])


def extract_features(frames: Iterable, profile: str = "roboskin", frame_size: int | None = 32,
                     n_frames: int | None = None, progress: bool = True, desc: str = "",
                     fps: float | None = None, mapper: LayoutMapper | None = None
                     ) -> ClipFeatures:
    """Run the Pi's :class:`MarkerStream` over ``frames`` (images, or objects with
    ``.image`` and ``.t_s`` such as camera ``Frame``) and collect per-frame features
    on the profile's fixed pin layout."""
    tqdm = need("tqdm").tqdm

    enc = FrameEncoder(profile, crop_px=frame_size or None,
                       layout_px=None if mapper is None else mapper.layout_px)
    stream = enc.stream
    vecs, losts, grids, crops, contact, ready, faults = [], [], [], [], [], [], []
    stats, times = [], []
    t0 = time.perf_counter()
    with tqdm(total=n_frames, desc=desc or "features", unit="frame", file=sys.stderr,
              disable=(not progress) or None, leave=False) as bar:   # None: off if no tty
        for fr in frames:
            image = getattr(fr, "image", fr)
            t_s = getattr(fr, "t_s", None)
            ef = enc.encode(image, t_s)
            stats.append(frame_stats(image))
            times.append(t_s if t_s is not None else (len(times) / fps if fps else None))
            ff = ef.features
            vecs.append(ef.vectors.copy())
            losts.append(ef.lost.copy())
            grids.append(np.asarray(ff.grid, np.float32))
            if ef.crop is not None:
                crops.append(ef.crop)
            contact.append(bool(ff.contact))
            ready.append(not (ff.faults & FAULT_NO_REFERENCE) and stream.reference is not None)
            faults.append(int(ff.faults))
            bar.update(1)
    seconds = time.perf_counter() - t0
    M, g = enc.n_pins, stream.profile.grid_n
    F = len(vecs)

    def stack(lst, shape, dtype):
        return np.stack(lst).astype(dtype, copy=False) if lst else np.zeros((0, *shape), dtype)

    return ClipFeatures(
        vectors=stack(vecs, (M, 2), np.float32), lost=stack(losts, (M,), bool),
        grids=stack(grids, (g, g), np.float32),
        frames=stack(crops, (frame_size, frame_size), np.uint8) if frame_size else None,
        contact=np.array(contact, bool).reshape(F), ready=np.array(ready, bool).reshape(F),
        faults=np.array(faults, np.int32).reshape(F), fps=fps, seconds=seconds,
        session=np.column_stack([np.array(stats, np.float32).reshape(F, 2),
                                 frame_intervals(times)]).astype(np.float32))
