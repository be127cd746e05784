"""Windows of T frames and their encodings (device/pi/models/window.py)."""
from __future__ import annotations

import numpy as np
import pytest

from device.pi.models.window import RollingWindow, encode_vectors


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

