"""Gray frames straight from a source: the luma plane of a V4L2 camera's raw buffer,
or one conversion of a decoded colour frame, done where the frame is grabbed (the
runtime's grab thread), so the loop thread gets gray and converts nothing.

The gray image is the one the colour path gives: ``cv2.cvtColor(bgr, BGR2GRAY)`` of
the frame OpenCV would have decoded. For a decoded colour frame that is exact. For
YUYV / UYVY the luma plane goes through a 256-entry table built from OpenCV's own
``YUV2BGR_YUYV`` and ``BGR2GRAY`` on neutral pixels (OpenCV expands the video range
16..235 to 0..255), so a neutral pixel gets exactly the colour path's gray and a
coloured one differs by rounding: at most one gray level where no decoded channel
clips; more where the colour path clips one at 0 or 255 (dark or bright pixels with
strong chroma; the roboskin frames' chroma reaches 15-27 at the 99th percentile). So
YUYV luma is not bit-identical to the colour path; the pins found may differ where a
pixel sits at the threshold. A GREY (Y800) buffer is exactly that image.

Plain functions over numpy; a bad buffer is a ``ValueError`` naming its shape.
"""
from __future__ import annotations

import functools

import cv2
import numpy as np

__all__ = ["PACKED_YUV", "PLANE_GRAY", "yuv_luma_table", "luma_plane", "to_gray_frame"]

#: packed 4:2:2 formats: byte offset of the first luma sample in each 2-byte pixel
PACKED_YUV = {"YUYV": 0, "YUY2": 0, "UYVY": 1}
#: formats whose buffer is the gray image itself
PLANE_GRAY = frozenset({"GREY", "Y800"})


@functools.lru_cache(maxsize=1)
def yuv_luma_table() -> np.ndarray:
    """uint8 (256,): the colour path's gray for a neutral pixel of luma Y (U = V = 128)."""
    yuyv = np.empty((1, 256, 2), np.uint8)
    yuyv[0, :, 0] = np.arange(256)
    yuyv[0, :, 1] = 128
    bgr = cv2.cvtColor(yuyv, cv2.COLOR_YUV2BGR_YUYV)
    table = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)[0]
    table.flags.writeable = False
    return table


def luma_plane(raw: np.ndarray, width: int, height: int, fourcc: str) -> np.ndarray:
    """The gray (height, width) uint8 image of one raw V4L2 buffer.

    ``raw`` is what OpenCV's V4L2 capture returns with ``CAP_PROP_CONVERT_RGB`` off:
    any uint8 array holding the buffer's bytes in order (1 x n, h x w x 2, h x 2w ...).
    YUYV / YUY2 / UYVY (``width * height * 2`` bytes) give the table-mapped luma plane
    (:func:`yuv_luma_table`); GREY / Y800 (``width * height`` bytes) the buffer itself.
    A new array is returned (the capture reuses its buffer)."""
    a = np.asarray(raw)
    if a.dtype != np.uint8:
        raise ValueError(f"raw buffer must be uint8, got raw.dtype={a.dtype}")
    w, h = int(width), int(height)
    if w < 2 or h < 1 or (fourcc in PACKED_YUV and w % 2):
        raise ValueError(f"frame size must be >= 2 x 1 (even width for packed YUV), got "
                         f"width={width!r}, height={height!r}")
    if fourcc in PLANE_GRAY:
        if a.size < w * h:
            raise ValueError(f"{fourcc} buffer must hold {w * h} bytes ({w}x{h}), got "
                             f"raw.shape={a.shape!r}")
        return np.ascontiguousarray(a.reshape(-1)[: w * h]).reshape(h, w).copy()
    if fourcc not in PACKED_YUV:
        raise ValueError(f"fourcc must be one of {sorted(PACKED_YUV) + sorted(PLANE_GRAY)}, "
                         f"got fourcc={fourcc!r}")
    if a.size < 2 * w * h:
        raise ValueError(f"{fourcc} buffer must hold {2 * w * h} bytes ({w}x{h}x2), got "
                         f"raw.shape={a.shape!r}")
    packed = np.ascontiguousarray(a.reshape(-1)[: 2 * w * h]).reshape(h, w, 2)
    code = cv2.COLOR_YUV2GRAY_UYVY if PACKED_YUV[fourcc] else cv2.COLOR_YUV2GRAY_YUYV
    y = cv2.cvtColor(packed, code)
    return cv2.LUT(y, yuv_luma_table(), dst=y)


def to_gray_frame(image: np.ndarray) -> np.ndarray:
    """A decoded frame in gray: BGR (h, w, 3) and BGRA (h, w, 4) by ``cv2.cvtColor``
    (the pipeline's own conversion, so the pipeline's result is unchanged), (h, w, 1)
    squeezed; a gray (h, w) frame is returned as it is."""
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] == 1:
        return np.ascontiguousarray(image[:, :, 0])
    if image.ndim == 3 and image.shape[2] in (3, 4):
        code = cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        return cv2.cvtColor(image, code)
    raise ValueError(f"image must be (h,w), (h,w,1), (h,w,3) or (h,w,4), got shape={image.shape!r}")
