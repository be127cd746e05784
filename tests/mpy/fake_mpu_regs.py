"""A small MPU6050 register model that runs on MicroPython (and CPython), for the
machine stand-in's I2C: ``machine.I2C.devices[0x68] = FakeMPURegs()``.

It follows the same register semantics as device/sim/fake_mpu6050.py, in the
subset MicroPython runs: power-on state PWR_MGMT_1 = 0x40 (SLEEP; data reads zeros),
DEVICE_RESET (0x80) restores it, WHO_AM_I is read-only, SMPLRT_DIV / CONFIG /
GYRO_CONFIG / ACCEL_CONFIG are stored and the ranges scale the data registers
(0x3B..0x48, big-endian int16, saturating), TEMP = (temp_c - 36.53) * 340.

Test hooks: ``motion`` (ax, ay, az g, gx, gy, gz deg/s), ``temp_c``; ``fail`` (the
next n transactions raise OSError(``fail_errno``) without effect); ``stuck`` (every
transaction raises OSError(110)); ``log`` of ("r", reg, n) / ("w", reg, value...)
entries; ``transactions``.
"""

ACCEL_LSB = (16384.0, 8192.0, 4096.0, 2048.0)
GYRO_LSB = (131.0, 65.5, 32.8, 16.4)
_RO = (0x3A, 0x72, 0x73, 0x75)


def _raw(v, lsb):
    x = v * lsb
    if x >= 32767:
        return 32767
    if x <= -32768:
        return -32768
    return int(x + 0.5) if x >= 0 else -int(-x + 0.5)


class FakeMPURegs:
    def __init__(self, who_am_i=0x68):
        self.who_am_i = who_am_i
        self.regs = bytearray(256)
        self.motion = (0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
        self.temp_c = 25.0
        self.fail = 0
        self.fail_errno = 5
        self.stuck = False
        self.log = []
        self.transactions = 0
        self.reset()

    def reset(self):
        for i in range(256):
            self.regs[i] = 0
        self.regs[0x6B] = 0x40
        self.regs[0x75] = self.who_am_i

    def _begin(self):
        self.transactions += 1
        if self.stuck:
            raise OSError(110)
        if self.fail > 0:
            self.fail -= 1
            raise OSError(self.fail_errno)

    def sample(self):
        """The 14 data bytes for the current motion and configuration."""
        out = bytearray(14)
        if self.regs[0x6B] & 0x40:
            return out
        a = ACCEL_LSB[(self.regs[0x1C] >> 3) & 3]
        g = GYRO_LSB[(self.regs[0x1B] >> 3) & 3]
        m = self.motion
        vals = (_raw(m[0], a), _raw(m[1], a), _raw(m[2], a), _raw(self.temp_c - 36.53, 340.0),
                _raw(m[3], g), _raw(m[4], g), _raw(m[5], g))
        for i in range(7):
            v = vals[i] & 0xFFFF
            out[2 * i] = v >> 8
            out[2 * i + 1] = v & 0xFF
        return out

    def read(self, reg, n):
        self._begin()
        self.log.append(("r", reg, n))
        s = None
        out = bytearray(n)
        for i in range(n):
            a = (reg + i) & 0xFF
            if 0x3B <= a <= 0x48:
                if s is None:
                    s = self.sample()
                out[i] = s[a - 0x3B]
            else:
                out[i] = self.regs[a]
        return out

    def write(self, reg, data):
        self._begin()
        self.log.append(("w", reg) + tuple(data))
        for i in range(len(data)):
            a = (reg + i) & 0xFF
            v = data[i]
            if a in _RO or 0x3B <= a <= 0x60:
                continue
            if a == 0x6B and v & 0x80:
                self.reset()
                continue
            self.regs[a] = v
