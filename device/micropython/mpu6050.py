"""MPU6050 driver for MicroPython's machine.I2C: the twin of device/pi/sources/imu.py.

Same logic as the Pi driver, on ``readfrom_mem_into`` / ``writeto_mem``, for the
RP2040 data-collection rig. Written in the subset CPython also runs::

    from machine import I2C, Pin
    from mpu6050 import MPU6050
    imu = MPU6050(I2C(0, scl=Pin(5), sda=Pin(4), freq=400000), addr=0x68,
                  rate_hz=200, accel_g=4, gyro_dps=500, dlpf=3)
    ax, ay, az, gx, gy, gz, temp_c = imu.read()      # g, deg/s, degrees C
    if imu.faults: ...                               # FAULT_* bits of that read

* Start-up reads WHO_AM_I first. 0x68 is genuine; the known clones 0x70, 0x72 and
  0x98 are accepted and flagged (``.clone`` True, ``.who_am_i`` holds the value;
  nothing is printed, because on the rig stdout is the host link). Anything else
  raises ``MPU6050Error`` (an ``OSError``) naming the address and the value; so
  does a device that does not answer. Then: wake (PWR_MGMT_1 = PLL X-gyro clock), PWR_MGMT_2 = 0,
  SMPLRT_DIV, CONFIG (DLPF_CFG), GYRO_CONFIG, ACCEL_CONFIG, and a read-back of the
  four configuration registers.
* ``read_raw()`` is one 14-byte burst from 0x3B into a scratch buffer; on success
  it is copied to ``.buf`` (big-endian accel xyz, temp, gyro xyz: the last good
  sample) and True is returned. ``read()`` scales it to a 7-tuple.
* Faults: neither read raises. A failed transaction is retried ``retries`` times;
  if it still fails the last good sample is kept, ``faults`` gets FAULT_STALE |
  FAULT_OFFLINE, ``fault_count`` counts it, and re-initialisation is tried on a
  later read after a back-off that doubles from ``backoff_ms`` to
  ``backoff_max_ms``. Success clears the bits. Every ``check_ms`` PWR_MGMT_1 is
  read, and a chip that reset itself (SLEEP set again) is re-initialised. An axis
  at the end of its range sets FAULT_SATURATED.
* No allocation in ``read_raw()`` beyond what the I2C driver does (preallocated
  buffers; ``read()`` builds one tuple of floats).
"""

from mpcompat import const, ticks_add, ticks_diff, ticks_ms  # noqa: F401

# registers (MPU-6000/6050 Register Map rev 4.2)
SMPLRT_DIV = const(0x19)
CONFIG = const(0x1A)
GYRO_CONFIG = const(0x1B)
ACCEL_CONFIG = const(0x1C)
ACCEL_XOUT_H = const(0x3B)
PWR_MGMT_1 = const(0x6B)
PWR_MGMT_2 = const(0x6C)
WHO_AM_I = const(0x75)

DATA_LEN = const(14)
SLEEP = const(0x40)
CLKSEL_PLL_XGYRO = const(0x01)
WHO_AM_I_MPU6050 = const(0x68)
WHO_AM_I_CLONES = (0x70, 0x72, 0x98)

ACCEL_RANGES_G = (2, 4, 8, 16)
ACCEL_LSB_PER_G = (16384.0, 8192.0, 4096.0, 2048.0)
GYRO_RANGES_DPS = (250, 500, 1000, 2000)
GYRO_LSB_PER_DPS = (131.0, 65.5, 32.8, 16.4)
TEMP_LSB_PER_C = 340.0
TEMP_OFFSET_C = 36.53

# fault bits: the same values as device/pi/sources/imu.py
FAULT_STALE = const(0x01)
FAULT_OFFLINE = const(0x02)
FAULT_SATURATED = const(0x04)


class MPU6050Error(OSError):
    """Wrong device, or nothing answering, at start-up (an OSError, so a caller's
    ``except OSError`` around the constructor catches it)."""


