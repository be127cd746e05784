"""Windows of T frames and their encodings (device/pi/models/window.py)."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from device.pi.models.window import (ENCODED_BOUND, IMU_CLIP, VECTOR_CLIP_PX, VECTOR_STEP_PX,
                                     RollingWindow, WindowTail, encode_frames, encode_grids,
                                     encode_vectors)

values = st.floats(allow_nan=True, allow_infinity=True, width=64)


def test_rolling_window_encodes_once_per_push_and_never_serves_a_stale_input():
    """Models sharing a window read one encoding per frame; a push or clear drops it,
    and the shared array is read-only so no model can alter another's input."""
    w = RollingWindow(2, 3)
    rng = np.random.default_rng(0)
    for _ in range(2):
        w.push(vectors=rng.normal(size=(3, 2)), imu=rng.normal(size=6))
    a = w.encode("vectors", with_imu=True)
    assert w.encode("vectors", with_imu=True) is a
    assert not a.flags.writeable
    with pytest.raises(ValueError):
        a[0, 0] = 1.0
    assert w.encode("vectors") is not a and w.encode("vectors").shape[1] == a.shape[1] - 12
    v_new = rng.normal(size=(3, 2))
    w.push(vectors=v_new, imu=np.zeros(6))
    b = w.encode("vectors", with_imu=True)
    assert b is not a
    np.testing.assert_array_equal(b, encode_vectors(w.vectors, w.imu))
    w.clear()
    assert w.encode("vectors", with_imu=True) is not b



