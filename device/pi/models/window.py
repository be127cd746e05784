"""Windows of T frames and the model inputs built from them.

The Pi runs these encoders on its rolling window; the host runs the same
functions on windows cut from recordings, so a model sees exactly the same
numbers in training and on the robot. The encoding has a version
(:data:`device.pi.models.artefact.FEATURE_SPEC_VERSION`): change an encoder, bump it.

Input layouts (the ``input_layout`` a model manifest names):

* ``vectors``   - (T, M, 2) pin vectors quantised to ``VECTOR_STEP_PX``, flattened
                  frame by frame, then (T, 6) IMU rows if the model uses IMU:
                  (1, T*M*2 [+ T*6]) float32.
* ``grids``     - (T, g, g) contact-grid maps, then their frame-to-frame
                  differences (the fine shake that tells Lego from smooth):
                  (1, 2*T*g*g) float32.
* ``frames``    - (T, S, S) binary dome crops scaled to 0..1:
                  (1, T, S, S) float32 (channels = frames), for the CNN.
"""
from __future__ import annotations

import numpy as np

from device.pi.numerics import finite

#: pin vectors are quantised to this step before they reach a model (the
#: paper's quantised vectors); it also removes sub-pixel noise
VECTOR_STEP_PX = 0.25
#: no vector component beyond this reaches a model
VECTOR_CLIP_PX = 64.0
IMU_CLIP = np.array([16.0, 16.0, 16.0, 2000.0, 2000.0, 2000.0], np.float32)

LAYOUTS = ("vectors", "grids", "frames")
#: no value of any encoding is larger in size than this (the IMU's gyro clip)
ENCODED_BOUND = float(max(VECTOR_CLIP_PX, IMU_CLIP.max(), 2.0))


def _clean(a, clip) -> np.ndarray:
    """``a`` finite (NaN/inf -> 0) and clipped to +-clip, as float32. Wider input is
    clipped in float64 *before* the cast: 1e39 gives the clip, never float32's inf."""
    x = np.asarray(a)
    if x.dtype == np.float32:
        return np.clip(finite(x), -clip, clip)
    return np.clip(finite(x, dtype=np.float64), -clip, clip).astype(np.float32)


def _fit(new, buf: np.ndarray, clip) -> np.ndarray:
    """One pushed part in the dtype of its window buffer, never wrapped or overflowed:
    NaN/inf -> 0 and values clipped to +-``clip`` (0..255 for a uint8 frame) before
    the cast."""
    a = np.asarray(new)
    if buf.dtype != np.uint8:
        return _clean(a, clip)
    if a.dtype == np.uint8:
        return a
    return np.clip(finite(a, dtype=np.float64), 0, 255).astype(np.uint8)


def quantise_vectors(vectors) -> np.ndarray:
    """Pin vectors as a model sees them: finite, clipped to VECTOR_CLIP_PX and
    rounded to VECTOR_STEP_PX (float32, same shape)."""
    return np.round(_clean(vectors, VECTOR_CLIP_PX) / VECTOR_STEP_PX) * VECTOR_STEP_PX


def encode_vectors(vectors: np.ndarray, imu: np.ndarray | None = None) -> np.ndarray:
    """(N, T, M, 2) or (T, M, 2) vectors [+ (N, T, 6) or (T, 6) IMU] -> (N, D) float32."""
    v = quantise_vectors(vectors)
    if v.ndim == 3:
        v = v[None]
    x = v.reshape(v.shape[0], -1)
    if imu is not None:
        m = _clean(imu, IMU_CLIP)
        if m.ndim == 2:
            m = m[None]
        x = np.concatenate([x, m.reshape(m.shape[0], -1)], axis=1)
    return np.ascontiguousarray(x, dtype=np.float32)


def encode_grids(grids: np.ndarray) -> np.ndarray:
    """(N, T, g, g) or (T, g, g) grids -> (N, 2*T*g*g): the maps and their changes."""
    g = _clean(grids, 1.0)
    if g.ndim == 3:
        g = g[None]
    d = np.zeros_like(g)
    d[:, 1:] = g[:, 1:] - g[:, :-1]
    x = np.concatenate([g.reshape(g.shape[0], -1), d.reshape(d.shape[0], -1)], axis=1)
    return np.ascontiguousarray(x, dtype=np.float32)


def encode_frames(frames: np.ndarray) -> np.ndarray:
    """(N, T, S, S) or (T, S, S) uint8 crops -> (N, T, S, S) float32 in 0..1 (other
    dtypes: NaN/inf -> 0, values clipped to 0..255 first)."""
    f = np.asarray(frames)
    if f.ndim == 3:
        f = f[None]
    if f.dtype != np.uint8:      # NaN/inf -> 0 and beyond 0..255 saturated, as a camera would
        f = np.clip(finite(f, dtype=np.float64), 0, 255)
    return np.ascontiguousarray(f, dtype=np.float32) * np.float32(1.0 / 255.0)


