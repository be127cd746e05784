"""Windows of T frames and their encodings (device/pi/models/window.py)."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from device.pi.models.window import ENCODED_BOUND, RollingWindow, WindowTail, encode_vectors

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



@given(st.lists(st.tuples(arrays(np.float64, (4, 2), elements=values),
                          arrays(np.float64, 6, elements=values), st.booleans()),
                min_size=1, max_size=8), st.integers(1, 4))
@settings(max_examples=80, deadline=None)
def test_the_window_encodes_as_encode_vectors_does_on_its_frames(pushes, T):
    """Whatever was pushed (NaN, inf, huge, a clear in between), the window's vectors
    encoding is encode_vectors of the frames it holds, finite and within ENCODED_BOUND."""
    w = RollingWindow(T, 4)
    with np.errstate(over="ignore", invalid="ignore"):       # float32 casts of huge values
        for v, imu, clear in pushes:
            if clear:
                w.clear()
            w.push(vectors=v, imu=imu)
            for with_imu in (False, True):
                x = w.encode("vectors", with_imu=with_imu)
                want = encode_vectors(w.vectors, w.imu if with_imu else None)
                assert x.dtype == want.dtype and np.array_equal(x, want)
                assert np.isfinite(x).all() and np.abs(x).max() <= ENCODED_BOUND


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