def _oracle(a, clip, step=None):
    """An encoding worked out in float64 apart from the window's own helpers: NaN/inf
    -> 0, clipped to +-clip, rounded to ``step``."""
    a = np.nan_to_num(np.asarray(a, np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    a = np.clip(a, -clip, clip)
    return a if step is None else np.round(a / step) * step


@given(st.lists(st.tuples(arrays(np.float64, (4, 2), elements=values),
                          arrays(np.float64, 6, elements=values), st.booleans()),
                min_size=1, max_size=8), st.integers(1, 4))
@settings(max_examples=80, deadline=None)
def test_the_window_encodes_its_newest_frames_clipped_and_quantised(pushes, T):
    """Whatever was pushed (NaN, inf, huge, a clear in between), the window's vectors
    encoding is the newest T pushes (zeros before them) with NaN/inf -> 0, clipped to
    VECTOR_CLIP_PX / IMU_CLIP *before* any float32 cast, rounded to VECTOR_STEP_PX."""
    w = RollingWindow(T, 4)
    held: list = []
    for v, imu, clear in pushes:
        if clear:
            w.clear()
        w.push(vectors=v, imu=imu)
        held = (held + [(v, imu)])[-T:]
        rows_v = [np.zeros(8)] * (T - len(held)) + [
            _oracle(x, VECTOR_CLIP_PX, VECTOR_STEP_PX).reshape(-1) for x, _ in held]
        rows_i = [np.zeros(6)] * (T - len(held)) + [_oracle(m, IMU_CLIP) for _, m in held]
        want = np.concatenate(rows_v)
        x = w.encode("vectors")
        assert x.dtype == np.float32 and x.shape == (1, 8 * T)
        np.testing.assert_allclose(x[0], want, rtol=1e-6, atol=1e-6)
        xi = w.encode("vectors", with_imu=True)
        np.testing.assert_allclose(xi[0], np.concatenate([want] + rows_i), rtol=1e-6, atol=1e-6)
        assert np.isfinite(xi).all() and np.abs(xi).max() <= ENCODED_BOUND


def test_values_beyond_float32_or_uint8_clip_or_saturate_and_never_wrap():
    """1e39 px encodes as the VECTOR_CLIP_PX clip (not float32's inf -> 0); a frame
    value of 300 is 255 (not 300 - 256 = 44); NaN frames encode as 0, not NaN."""
    w = RollingWindow(1, 2, grid_n=2, frame_size=4)
    w.push(vectors=np.array([[1e39, -1e39], [np.nan, 3.1]]), imu=np.full(6, 1e39),
           grid=np.full((2, 2), 7.0), frame=np.full((4, 4), 300))
    np.testing.assert_array_equal(w.encode("vectors")[0], [64.0, -64.0, 0.0, 3.0])
    np.testing.assert_array_equal(w.encode("vectors", with_imu=True)[0, 4:], IMU_CLIP)
    assert (w.frames == 255).all() and (w.grids == 1.0).all()
    w.push(frame=np.full((4, 4), -5.0), vectors=None)        # a missing part is 0, not 1
    assert (w.frames == 0).all() and (w.vectors == 0).all() and (w.imu == 0).all()
    np.testing.assert_array_equal(encode_vectors(np.full((1, 1, 2), 1e39)), [[64.0, 64.0]])
    f = encode_frames(np.array([[[np.nan, np.inf, 300.0, -1.0, 127.5]]]))
    np.testing.assert_allclose(f.ravel(), [0.0, 0.0, 1.0, 0.0, 0.5])
    np.testing.assert_array_equal(encode_frames(np.full((1, 1, 1), 300, np.uint16)), [[[[1.0]]]])


def test_the_grid_encoding_holds_the_maps_then_their_frame_to_frame_change():
    g = np.zeros((2, 2, 2))
    g[1, 0, 1] = 0.5                       # the change appears in frame 1: +0.5
    x = encode_grids(g)[0]
    np.testing.assert_array_equal(x[:8], g.reshape(-1))
    np.testing.assert_array_equal(x[8:], [0, 0, 0, 0, 0, 0.5, 0, 0])


def test_a_tail_reads_as_a_window_of_its_own_T():
    """A WindowTail of T over a longer window encodes, fills and clears as a
    RollingWindow of T pushed the same frames would."""
    rng = np.random.default_rng(2)
    long, short = RollingWindow(5, 4), RollingWindow(2, 4)
    tail = WindowTail(long, 2)
    for i in range(7):
        if i == 4:
            tail.clear()
            short.clear()
            assert not long.full
        parts = {"vectors": rng.normal(0, 3, (4, 2)), "imu": rng.normal(0, 1, 6),
                 "grid": rng.random((8, 8))}
        long.push(**parts)
        short.push(**parts)
        assert tail.full == short.full
        for layout, with_imu in (("vectors", False), ("vectors", True), ("grids", False)):
            assert np.array_equal(tail.encode(layout, with_imu=with_imu),
                                  short.encode(layout, with_imu=with_imu))
        assert np.array_equal(tail.vectors, short.vectors)
    with pytest.raises(TypeError, match="read only"):
        tail.push(vectors=np.zeros((4, 2)))
    with pytest.raises(ValueError, match=r"1\.\.5"):
        WindowTail(long, 6)


def test_encode_by_layout_name_passes_the_imu_and_the_frames():
    """encode(layout, ...) is the encoder of that layout with all its parts (the IMU
    rows of the vectors layout too), and a window encodes its frames crops."""
    from device.pi.models.window import encode
    v, m = np.full((2, 3, 2), 1.0), np.full((2, 6), 0.5)
    np.testing.assert_array_equal(encode("vectors", vectors=v, imu=m),
                                  [[1.0] * 12 + [0.5] * 12])
    assert encode("vectors", vectors=v).shape == (1, 12)
    frames = np.zeros((2, 4, 4), np.uint8)
    frames[1] = 255
    np.testing.assert_array_equal(encode("frames", frames=frames), frames[None] / 255.0)
    with pytest.raises(ValueError, match="'nope'"):
        encode("nope")
    w = RollingWindow(2, 3, frame_size=4)
    w.push(frame=frames[0])
    w.push(frame=frames[1])
    np.testing.assert_array_equal(w.encode("frames"), frames[None] / 255.0)