def encode(layout: str, **parts) -> np.ndarray:
    if layout == "vectors":
        return encode_vectors(parts["vectors"], parts.get("imu"))
    if layout == "grids":
        return encode_grids(parts["grids"])
    if layout == "frames":
        return encode_frames(parts["frames"])
    raise ValueError(f"input_layout must be one of {LAYOUTS}, got {layout!r}")


class RollingWindow:
    """The last T frames of per-frame features, preallocated; the Pi pushes one
    frame at a time and encodes the window when it is full.

    The buffers are written by :meth:`push` only: it also keeps each frame's vectors
    quantised and its IMU row clipped as it arrives, so the ``vectors`` encoding is
    those rows put together, the same numbers as :func:`encode_vectors` on the
    whole window without redoing T frames each time."""

    def __init__(self, T: int, n_pins: int, grid_n: int = 8, frame_size: int = 32):
        if not isinstance(T, (int, np.integer)) or T < 1:
            raise ValueError(f"window T must be a whole number >= 1, got {T!r}")
        self.T = int(T)
        self.vectors = np.zeros((self.T, n_pins, 2), np.float32)
        self.imu = np.zeros((self.T, 6), np.float32)
        self.grids = np.zeros((self.T, grid_n, grid_n), np.float32)
        self.frames = np.zeros((self.T, frame_size, frame_size), np.uint8)
        self._qvectors = np.zeros((self.T, n_pins * 2), np.float32)
        self._qimu = np.zeros((self.T, 6), np.float32)
        self.count = 0
        # encodings of the current contents, by (layout, with_imu): several models
        # with the same window read one encoding per frame; push/clear drop them
        self._encoded: dict = {}

    @property
    def full(self) -> bool:
        return self.count >= self.T

    def clear(self) -> None:
        self.count = 0
        self._encoded.clear()

    def push(self, vectors=None, imu=None, grid=None, frame=None) -> None:
        for buf, new, clip in ((self.vectors, vectors, VECTOR_CLIP_PX), (self.imu, imu, IMU_CLIP),
                               (self.grids, grid, 1.0), (self.frames, frame, 255)):
            buf[:-1] = buf[1:]
            if new is None:
                buf[-1] = 0
            else:
                buf[-1] = _fit(new, buf, clip).reshape(buf.shape[1:])
        for buf in (self._qvectors, self._qimu):
            buf[:-1] = buf[1:]
        # the new frame as encode_vectors would give it
        self._qvectors[-1] = quantise_vectors(self.vectors[-1]).reshape(-1)
        self._qimu[-1] = _clean(self.imu[-1], IMU_CLIP)
        self.count += 1
        self._encoded.clear()

    def encode(self, layout: str, with_imu: bool = False, last: int | None = None) -> np.ndarray:
        """The model input for the current T frames, or the newest ``last`` of them
        (read-only; computed once per push for each layout)."""
        n = self.T if last is None else int(last)
        if not 1 <= n <= self.T:
            raise ValueError(f"last must be 1..{self.T} frames, got {last!r}")
        key = (layout, bool(with_imu), n)
        x = self._encoded.get(key)
        if x is None:
            if layout == "vectors":
                x = self._qvectors[-n:].reshape(1, -1)
                x = np.concatenate([x, self._qimu[-n:].reshape(1, -1)], axis=1) if with_imu \
                    else x.copy()
            else:
                x = encode(layout, vectors=self.vectors[-n:],
                           imu=self.imu[-n:] if with_imu else None,
                           grids=self.grids[-n:], frames=self.frames[-n:])
            x.flags.writeable = False
            self._encoded[key] = x
        return x


def _tail_of(name: str) -> property:
    """A read-only view of the newest T rows of the window's ``name`` buffer."""
    return property(lambda self: getattr(self.window, name)[-self.T:],
                    doc=f"The newest T rows of the window's {name}.")


class WindowTail:
    """The newest T frames of a longer :class:`RollingWindow`, read in place: models
    of several T read one window that is pushed once per frame. Full once the
    window has had T pushes since it was cleared; pushed through the window only."""

    def __init__(self, window: RollingWindow, T: int):
        if isinstance(T, bool) or not isinstance(T, (int, np.integer)) or not 1 <= T <= window.T:
            raise ValueError(f"a tail's T must be a whole number 1..{window.T}, got {T!r}")
        self.window = window
        self.T = int(T)

    @property
    def count(self) -> int:
        return self.window.count

    @property
    def full(self) -> bool:
        return self.window.count >= self.T

    def clear(self) -> None:
        self.window.clear()

    def push(self, **parts) -> None:
        raise TypeError("a WindowTail is read only: push its RollingWindow")

    def encode(self, layout: str, with_imu: bool = False) -> np.ndarray:
        return self.window.encode(layout, with_imu, last=self.T)

    vectors = _tail_of("vectors")
    imu = _tail_of("imu")
    grids = _tail_of("grids")
    frames = _tail_of("frames")
