"""Gray straight from a source (device/pi/sources/luma.py): the luma plane of raw V4L2
buffers, checked on synthetic YUYV / UYVY / GREY buffers against OpenCV's colour path
(there is no camera here)."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from device.pi.sources.luma import luma_plane, to_gray_frame, yuv_luma_table


def yuyv_buffer(y: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(h, w, 2) YUYV bytes from luma (h, w) and chroma (h, w/2)."""
    h, w = y.shape
    buf = np.empty((h, w, 2), np.uint8)
    buf[:, :, 0] = y
    buf[:, 0::2, 1] = u
    buf[:, 1::2, 1] = v
    return buf


def colour_path_gray(yuyv: np.ndarray) -> np.ndarray:
    """What the pipeline would see from OpenCV's default capture: decode to BGR, then gray."""
    return cv2.cvtColor(cv2.cvtColor(yuyv, cv2.COLOR_YUV2BGR_YUYV), cv2.COLOR_BGR2GRAY)


def test_table_is_the_colour_paths_gray_of_neutral_pixels():
    t = yuv_luma_table()
    assert t.dtype == np.uint8 and t.shape == (256,)
    assert t[16] == 0 and t[235] == 255          # video range expanded, as OpenCV decodes it
    assert np.all(np.diff(t.astype(int)) >= 0)   # monotonic: the threshold keeps its order
    y = np.arange(256, dtype=np.uint8).reshape(8, 32)
    buf = yuyv_buffer(y, np.full((8, 16), 128), np.full((8, 16), 128))
    np.testing.assert_array_equal(luma_plane(buf, 32, 8, "YUYV"), colour_path_gray(buf))


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31), h=st.integers(1, 40), half_w=st.integers(1, 40),
       chroma=st.integers(0, 12))
def test_yuyv_luma_is_the_colour_paths_gray_within_rounding(seed, h, half_w, chroma):
    """Mild chroma, luma where no decoded channel clips (Y 40..200): at most one gray
    level from decoding the colour and converting it back. (Where the colour path clips
    a channel at 0 or 255 it loses the chroma's cancellation and differs by more.)"""
    rng = np.random.default_rng(seed)
    w = 2 * half_w
    y = rng.integers(40, 201, (h, w))
    u = 128 + rng.integers(-chroma, chroma + 1, (h, half_w))
    v = 128 + rng.integers(-chroma, chroma + 1, (h, half_w))
    buf = yuyv_buffer(y, u, v)
    got = luma_plane(buf.reshape(1, -1), w, h, "YUYV")   # as OpenCV hands a raw buffer over
    assert got.shape == (h, w) and got.dtype == np.uint8 and got.flags.c_contiguous
    assert np.abs(got.astype(int) - colour_path_gray(buf)).max() <= 1
    uyvy = np.ascontiguousarray(buf[:, :, ::-1])           # U Y V Y: the same pixels
    np.testing.assert_array_equal(luma_plane(uyvy, w, h, "UYVY"), got)
    np.testing.assert_array_equal(luma_plane(buf.reshape(h, 2 * w), w, h, "YUY2"), got)


def test_grey_buffer_is_the_image_and_a_new_array():
    rng = np.random.default_rng(1)
    g = rng.integers(0, 256, (6, 10), dtype=np.uint8)
    raw = g.reshape(1, -1)
    out = luma_plane(raw, 10, 6, "GREY")
    np.testing.assert_array_equal(out, g)
    assert not np.shares_memory(out, raw)                  # the capture reuses its buffer
    np.testing.assert_array_equal(luma_plane(g, 10, 6, "Y800"), g)
    # the colour path replicates gray into B, G and R and converts back: the same image
    np.testing.assert_array_equal(cv2.cvtColor(cv2.cvtColor(g, cv2.COLOR_GRAY2BGR),
                                               cv2.COLOR_BGR2GRAY), out)


def test_bad_buffers_name_the_field():
    buf = np.zeros((4, 8, 2), np.uint8)
    with pytest.raises(ValueError, match="fourcc='MJPG'"):
        luma_plane(buf, 8, 4, "MJPG")
    with pytest.raises(ValueError, match=r"raw.shape=\(1, 63\)"):
        luma_plane(buf.reshape(1, -1)[:, :63], 8, 4, "YUYV")
    with pytest.raises(ValueError, match="raw.dtype=float32"):
        luma_plane(buf.astype(np.float32), 8, 4, "YUYV")
    with pytest.raises(ValueError, match="width=7"):
        luma_plane(buf, 7, 4, "YUYV")
    with pytest.raises(ValueError, match=r"raw.shape=\(3, 5\)"):
        luma_plane(np.zeros((3, 5), np.uint8), 8, 4, "GREY")


def test_to_gray_frame_is_the_pipelines_conversion():
    rng = np.random.default_rng(2)
    bgr = rng.integers(0, 256, (5, 7, 3), dtype=np.uint8)
    np.testing.assert_array_equal(to_gray_frame(bgr), cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))
    bgra = rng.integers(0, 256, (5, 7, 4), dtype=np.uint8)
    np.testing.assert_array_equal(to_gray_frame(bgra), cv2.cvtColor(bgra, cv2.COLOR_BGRA2GRAY))
    g = bgr[:, :, 0].copy()
    assert to_gray_frame(g) is g
    np.testing.assert_array_equal(to_gray_frame(g[:, :, None]), g)
    with pytest.raises(ValueError, match=r"shape=\(5, 7, 2\)"):
        to_gray_frame(bgr[:, :, :2])
