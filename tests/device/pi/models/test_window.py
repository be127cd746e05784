"""Windows of T frames and their encodings (device/pi/models/window.py)."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from device.pi.models.window import ENCODED_BOUND, RollingWindow, encode_vectors

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
