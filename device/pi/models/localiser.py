"""Fixed-count pin localiser: the binary dome image -> all N pin positions.

Runs on the Pi (numpy + OpenCV + onnxruntime through :mod:`device.pi.models.artefact`).
A linear (Ridge) model, trained on the host by ``host/localiser/train.py``, maps the
downscaled binary image of the dome to the positions of a fixed set of pins
(133 for ``roboskin``). Unlike blob detection plus tracking it always returns
every pin, also where glare hides one or two pins merge.

Coordinates. The model sees a square crop around the dome centre with
half-side ``crop_factor * r`` and predicts each pin in *dome-normalised*
coordinates ``u = (x - cx) / r, v = (y - cy) / r``, so it does not depend on
where the dome sits in the frame or on its size in px. The crop is cut on the
pixel grid: ``(cx, cy, r)`` is first snapped to the *effective dome* of the
integer square actually cut (:func:`crop_square`, :func:`effective_dome`), and
the normalisation uses that, so image and coordinates always agree exactly.
The output vector is ``u0, v0, u1, v1, ...`` (pin order of the profile).

Per frame::

    binary crop (PinDetector.binary, its box) + dome
        -> localiser_input: cut the square (zero padding outside the image),
           INTER_AREA resize to size x size, scale to 0..1   (1, size*size) float32
        -> ONNX Ridge                                        (1, 2N)
        -> back to frame px                                  (N, 2) float32

Hard cases (no dome, absurd dome, black / white / noise binary images, a
non-finite or implausible model output) give the manifest's mean layout mapped
into the frame, finite, with ``fault`` set. :meth:`Localiser.locate` never
raises on the per-frame path.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from device.checks import finite_number
from device.pi.models.artefact import Model, ModelError, load_model

__all__ = [
    "KIND",
    "DEFAULT_CROP_FACTOR",
    "crop_square",
    "effective_dome",
    "localiser_input",
    "to_normalised",
    "from_normalised",
    "Localiser",
]

#: manifest ``kind`` of a localiser artefact
KIND = "localiser"
#: half-side of the crop square in dome radii (roboskin: pins reach 0.67 r at
#: rest, the PinDetector's mask 0.75 r); a trained model stores its own
DEFAULT_CROP_FACTOR = 0.75
#: a crop side above this many px is not a dome of any camera this runs on
_MAX_SIDE_PX = 4096
#: a dome radius below this many px cannot hold a pin layout
_MIN_RADIUS_PX = 4.0


# --------------------------------------------------------------------------
# Geometry of the crop
# --------------------------------------------------------------------------


def _dome3(dome) -> tuple[float, float, float]:
    """``dome`` as three finite floats with r > 0, or ValueError naming it."""
    try:
        cx, cy, r = (float(v) for v in dome)
    except (TypeError, ValueError):
        raise ValueError(f"dome must be (cx, cy, r) px, got dome={dome!r}") from None
    if not (math.isfinite(cx) and math.isfinite(cy) and math.isfinite(r)) or r <= 0.0:
        raise ValueError(f"dome must be finite (cx, cy, r) with r > 0, got dome={dome!r}")
    return cx, cy, r


def _check_factor(crop_factor) -> float:
    return finite_number("crop_factor", crop_factor, 0.05, 4.0)


def crop_square(dome, crop_factor: float = DEFAULT_CROP_FACTOR) -> tuple[int, int, int]:
    """The integer square ``(x0, y0, side_px)`` in frame px cut around ``dome``.

    ``side_px`` is even, ``2 * round(crop_factor * r)`` (at least 2), and the
    square is placed so its centre is within half a pixel of ``(cx, cy)``.
    Raises ValueError for a malformed dome or a square above 4096 px.
    """
    cx, cy, r = _dome3(dome)
    f = _check_factor(crop_factor)
    half = max(1, int(round(f * r)))
    side = 2 * half
    if side > _MAX_SIDE_PX:
        raise ValueError(f"dome radius too large for a crop: dome={dome!r} gives a "
                         f"{side} px square (max {_MAX_SIDE_PX})")
    # pixel centres are at integers: the square x0 .. x0+side-1 has centre x0 + (side-1)/2
    x0 = int(math.floor(cx - (side - 1) / 2.0 + 0.5))
    y0 = int(math.floor(cy - (side - 1) / 2.0 + 0.5))
    return x0, y0, side


def effective_dome(dome, crop_factor: float = DEFAULT_CROP_FACTOR) -> tuple[float, float, float]:
    """The dome ``(cx, cy, r)`` that the integer crop of ``dome`` exactly represents."""
    f = _check_factor(crop_factor)
    x0, y0, side = crop_square(dome, f)
    return x0 + (side - 1) / 2.0, y0 + (side - 1) / 2.0, side / (2.0 * f)


def to_normalised(pins_px: np.ndarray, dome,
                  crop_factor: float = DEFAULT_CROP_FACTOR) -> np.ndarray:
    """Frame px (N, 2) -> dome-normalised (N, 2) float64 for the crop of ``dome``."""
    cx, cy, r = effective_dome(dome, crop_factor)
    p = np.asarray(pins_px, dtype=np.float64).reshape(-1, 2)
    return (p - (cx, cy)) / r


def from_normalised(uv: np.ndarray, dome, crop_factor: float = DEFAULT_CROP_FACTOR,
                    out: np.ndarray | None = None) -> np.ndarray:
    """Dome-normalised (N, 2) -> frame px (N, 2) float32 for the crop of ``dome``."""
    cx, cy, r = effective_dome(dome, crop_factor)
    a = np.asarray(uv).reshape(-1, 2)
    if out is None:
        out = np.empty(a.shape, np.float32)
    np.multiply(a, r, out=out, casting="unsafe")
    out[:, 0] += cx
    out[:, 1] += cy
    return out


# --------------------------------------------------------------------------
# Model input
# --------------------------------------------------------------------------


def _check_size(size) -> int:
    if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or not 4 <= size <= 256:
        raise ValueError(f"size must be an integer in [4, 256], got size={size!r}")
    return int(size)


def _origin(box) -> tuple[int, int]:
    if box is None:
        return 0, 0
    try:
        x0, y0 = int(box[0]), int(box[1])
    except (TypeError, ValueError, IndexError, OverflowError):
        raise ValueError(f"box must be (x0, y0, x1, y1) px or None, got box={box!r}") from None
    return x0, y0


def _edges(side: int, size: int, offset: int, extent: int) -> tuple[np.ndarray, np.ndarray]:
    """Integral-image sample points of the ``size + 1`` output cell edges along one axis.

    The square's edges ``k * side / size`` (k = 0..size), shifted by ``offset``
    into the overlap's coordinates and clipped to ``[0, extent]`` (outside the
    image counts as 0, so clipping is exact); returned as the integer index
    ``i`` (0..extent-1) and the fraction ``f`` with edge = i + f.
    """
    e = np.arange(size + 1, dtype=np.float64) * (side / size) + offset
    np.clip(e, 0.0, float(extent), out=e)
    i = np.minimum(np.floor(e), extent - 1).astype(np.intp)
    return i, e - i


def localiser_input(
    binary: np.ndarray,
    box,
    dome,
    size: int,
    crop_factor: float = DEFAULT_CROP_FACTOR,
    out: np.ndarray | None = None,
    scratch: dict | None = None,
) -> np.ndarray:
    """The model input ``x`` (1, size*size) float32 in 0..1 for one binary image.

    ``binary``: 2-D array, the thresholded image (nonzero = pin); either the
    whole frame (``box`` None) or a crop of it whose top-left pixel is frame
    px ``(box[0], box[1])`` (``PinDetector.binary`` with ``PinDetector.box``).
    ``dome``: ``(cx, cy, r)`` in frame px. The square of half-side
    ``crop_factor * r`` around the dome centre (:func:`crop_square`) is cut,
    anything outside ``binary`` counting as 0, and shrunk to size x size by
    area averaging: each output cell is the share of foreground pixels under
    it, partial pixels weighted by their overlap. That is exactly what
    ``cv2.resize(..., interpolation=cv2.INTER_AREA)`` computes (in float)
    when shrinking, but done from an integral image, 2x faster than
    cv2.resize for the non-integer ratios a dome gives (218 -> 32 px: ~55 us
    instead of 100 us). For a square smaller than ``size`` (absurd domes
    only) it is still the exact area average.

    ``out`` (float32, size*size elements) and ``scratch`` (a dict in which
    this function keeps its buffers and the crop geometry) make the call
    allocation-light in steady state. Raises ValueError only for malformed
    arguments (a crop partly or wholly outside ``binary`` is fine: zeros).
    """
    size = _check_size(size)
    b = np.asarray(binary)
    if b.ndim != 2:
        raise ValueError(f"binary must be a 2-D image, got binary.shape={b.shape!r}")
    bx0, by0 = _origin(box)
    x0, y0, side = crop_square(dome, crop_factor)
    if out is None:
        out = np.empty((1, size * size), np.float32)
    elif not isinstance(out, np.ndarray) or out.dtype != np.float32 or out.size != size * size:
        raise ValueError(f"out must be float32 with {size * size} elements, got "
                         f"out={type(out).__name__} {getattr(out, 'dtype', None)} "
                         f"size {getattr(out, 'size', None)}")
    o2 = out.reshape(size, size)
    h, w = b.shape
    sx0, sy0 = x0 - bx0, y0 - by0          # square's corner in binary coordinates
    ix0, iy0 = max(sx0, 0), max(sy0, 0)
    ix1, iy1 = min(sx0 + side, w), min(sy0 + side, h)
    if ix1 <= ix0 or iy1 <= iy0:
        o2[:] = 0.0
        return out
    hh, ww = iy1 - iy0, ix1 - ix0
    if scratch is None:
        scratch = {}
    key = (side, size, sx0 - ix0, sy0 - iy0, hh, ww)
    geo = scratch.get("geo")
    if geo is None or geo[0] != key:
        yi, fy = _edges(side, size, sy0 - iy0, hh)
        xi, fx = _edges(side, size, sx0 - ix0, ww)
        geo = scratch["geo"] = (key, yi, yi + 1, fy[:, None], 1.0 - fy[:, None],
                                xi, xi + 1, fx, 1.0 - fx, 1.0 / (side / size) ** 2,
                                np.empty((hh, ww), np.uint8),
                                np.empty((hh + 1, ww + 1), np.int32))
    _, yi, yi1, fy, gy, xi, xi1, fx, gx, inv_area, thr, integ = geo
    src = b[iy0:iy1, ix0:ix1]
    if src.dtype == np.uint8:
        cv2.threshold(src, 0, 1, cv2.THRESH_BINARY, dst=thr)
    else:  # bool, float (NaN counts as set), ...: anything nonzero is foreground
        np.not_equal(src, 0, out=thr, casting="unsafe")
    cv2.integral(thr, integ, sdepth=cv2.CV_32S)
    # integral at the fractional cell edges: bilinear in the integral image is
    # exact for a pixel-wise constant image; rows first, then columns
    rows = integ[yi] * gy + integ[yi1] * fy                 # (size+1, ww+1)
    g = rows[:, xi] * gx + rows[:, xi1] * fx                # (size+1, size+1)
    cell = g[1:, 1:] - g[:-1, 1:] - g[1:, :-1] + g[:-1, :-1]
    np.multiply(cell, inv_area, out=o2, casting="unsafe")
    np.clip(o2, 0.0, 1.0, out=o2)  # rounding can leave -1e-16 or 1 + 1e-16
    return out


# --------------------------------------------------------------------------
# The runtime object
# --------------------------------------------------------------------------


class Localiser:
    """A loaded localiser artefact with its preallocated per-frame buffers.

    >>> loc = Localiser.load("models/localiser-roboskin")          # doctest: +SKIP
    >>> det.detect(frame)                                          # doctest: +SKIP
    >>> pins_px, fault = loc.locate(det.binary, dome, box=det.box) # doctest: +SKIP

    Parameters used (the spec's ``params``): ``n_pins``, ``size``, ``crop_factor``,
    ``mean_layout_norm`` (N x 2), and optionally ``fill_range`` (plausible
    mean of the input, [lo, hi]), ``fill_grid`` and ``fill_cells_range``
    (the same per cell of a grid over the crop: [lo x g*g, hi x g*g]) and
    ``max_dev_norm`` (largest plausible distance of a pin from its mean
    position, in dome radii).
    """

    def __init__(self, model: Model) -> None:
        p = model.spec.params           # LocaliserParams, typed by the one parse
        where = f"{model.source}"
        try:
            self.n_pins = p.n_pins
            self.size = _check_size(p.size)
            self.crop_factor = _check_factor(float(p.crop_factor))
            mean = np.asarray(p.mean_layout_norm, dtype=np.float64)
            self.fill_range = (float(p.fill_range[0]), float(p.fill_range[1]))
            self.fill_grid = p.fill_grid
            cells = np.asarray(p.fill_cells_range, dtype=np.float32)
            self.max_dev_norm = math.inf if p.max_dev_norm is None else float(p.max_dev_norm)
        except (TypeError, ValueError, IndexError) as exc:
            raise ModelError(f"{where}: bad localiser parameters ({exc})") from None
        if self.n_pins < 1 or mean.shape != (self.n_pins, 2) or not np.isfinite(mean).all():
            raise ModelError(f"{where}: mean_layout_norm must be finite ({self.n_pins}, 2), "
                             f"got shape {mean.shape}")
        g = self.fill_grid
        if g and (self.size % g or cells.shape != (2, g * g)):
            raise ModelError(f"{where}: fill_cells_range must be 2 x {g * g} and size "
                             f"{self.size} divisible by fill_grid {g}")
        n_in = model.spec.n_inputs
        if n_in != self.size * self.size:
            raise ModelError(f"{where}: input width {n_in} does not match size "
                             f"{self.size} ({self.size * self.size})")
        self.model = model
        self.spec = model.spec
        self.mean_layout_norm = mean.astype(np.float32)
        self._x = np.zeros((1, self.size * self.size), np.float32)
        self._scratch: dict = {}
        self._uv = np.empty((self.n_pins, 2), np.float32)
        self._dev = np.empty((self.n_pins, 2), np.float32)
        if self.fill_grid:
            self._cells = np.empty((self.fill_grid, self.fill_grid), np.float32)
            self._cells_lo = cells[0].reshape(self.fill_grid, self.fill_grid)
            self._cells_hi = cells[1].reshape(self.fill_grid, self.fill_grid)
        self._geo_key: object = ()
        self._geo: tuple = ((0.0, 0.0, 1.0), "no dome")
        #: why the last call set the fault flag ("" when it did not)
        self.fault_reason = ""

    @classmethod
    def load(cls, model_dir: Path | str) -> "Localiser":
        """Load a localiser artefact folder (checksum and feature spec checked)."""
        return cls(load_model(model_dir, expect_kind=KIND))

    @property
    def input(self) -> np.ndarray:
        """The last model input (1, size*size), a view of the internal buffer."""
        return self._x

    def predict_normalised(self, x: np.ndarray) -> np.ndarray:
        """Raw model output for inputs (k, size*size) float32 -> (k, 2N) float32."""
        return np.asarray(self.model.run(np.ascontiguousarray(x, dtype=np.float32))[0])

    def _fallback_dome(self, shape: tuple[int, int], box) -> tuple[float, float, float]:
        """A dome for the mean layout when the given one is unusable: the middle
        of the image region (the box, or the whole binary image), sized so the
        crop square would just fill the region."""
        h, w = shape
        try:
            bx0, by0 = _origin(box)
        except ValueError:
            bx0, by0 = 0, 0
        return (bx0 + (w - 1) / 2.0, by0 + (h - 1) / 2.0,
                max(1.0, min(h, w) / 2.0) / self.crop_factor)

    def _mean_pins(self, dome, out: np.ndarray) -> np.ndarray:
        cx, cy, r = dome
        np.multiply(self.mean_layout_norm, np.float32(r), out=out)
        out[:, 0] += np.float32(cx)
        out[:, 1] += np.float32(cy)
        if not np.isfinite(out).all():  # cannot happen for a finite fallback dome
            out[:] = 0.0
        return out

    def _geometry(self, shape: tuple[int, int], dome, box):
        """(effective dome, fault reason or "") for this image shape, dome and box.

        Cached: the dome and box change rarely, so the per-frame cost is one
        tuple comparison.
        """
        key = (shape, dome if dome is None else tuple(dome), box if box is None else tuple(box))
        if key == self._geo_key:
            return self._geo
        fallback = self._fallback_dome(shape, box)
        geo = None
        if dome is None:
            geo = (fallback, "no dome")
        else:
            try:
                cx, cy, r = _dome3(dome)
                if r < _MIN_RADIUS_PX:
                    geo = (fallback, f"dome radius {r:.3g} px below {_MIN_RADIUS_PX}")
                else:
                    x0, y0, side = crop_square((cx, cy, r), self.crop_factor)
                    eff = effective_dome((cx, cy, r), self.crop_factor)
                    bx0, by0 = _origin(box)
                    h, w = shape
                    if x0 + side <= bx0 or y0 + side <= by0 or x0 >= bx0 + w or y0 >= by0 + h:
                        geo = (fallback, "dome crop lies outside the image")
                    else:
                        geo = (eff, "")
            except (ValueError, TypeError, OverflowError) as exc:
                geo = (fallback, f"unusable dome or box ({exc})")
        self._geo_key, self._geo = key, geo
        return geo

    def _implausible_input(self) -> str:
        """Why the current input does not look like a dome of pins, or "".

        The foreground share of the whole crop, and of each cell of a
        ``fill_grid`` x ``fill_grid`` grid over it, must lie in the ranges seen
        in training (with a margin): black, white, noise and a dome that
        misses the pins fail; so does noise in the corners, which the dome
        mask keeps black.
        """
        fill = float(self._x.mean())
        lo, hi = self.fill_range
        if not lo <= fill <= hi:
            return f"foreground fraction {fill:.3f} outside [{lo:.3f}, {hi:.3f}]"
        if self.fill_grid:
            g = self.fill_grid
            cv2.resize(self._x.reshape(self.size, self.size), (g, g), dst=self._cells,
                       interpolation=cv2.INTER_AREA)
            bad = (self._cells < self._cells_lo) | (self._cells > self._cells_hi)
            if bad.any():
                i, j = (int(v) for v in np.argwhere(bad)[0])
                return (f"foreground fraction {self._cells[i, j]:.3f} of grid cell ({i}, {j}) "
                        f"outside [{self._cells_lo[i, j]:.3f}, {self._cells_hi[i, j]:.3f}]")
        return ""

    def locate(self, binary: np.ndarray, dome, box=None,
               out: np.ndarray | None = None) -> tuple[np.ndarray, bool]:
        """All pins of one frame: ``(pins (N, 2) float32 frame px, fault)``.

        ``binary``: the thresholded image, whole frame (``box`` None) or the
        crop ``PinDetector.binary`` whose origin is ``box = PinDetector.box``.
        ``dome``: ``(cx, cy, r)`` frame px, or None when no dome was found.
        ``out``: optional (N, 2) float32 array to write the pins into.
        Always returns N finite pins; with ``fault`` True they are the mean
        layout mapped into the frame (and :attr:`fault_reason` says why).
        Never raises.
        """
        if not (isinstance(out, np.ndarray) and out.shape == (self.n_pins, 2)
                and out.dtype == np.float32):
            out = np.empty((self.n_pins, 2), np.float32)
        try:
            b = binary if isinstance(binary, np.ndarray) else np.asarray(binary)
            ok_image = b.ndim == 2 and b.size > 0
        except Exception:  # an object numpy cannot take
            ok_image = False
        if not ok_image:
            return self._fail("binary image is not a non-empty 2-D array",
                              self._fallback_dome((1, 1), None), out)
        try:
            eff, reason = self._geometry(b.shape, dome, box)
        except Exception as exc:  # unhashable or odd dome/box objects
            return self._fail(f"unusable dome or box ({exc})",
                              self._fallback_dome(b.shape, None), out)
        if reason:
            return self._fail(reason, eff, out)
        try:
            localiser_input(b, box, eff, self.size, self.crop_factor,
                            out=self._x, scratch=self._scratch)
        except (ValueError, TypeError, OverflowError, cv2.error, MemoryError) as exc:
            return self._fail(f"unusable input ({exc})", eff, out)
        reason = self._implausible_input()
        if reason:
            return self._fail(reason, eff, out)
        try:
            y = self.model.run(self._x)[0]
        except Exception as exc:  # onnxruntime raises its own types
            return self._fail(f"model run failed ({exc})", eff, out)
        uv = self._uv
        if y.size != uv.size:
            return self._fail(f"model output has {y.size} values, expected {uv.size}", eff, out)
        uv.reshape(-1)[:] = y.reshape(-1)
        np.subtract(uv, self.mean_layout_norm, out=self._dev)
        np.abs(self._dev, out=self._dev)
        dev = float(self._dev.max())
        if not math.isfinite(dev):
            return self._fail("model output not finite", eff, out)
        if dev > self.max_dev_norm:
            return self._fail(f"implausible output: a pin {dev:.3f} r from its mean", eff, out)
        self.fault_reason = ""
        ecx, ecy, er = eff
        np.multiply(uv, np.float32(er), out=out)
        out[:, 0] += np.float32(ecx)
        out[:, 1] += np.float32(ecy)
        return out, False

    def _fail(self, reason: str, dome, out: np.ndarray) -> tuple[np.ndarray, bool]:
        self.fault_reason = reason
        return self._mean_pins(dome, out), True
