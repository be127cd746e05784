"""Bus helpers shared by the MPU6050 driver and IMU source tests."""

from __future__ import annotations

import numpy as np

from device.sim.fake_mpu6050 import FakeMPU6050

__all__ = ["ADDR", "MOTION", "Clock", "Recorder", "fake", "tol"]

ADDR = 0x68
MOTION = np.array([
    [0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
    [0.5, -0.25, 0.98, 10.0, -20.0, 30.0],
    [-1.5, 1.25, -0.5, -100.5, 200.25, -240.0],
])


class Clock:
    def __init__(self, t=0.0):
        self.t = t

    def __call__(self):
        return self.t


class Recorder:
    """Wraps a bus and logs every transaction in order."""

    def __init__(self, bus):
        self.bus = bus
        self.log = []

    def read_byte_data(self, a, r):
        self.log.append(("rb", r))
        return self.bus.read_byte_data(a, r)

    def write_byte_data(self, a, r, v):
        self.log.append(("wb", r, v))
        return self.bus.write_byte_data(a, r, v)

    def read_i2c_block_data(self, a, r, n):
        self.log.append(("rblk", r, n))
        return self.bus.read_i2c_block_data(a, r, n)


def fake(motion=MOTION, **kw):
    kw.setdefault("clock", None)
    return FakeMPU6050(motion, 100.0, **kw)


def tol(lsb, v):
    """Half an LSB plus float32 rounding of the value."""
    return 0.5 / lsb + abs(float(v)) * 2.0 ** -23 + 1e-12
