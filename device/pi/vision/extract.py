"""First stages of the TacTip marker pipeline: dome ROI, threshold, pin blobs.

Runs on the Pi (numpy + OpenCV only). Everything here is a plain function over
numpy arrays, plus one small object (:class:`PinDetector`) that owns the
preallocated buffers for the per-frame hot path.

Image conventions: ``gray`` is a 2-D ``uint8`` array; points are ``(x, y)`` in
pixels with the origin at the top-left pixel centre, as OpenCV reports them.

Pipeline per frame::

    to_gray -> (optional Gaussian pre-blur) -> binarise (adaptive mean-C
    threshold inside the dome mask) -> extract_pins (connected components;
    blobs larger than ``max_area_px`` are glare, smaller than ``min_area_px``
    are noise)

``find_dome`` is run once at start-up (or when the view changes), not per frame.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from device.profile import VisionParams
# gray frames and the dome (found once per view), re-exported with the per-frame stages
from device.pi.vision.gray import image_shape, to_gray  # noqa: F401
from device.pi.vision.dome import dome_mask, find_dome  # noqa: F401

__all__ = [
    "VisionParams",
    "ROBOSKIN_PARAMS",
    "TACTIP_SHEAR_PARAMS",
    "to_gray",
    "find_dome",
    "dome_mask",
    "binarise",
    "components",
    "extract_pins",
    "local_contrast",
    "offset_scale",
    "PinDetector",
]


# --------------------------------------------------------------------------
# Parameters
# --------------------------------------------------------------------------


#: Tuned on the roboskin recordings (640x480, pins ~6.6 px across, ~11.7 px apart):
#: at rest it finds ~113 of the 133 pins plus ~15 glare-texture blobs per frame;
#: a larger block or smaller offset finds more blobs but more of them false.
ROBOSKIN_PARAMS = VisionParams()

#: For the already-binarised 445x440 tactip_shear images (pins ~13 px across).
TACTIP_SHEAR_PARAMS = VisionParams(
    block=31, offset=20.0, blur_sigma_px=0.0, min_area_px=40, max_area_px=400, roi_shrink=1.0
)


# --------------------------------------------------------------------------
# Threshold and blobs
# --------------------------------------------------------------------------


def binarise(
    gray: np.ndarray,
    block: int,
    offset: float,
    roi_mask: np.ndarray | None,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """Adaptive mean-C threshold: 255 where a pixel exceeds its local mean by ``offset``.

    ``gray`` uint8 (H,W); ``block`` odd >= 3; ``roi_mask`` uint8 (H,W) or None
    (whole frame). Writes into ``out`` (uint8 (H,W)) when given.
    """
    if gray.ndim != 2 or gray.dtype != np.uint8:
        raise ValueError(f"gray must be a 2-D uint8 array, got shape={gray.shape!r} dtype={gray.dtype}")
    if isinstance(block, bool) or int(block) != block or block < 3 or block % 2 != 1:
        raise ValueError(f"block must be an odd integer >= 3, got block={block!r}")
    if out is None:
        out = np.empty_like(gray)
    cv2.adaptiveThreshold(
        gray, 255, cv2.ADAPTIVE_THRESH_MEAN_C, cv2.THRESH_BINARY, int(block), -float(offset), dst=out
    )
    if roi_mask is not None:
        if roi_mask.shape != gray.shape:
            raise ValueError(
                f"roi_mask must have the frame's shape {gray.shape!r}, got roi_mask.shape={roi_mask.shape!r}"
            )
        cv2.bitwise_and(out, roi_mask, dst=out)
    return out


#: the offset's exposure scale (:func:`offset_scale`) never goes below this: a very
#: dark frame's threshold stays above its noise
MIN_OFFSET_SCALE = 0.5
#: a contrast ratio at or above this is the calibration's exposure: the contrast
#: varies by 1-3 % between frames and sessions of one exposure, and one gray level
#: less (offset 14 -> 13, the threshold takes whole levels) changes the pins
SAME_EXPOSURE_RATIO = 0.95
#: a contrast below this many gray levels (a black, white or blank dome) is no
#: measure of the exposure: the offset is not scaled
MIN_CONTRAST_LEVELS = 1.0


def local_contrast(smooth: np.ndarray, mask: np.ndarray | None, block: int) -> float:
    """The dome's local contrast, gray levels: the 95th percentile, over the pixels
    where ``mask`` (uint8, ``smooth``'s shape; None = all) is set, of ``smooth`` minus
    its ``block`` x ``block`` box mean (the pins' height above their surround, which a
    darker exposure lowers). 0.0 with no pixel in the mask."""
    if smooth.ndim != 2:
        raise ValueError(f"smooth must be 2-D, got shape={smooth.shape!r}")
    if mask is not None and mask.shape != smooth.shape:
        raise ValueError(f"mask must have smooth's shape {smooth.shape!r}, got "
                         f"mask.shape={mask.shape!r}")
    g = smooth.astype(np.float32)
    d = g - cv2.boxFilter(g, -1, (int(block), int(block)), normalize=True,
                          borderType=cv2.BORDER_REPLICATE)
    d = d if mask is None else d[mask != 0]
    if d.size == 0:
        return 0.0
    v = float(np.percentile(d, 95.0))
    return v if math.isfinite(v) else 0.0


def offset_scale(contrast: float | None, contrast_ref: float | None) -> float:
    """The threshold offset's factor for a frame of local contrast ``contrast`` when
    the calibration measured ``contrast_ref``: ``clamp(contrast / contrast_ref,
    MIN_OFFSET_SCALE, 1)``, and 1 for a ratio of :data:`SAME_EXPOSURE_RATIO` or
    more (the same exposure). Never above 1: a brighter exposure keeps the offset (its
    pins stand out already; a larger offset lost pins). 1.0 (no scaling) when either
    is None, not finite, or below :data:`MIN_CONTRAST_LEVELS` (a black or white dome
    has no contrast to compare)."""
    try:
        c, ref = float(contrast), float(contrast_ref)
    except (TypeError, ValueError):
        return 1.0
    if not (math.isfinite(c) and math.isfinite(ref)) or min(c, ref) < MIN_CONTRAST_LEVELS:
        return 1.0
    r = c / ref
    return 1.0 if r >= SAME_EXPOSURE_RATIO else float(max(MIN_OFFSET_SCALE, r))


#: the labelling algorithm for the pin image: Grana's block-based decision tree
#: (BBDT) with statistics is 2-3x faster on the sparse pin image than OpenCV 5's
#: default (Spaghetti) with statistics, with the same labels and centroids
_CCL = getattr(cv2, "CCL_BBDT", getattr(cv2, "CCL_GRANA", 1))


def components(binary: np.ndarray, labels: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
    """All foreground blobs (8-connected): centroids float32 (n,2) x,y and areas int32 (n,).

    One ``cv2.connectedComponentsWithStatsWithAlgorithm`` call with the BBDT
    labelling (:data:`_CCL`). Pass ``labels`` (int32, the binary's shape) to label
    without allocating.
    """
    if binary.ndim != 2:
        raise ValueError(f"binary must be 2-D, got shape={binary.shape!r}")
    b = binary if binary.dtype == np.uint8 else (binary != 0).astype(np.uint8)
    if labels is None or labels.shape != b.shape or labels.dtype != np.int32:
        labels = np.empty(b.shape, np.int32)
    n, _, stats, cents = cv2.connectedComponentsWithStatsWithAlgorithm(
        b, 8, cv2.CV_32S, _CCL, labels=labels)
    if n <= 1:
        return np.zeros((0, 2), np.float32), np.zeros((0,), np.int32)
    return cents[1:].astype(np.float32), stats[1:, cv2.CC_STAT_AREA].astype(np.int32)


def extract_pins(
    binary: np.ndarray, min_area: int, max_area: int, labels: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Pin centroids float32 (n,2) as x,y and their areas int32 (n,).

    Blobs with area > ``max_area`` (glare) or < ``min_area`` (noise) are dropped.
    Zero pins gives arrays of shape (0,2) and (0,).
    """
    if max_area < min_area:
        raise ValueError(f"max_area must be >= min_area, got max_area={max_area!r}, min_area={min_area!r}")
    cents, areas = components(binary, labels)
    keep = (areas >= min_area) & (areas <= max_area)
    return np.ascontiguousarray(cents[keep]), areas[keep]


# --------------------------------------------------------------------------
# Hot-path object
# --------------------------------------------------------------------------


class PinDetector:
    """Per-frame pin extraction with preallocated buffers.

    Works on the bounding box of the dome only (about 1/6 of a 640x480 frame
    for roboskin), and returns centroids in full-frame coordinates.

    >>> det = PinDetector(ROBOSKIN_PARAMS, (480, 640), dome=(326.0, 219.0, 145.0))  # doctest: +SKIP
    >>> xy, areas = det.detect(frame)                                                # doctest: +SKIP
    """

    def __init__(
        self,
        params: VisionParams,
        frame_shape: tuple[int, int],
        dome: tuple[float, float, float] | None = None,
    ) -> None:
        if not isinstance(params, VisionParams):
            raise ValueError(f"params must be a VisionParams, got params={params!r}")
        h, w = int(frame_shape[0]), int(frame_shape[1])
        if h < 1 or w < 1:
            raise ValueError(f"frame_shape must be positive, got frame_shape={frame_shape!r}")
        self.params = params
        self.frame_shape = (h, w)
        self.n_blobs = 0
        self.set_dome(dome)

    def set_dome(self, dome: tuple[float, float, float] | None) -> None:
        h, w = self.frame_shape
        p = self.params
        if dome is None:
            x0, y0, x1, y1 = 0, 0, w, h
        else:
            cx, cy, r = (float(v) for v in dome)
            if not all(math.isfinite(v) for v in (cx, cy, r)) or r <= 0:
                raise ValueError(f"dome must be finite (cx, cy, r) with r > 0, got dome={dome!r}")
            rr = r * p.roi_shrink + p.block  # margin so the local mean sees context
            x0 = max(0, int(math.floor(cx - rr)))
            y0 = max(0, int(math.floor(cy - rr)))
            x1 = min(w, int(math.ceil(cx + rr)) + 1)
            y1 = min(h, int(math.ceil(cy + rr)) + 1)
            if x1 <= x0 or y1 <= y0:
                x0, y0, x1, y1 = 0, 0, w, h
        self.dome = dome
        self.box = (x0, y0, x1, y1)
        bh, bw = y1 - y0, x1 - x0
        self._gray = np.empty((bh, bw), np.uint8)     # the crop in gray (colour frames)
        self._smooth = np.empty((bh, bw), np.uint8)
        # the labelling (_CCL) with statistics takes its fast path on even sides
        # only (about 2.5x faster on a 240 px crop): the binary crop is a view into
        # a buffer one zero row / column larger when a side is odd
        self._binary_even = np.zeros((bh + bh % 2, bw + bw % 2), np.uint8)
        self._binary = self._binary_even[:bh, :bw]
        # a kernel of +-2 sigma (OpenCV's own default is +-3, which is slower)
        k = max(3, 2 * int(math.ceil(2.0 * p.blur_sigma_px)) + 1)
        self._ksize = (k, k)
        self._origin = np.array([x0, y0], np.float32)
        mask_full = dome_mask((h, w), dome, p.roi_shrink)
        self._mask = np.ascontiguousarray(mask_full[y0:y1, x0:x1])
        self._set_core(bh, bw)

    def _set_core(self, bh: int, bw: int) -> None:
        """The dome's own pixels: the mask disc's bounding box inside the dome box.

        Only they are thresholded (about 80 % of the box for roboskin); the rest of the
        binary box stays 0, as the mask made it before. The labelling runs from the
        box's origin to the disc's far edge, rounded up to even sides (about 90 % of
        the box): the block-based labelling then sees the same 2x2 blocks, in the same
        order, as on the whole buffer, so the same labels in the same order, and the
        centroids are OpenCV's own in box px (no shift to correct)."""
        p = self.params
        ys, xs = np.nonzero(self._mask)
        if len(ys):
            cy0, cx0 = int(ys.min()), int(xs.min())
            cy1, cx1 = int(ys.max()) + 1, int(xs.max()) + 1
        else:
            cy0, cx0, cy1, cx1 = 0, 0, 2, 2
        eh, ew = self._binary_even.shape
        cy1, cx1 = min(eh, cy1 + cy1 % 2), min(ew, cx1 + cx1 % 2)
        self.core = (cx0, cy0, cx1, cy1)             # in box px
        self._core_binary = self._binary_even[:cy1, :cx1]
        self._core_labels = np.empty((cy1, cx1), np.int32)
        # the threshold runs on the core clipped to the box (the odd-side pad is not
        # in the gray box); its local mean on the core grown by half a block, so every
        # core pixel's block sees the pixels it saw in the whole box (and the box's
        # replicated edge where the whole box had it)
        ty1, tx1 = min(cy1, self._smooth.shape[0]), min(cx1, self._smooth.shape[1])
        half = p.block // 2
        gy0, gx0 = max(0, cy0 - half), max(0, cx0 - half)
        gy1 = min(self._smooth.shape[0], ty1 + half)
        gx1 = min(self._smooth.shape[1], tx1 + half)
        self._grown = (slice(gy0, gy1), slice(gx0, gx1))
        self._in_grown = (slice(cy0 - gy0, ty1 - gy0), slice(cx0 - gx0, tx1 - gx0))
        self._core_src = (slice(cy0, ty1), slice(cx0, tx1))
        self._mean = np.empty((gy1 - gy0, gx1 - gx0), np.uint8)
        self._core_mask = np.ascontiguousarray(self._mask[cy0:ty1, cx0:tx1])
        self._core_out = self._binary_even[cy0:ty1, cx0:tx1]
        self._compiled = None
        #: after a compiled detection, the smoothed box's plausibility sums
        #: (:meth:`device.pi.vision.core.DetectCore.sums`, a bound method); None after numpy
        self.sums = None
        #: why detection runs on numpy (OpenCV) rather than compiled ('' when compiled)
        self.compiled_why = "not tried"
        self.set_offset(p.offset)
        self._try_compiled()

    def __getstate__(self) -> dict:
        # the compiled core points at this object's own buffers: a copy makes its own
        state = dict(self.__dict__)
        state["_compiled"] = state["sums"] = None
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._try_compiled()

    def _try_compiled(self) -> None:
        """Use ``detect.c`` (:mod:`device.pi.vision.core`) from now on when its
        library is loaded, it takes these parameters, and it reproduces this
        detector's own numpy path to the byte on a test frame of this geometry."""
        from device.pi.vision import core, native
        self._compiled = None
        fn = native.detect_fn()
        if fn is None:
            self.compiled_why = f"no compiled library ({native.status()})"
            return
        why = core.supported(self.params, self.offset)
        if why:
            self.compiled_why = why
            return
        c = core.DetectCore(fn, self)
        why = core.self_check(self, c)
        self.compiled_why = why
        if not why:
            self._compiled = c

    def set_offset(self, offset: float) -> None:
        """Threshold from now on with ``offset`` gray levels (the profile's, or the
        profile's scaled for the exposure, :func:`offset_scale`)."""
        offset = float(offset)
        if not math.isfinite(offset):
            raise ValueError(f"offset must be finite, got offset={offset!r}")
        #: the offset the threshold uses
        self.offset = offset
        # OpenCV's mean-C threshold keeps src - mean > floor(offset); for offset >= 0
        # a saturating subtraction gives the same test (a negative offset takes
        # cv2.adaptiveThreshold on the whole box)
        self._floor_offset = math.floor(offset)
        self._fast = self._floor_offset >= 0
        c = getattr(self, "_compiled", None)
        if c is not None:
            if self._fast:
                c.set_offset(offset)
            else:                    # a negative offset: cv2.adaptiveThreshold, numpy
                self._compiled = None
                self.compiled_why = f"a negative threshold offset ({offset})"

    def local_contrast(self) -> float:
        """:func:`local_contrast` of the last blurred dome box over the dome disc."""
        return local_contrast(self._smooth, self._mask, self.params.block)

    @property
    def blur_ksize(self) -> tuple[int, int]:
        """The pre-blur kernel: +-2 sigma, odd."""
        return self._ksize

    @property
    def binary(self) -> np.ndarray:
        """The last thresholded crop (view of the internal buffer)."""
        return self._binary

    def gray_crop(self, frame: np.ndarray) -> np.ndarray:
        """The dome box of ``frame`` in gray: a view when the frame is gray uint8
        already (no copy), else converted into the internal buffer. Only the box is
        read: a colour frame's pixels outside it are never converted."""
        if frame.shape[:2] != self.frame_shape:
            raise ValueError(f"frame shape must be {self.frame_shape!r}, got frame.shape={frame.shape!r}")
        x0, y0, x1, y1 = self.box
        crop = frame[y0:y1, x0:x1]
        if crop.ndim == 3 or crop.dtype != np.uint8:
            crop = to_gray(crop, out=self._gray)
        return crop

    def threshold(self, frame: np.ndarray) -> np.ndarray:
        """Gray, blur and binarise the dome crop; returns the internal binary buffer."""
        return self.threshold_gray(self.gray_crop(frame))

    def threshold_gray(self, crop: np.ndarray) -> np.ndarray:
        """Blur and binarise a gray dome box (:meth:`gray_crop`'s); returns the
        internal binary buffer. The same pixels as ``binarise`` on the blurred box with
        the dome mask, computed on the dome's own pixels only (:meth:`_set_core`)."""
        p = self.params
        if p.blur_sigma_px > 0:
            cv2.GaussianBlur(crop, self._ksize, p.blur_sigma_px, dst=self._smooth)
        else:
            np.copyto(self._smooth, crop)
        if not self._fast:
            return binarise(self._smooth, p.block, self.offset, self._mask, out=self._binary)
        # cv2.adaptiveThreshold(MEAN_C) is this box filter then a per-pixel table
        # look-up; a saturating subtraction, one threshold and the mask do the look-up
        # and the masking in three vectorised passes over the core
        out = self._core_out
        cv2.boxFilter(self._smooth[self._grown], -1, (p.block, p.block), dst=self._mean,
                      normalize=True, borderType=cv2.BORDER_REPLICATE)
        cv2.subtract(self._smooth[self._core_src], self._mean[self._in_grown], dst=out)
        cv2.threshold(out, self._floor_offset, 255, cv2.THRESH_BINARY, dst=out)
        cv2.bitwise_and(out, self._core_mask, dst=out)
        return self._binary

    @property
    def smooth(self) -> np.ndarray:
        """The last gray, pre-blurred dome box (view of the internal buffer)."""
        return self._smooth

    def _blobs(self) -> tuple[np.ndarray, np.ndarray]:
        """Every blob of the binary box (labelled up to the dome's far edge):
        centroids float64 (n,2) in box px, areas int32 (n,), views of OpenCV's output."""
        n, _, stats, cents = cv2.connectedComponentsWithStatsWithAlgorithm(
            self._core_binary, 8, cv2.CV_32S, _CCL, labels=self._core_labels)
        return cents[1:], stats[1:, cv2.CC_STAT_AREA]

    def detect(self, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pins of one frame: centroids float32 (n,2) x,y in frame px, areas int32 (n,).
        :attr:`n_blobs` is the number of blobs of any size it was chosen from."""
        return self.detect_gray(self.gray_crop(frame))

    @property
    def compiled(self) -> bool:
        """True when :meth:`detect_gray` runs ``detect.c`` (one call), not OpenCV."""
        return self._compiled is not None

    def detect_gray(self, crop: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`detect` on the gray dome box (:meth:`gray_crop`'s): compiled when
        :attr:`compiled`, the same bytes as :meth:`detect_numpy`."""
        c = self._compiled
        if c is not None and crop.strides[1] == 1 and crop.dtype == np.uint8 \
                and crop.shape == self._smooth.shape:
            n = c.detect(crop)
            if n >= 0:
                self.n_blobs = c.n_blobs
                self.sums = c.sums
                return c.xy[:n].copy(), c.areas[:n].copy()
        return self.detect_numpy(crop)

    def detect_numpy(self, crop: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The specification of :meth:`detect_gray`: OpenCV's blur, threshold and
        connected components."""
        self.sums = None
        self.threshold_gray(crop)
        cents, areas = self._blobs()
        self.n_blobs = len(areas)
        p = self.params
        keep = (areas >= p.min_area_px) & (areas <= p.max_area_px)
        # float32 centroids plus the float32 origin, added in float32
        xy = np.add(cents[keep], self._origin, dtype=np.float32)
        return xy, areas[keep]

    def detect_all(self, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """All blobs (pins, glare and noise) in frame px, for measurement."""
        self.threshold(frame)
        cents, areas = self._blobs()
        return np.add(cents, self._origin, dtype=np.float32), areas.copy()