def _index(name, value, allowed):
    for i in range(len(allowed)):
        if value == allowed[i]:
            return i
    raise ValueError("%s must be one of %s, got %r" % (name, list(allowed), value))


def _s16(b, i):
    v = (b[i] << 8) | b[i + 1]
    return v - 65536 if v & 0x8000 else v


class MPU6050:
    def __init__(self, i2c, addr=0x68, rate_hz=200, accel_g=4, gyro_dps=500, dlpf=3, retries=2,
                 backoff_ms=50, backoff_max_ms=2000, check_ms=1000, clock_ms=None):
        if not isinstance(addr, int) or isinstance(addr, bool) or not 0 <= addr <= 0x7F:
            raise ValueError("addr must be a 7-bit int, got %r" % (addr,))
        if not isinstance(dlpf, int) or isinstance(dlpf, bool) or not 0 <= dlpf <= 6:
            raise ValueError("dlpf must be an int in [0, 6], got %r" % (dlpf,))
        if not isinstance(retries, int) or isinstance(retries, bool) or not 0 <= retries <= 100:
            raise ValueError("retries must be an int in [0, 100], got %r" % (retries,))
        for name, v in (("backoff_ms", backoff_ms), ("backoff_max_ms", backoff_max_ms), ("check_ms", check_ms)):
            if not isinstance(v, int) or isinstance(v, bool) or v <= 0:
                raise ValueError("%s must be an int > 0, got %r" % (name, v))
        self.afs_sel = _index("accel_g", accel_g, ACCEL_RANGES_G)
        self.fs_sel = _index("gyro_dps", gyro_dps, GYRO_RANGES_DPS)
        base = 8000.0 if dlpf == 0 else 1000.0
        try:
            div = int(base / rate_hz + 0.5) - 1
        except (TypeError, ZeroDivisionError):
            div = -1
        if not isinstance(rate_hz, (int, float)) or isinstance(rate_hz, bool) or not 0 <= div <= 255:
            raise ValueError("rate_hz must be in [%g, %g] with dlpf=%d, got %r" % (base / 256, base, dlpf, rate_hz))
        self.i2c = i2c
        self.addr = addr
        self.dlpf = dlpf
        self.divider = div
        self.rate_hz = base / (1 + div)
        self.accel_g = ACCEL_RANGES_G[self.afs_sel]
        self.gyro_dps = GYRO_RANGES_DPS[self.fs_sel]
        self.accel_lsb_per_g = ACCEL_LSB_PER_G[self.afs_sel]
        self.gyro_lsb_per_dps = GYRO_LSB_PER_DPS[self.fs_sel]
        self.retries = retries
        self.backoff_ms = backoff_ms
        self.backoff_max_ms = max(backoff_ms, backoff_max_ms)
        self.check_ms = check_ms
        self._clock = clock_ms if clock_ms is not None else ticks_ms

        self._b1 = bytearray(1)
        self._b4 = bytearray(4)
        self._rx = bytearray(DATA_LEN)        # scratch for the burst
        self.buf = bytearray(DATA_LEN)        # last good sample, raw big-endian
        self.values = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        self.temp_c = 0.0
        self.faults = 0
        self.errors = 0          # OSErrors seen, retried ones included
        self.fault_count = 0     # reads that kept stale values
        self.reinit_count = 0    # successful re-initialisations after start-up
        self.who_am_i = -1
        self.clone = False
        self.online = False
        self._backoff = backoff_ms
        self._next_init = 0
        self._next_check = 0
        try:
            self.init()
        except MPU6050Error:
            raise
        except OSError as e:
            raise MPU6050Error("no MPU6050 answering at address 0x%02x: %s" % (addr, e))

    # -- bus helpers (retry ``retries`` times, then re-raise) ------------------------
    def _xfer(self, write, reg, buf):
        n = self.retries
        while True:
            try:
                if write:
                    self.i2c.writeto_mem(self.addr, reg, buf)
                else:
                    self.i2c.readfrom_mem_into(self.addr, reg, buf)
                return
            except OSError:
                self.errors += 1
                if n <= 0:
                    raise
                n -= 1

    def _rd(self, reg, buf):
        self._xfer(False, reg, buf)

    def _wr(self, reg, value):
        self._b1[0] = value
        self._xfer(True, reg, self._b1)

    # -- start-up -----------------------------------------------------------------
    def init(self):
        """WHO_AM_I, wake, configure, read back. OSError on a bus error,
        MPU6050Error for a device that is not an MPU6050."""
        self._rd(WHO_AM_I, self._b1)
        who = self._b1[0]
        if who != WHO_AM_I_MPU6050 and who not in WHO_AM_I_CLONES:
            raise MPU6050Error("device at address 0x%02x is not an MPU6050: WHO_AM_I reads 0x%02x, "
                               "expected 0x68 (or a clone: 0x70, 0x72, 0x98)" % (self.addr, who))
        self.who_am_i = who
        self.clone = who != WHO_AM_I_MPU6050
        self._wr(PWR_MGMT_1, CLKSEL_PLL_XGYRO)
        self._wr(PWR_MGMT_2, 0)
        self._wr(SMPLRT_DIV, self.divider)
        self._wr(CONFIG, self.dlpf)
        self._wr(GYRO_CONFIG, self.fs_sel << 3)
        self._wr(ACCEL_CONFIG, self.afs_sel << 3)
        b = self._b4
        self._rd(SMPLRT_DIV, b)
        if (b[0] != self.divider or (b[1] & 7) != self.dlpf or (b[2] & 0x18) != self.fs_sel << 3
                or (b[3] & 0x18) != self.afs_sel << 3):
            raise OSError(5)
        self.online = True
        self._next_check = ticks_add(self._clock(), self.check_ms)

    # -- reading ------------------------------------------------------------------
    def _offline(self, now):
        self.online = False
        self._next_init = ticks_add(now, self._backoff)
        self._backoff = min(self._backoff * 2, self.backoff_max_ms)

    def read_raw(self):
        """One burst into ``.buf``; True when it is fresh. Never raises."""
        now = self._clock()
        if not self.online and ticks_diff(now, self._next_init) >= 0:
            try:
                self.init()
                self.reinit_count += 1
            except (OSError, MPU6050Error):
                self._offline(now)
        if self.online:
            try:
                self._rd(ACCEL_XOUT_H, self._rx)
            except OSError:
                self._offline(now)
        if not self.online:
            self.faults = FAULT_STALE | FAULT_OFFLINE
            self.fault_count += 1
            return False
        self.buf[:] = self._rx
        self._backoff = self.backoff_ms
        self.faults = 0
        b = self.buf
        for i in (0, 2, 4, 8, 10, 12):
            v = (b[i] << 8) | b[i + 1]
            if v == 0x7FFF or v == 0x8000:
                self.faults = FAULT_SATURATED
        if ticks_diff(now, self._next_check) >= 0:
            self._next_check = ticks_add(now, self.check_ms)
            try:
                self._rd(PWR_MGMT_1, self._b1)
                if self._b1[0] & SLEEP:
                    self.init()
                    self.reinit_count += 1
            except (OSError, MPU6050Error):
                self._offline(now)
        return True

    def read(self):
        """(ax, ay, az [g], gx, gy, gz [deg/s], temp_c): the latest sample, or the
        last good one with ``faults`` set. Never raises."""
        if self.read_raw():
            b = self.buf
            a = self.accel_lsb_per_g
            g = self.gyro_lsb_per_dps
            self.temp_c = _s16(b, 6) / TEMP_LSB_PER_C + TEMP_OFFSET_C
            self.values = (_s16(b, 0) / a, _s16(b, 2) / a, _s16(b, 4) / a,
                           _s16(b, 8) / g, _s16(b, 10) / g, _s16(b, 12) / g, self.temp_c)
        return self.values
