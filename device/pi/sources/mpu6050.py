"""The MPU6050 driver on smbus2, in the style of micropython-lib's IMU drivers.

The bus is injected (anything with smbus2's ``read_byte_data`` / ``write_byte_data`` /
``read_i2c_block_data``: a real ``smbus2.SMBus`` or
``device.sim.fake_mpu6050.FakeMPU6050``), registers are named constants, and reads go
into a scratch buffer::

    imu = MPU6050(smbus2.SMBus(1), address=0x68, rate_hz=200, accel_g=4, gyro_dps=500, dlpf=3)
    values, faults = imu.read()      # float32 (6,): ax, ay, az [g], gx, gy, gz [deg/s]

* Start-up checks WHO_AM_I before writing anything: 0x68 is a genuine part; the
  known clones (0x70, 0x72, 0x98) are accepted with a ``warnings.warn``; anything
  else raises ``IMUError`` naming the address and the value read. A device that
  does not answer at start-up also raises ``IMUError`` (naming the address).
  It then wakes the chip (PWR_MGMT_1 = PLL with X-gyro clock, SLEEP cleared;
  PWR_MGMT_2 = 0), sets SMPLRT_DIV, CONFIG (DLPF_CFG), GYRO_CONFIG (FS_SEL) and
  ACCEL_CONFIG (AFS_SEL), and reads the four configuration registers back.
* A read is one 14-byte burst from ACCEL_XOUT_H (0x3B), scaled to g, deg/s and
  degrees C (``temp_c``).
* Faults: ``read()`` never raises. A failed transaction (``OSError``) is retried
  ``retries`` times at once; if the read still fails (or the bus misbehaves in
  another way, e.g. a short block; ``last_error`` keeps the text), the last good
  values (zeros before the first) are returned with ``FAULT_STALE |
  FAULT_OFFLINE`` set and the device is re-initialised
  (WHO_AM_I, wake, configure) on a later ``read()``, with a back-off that doubles
  from ``backoff_s`` up to ``backoff_max_s`` while it keeps failing, so a dead bus
  costs nothing on most frames. The first good read clears the bits by itself.
  Every ``check_s`` seconds PWR_MGMT_1 is read: a chip found asleep (it reset after
  a brown-out) is re-initialised. An axis at the end of its range sets
  ``FAULT_SATURATED`` (the value is the full-scale value, finite).
"""

from __future__ import annotations

import errno
import struct
import time
import warnings
from typing import Callable

import numpy as np

from device.pi.sources.options import opt_choice, opt_int_in, opt_positive
from device.errors import TacfootError

__all__ = [
    "IMUError",
    "MPU6050",
    "IMUUnavailable",
    "sample_rate_divider",
    "fault_names",
    "FAULT_STALE",
    "FAULT_OFFLINE",
    "FAULT_SATURATED",
    "FAULT_ENDED",
    "FAULT_NAMES",
    "ACCEL_RANGES_G",
    "GYRO_RANGES_DPS",
]

# ---------------------------------------------------------------- registers
# MPU-6000/6050 Register Map and Descriptions, rev 4.2
SMPLRT_DIV = 0x19
CONFIG = 0x1A
GYRO_CONFIG = 0x1B
ACCEL_CONFIG = 0x1C
ACCEL_XOUT_H = 0x3B          # first of 14 data bytes: accel xyz, temp, gyro xyz
PWR_MGMT_1 = 0x6B
PWR_MGMT_2 = 0x6C
WHO_AM_I = 0x75

DATA_LEN = 14
SLEEP = 0x40                 # PWR_MGMT_1 bit 6
CLKSEL_PLL_XGYRO = 0x01      # PWR_MGMT_1 CLKSEL: PLL with the X-gyro reference
FS_SHIFT = 3                 # FS_SEL / AFS_SEL are bits 4:3

WHO_AM_I_MPU6050 = 0x68
WHO_AM_I_CLONES = (0x70, 0x72, 0x98)

ACCEL_RANGES_G = (2, 4, 8, 16)                  # AFS_SEL 0..3
ACCEL_LSB_PER_G = (16384.0, 8192.0, 4096.0, 2048.0)
GYRO_RANGES_DPS = (250, 500, 1000, 2000)        # FS_SEL 0..3
GYRO_LSB_PER_DPS = (131.0, 65.5, 32.8, 16.4)
TEMP_LSB_PER_C = 340.0
TEMP_OFFSET_C = 36.53
GYRO_RATE_DLPF_OFF_HZ = 8000.0                  # DLPF_CFG 0 (or 7)
GYRO_RATE_DLPF_ON_HZ = 1000.0                   # DLPF_CFG 1..6
RAW_MIN, RAW_MAX = -32768, 32767

# ---------------------------------------------------------------- fault bits
FAULT_STALE = 0x01       # values are not fresh from the sensor (last good, or zeros)
FAULT_OFFLINE = 0x02     # the device failed and waits to be re-initialised
FAULT_SATURATED = 0x04   # an axis reads the end of its range
FAULT_ENDED = 0x08       # a file source without loop is past its last row (held)
FAULT_NAMES = {
    FAULT_STALE: "imu_stale",
    FAULT_OFFLINE: "imu_offline",
    FAULT_SATURATED: "imu_saturated",
    FAULT_ENDED: "imu_ended",
}


def fault_names(bits: int) -> list[str]:
    """Names of the IMU fault bits set in ``bits`` (unknown bits as ``bit<n>``)."""
    out = []
    for n in range(32):
        b = 1 << n
        if bits & b:
            out.append(FAULT_NAMES.get(b, f"bit{n}"))
    return out


class IMUError(TacfootError, RuntimeError):
    """The IMU cannot be used: wrong device, nothing answering, bad recording."""


class IMUUnavailable(IMUError):
    """Nothing answers (no I2C bus node, no acknowledge): a hardware state that may
    pass (a loose cable, a bus still coming up), unlike a wrong device."""


# ---------------------------------------------------------------- validation
def sample_rate_divider(rate_hz: float, dlpf: int) -> tuple[int, float]:
    """SMPLRT_DIV for ``rate_hz`` with DLPF_CFG ``dlpf``, and the rate it gives."""
    base = GYRO_RATE_DLPF_OFF_HZ if dlpf in (0, 7) else GYRO_RATE_DLPF_ON_HZ
    div = int(round(base / rate_hz)) - 1
    if not 0 <= div <= 255:
        lo, hi = base / 256, base
        raise ValueError(f"rate_hz must be in [{lo:g}, {hi:g}] with dlpf={dlpf}, got {rate_hz!r}")
    return div, base / (1 + div)


# ---------------------------------------------------------------- driver
class MPU6050:
    """MPU6050 on an smbus2-style ``bus`` at ``address``. See the module docstring.

    Parameters
    ----------
    bus : smbus2.SMBus or a stand-in with the same byte/block methods.
    address : 7-bit I2C address (0x68, or 0x69 with AD0 high).
    rate_hz : output data rate (sets SMPLRT_DIV; the achieved rate is ``rate_hz``).
    accel_g : accelerometer full scale, one of 2, 4, 8, 16.
    gyro_dps : gyro full scale, one of 250, 500, 1000, 2000.
    dlpf : DLPF_CFG 0..6 (0: 260 Hz, 3: 44 Hz, 6: 5 Hz accel bandwidth).
    retries : immediate retries of a failed transaction before it counts as a fault.
    backoff_s, backoff_max_s : re-init back-off, doubling while failures go on.
    check_s : how often PWR_MGMT_1 is checked for a chip that reset itself.
    clock : seconds (default ``time.monotonic``), for the back-off and the check.
    """

    def __init__(self, bus, address: int = 0x68, *, rate_hz: float = 200.0, accel_g: int = 4,
                 gyro_dps: int = 500, dlpf: int = 3, retries: int = 2, backoff_s: float = 0.05,
                 backoff_max_s: float = 2.0, check_s: float = 1.0,
                 clock: Callable[[], float] = time.monotonic):
        self.bus = bus
        self.address = opt_int_in("address", address, 0x00, 0x7F)
        self.dlpf = opt_int_in("dlpf", dlpf, 0, 6)
        self.afs_sel = opt_choice("accel_g", accel_g, ACCEL_RANGES_G)
        self.fs_sel = opt_choice("gyro_dps", gyro_dps, GYRO_RANGES_DPS)
        self.divider, self.rate_hz = sample_rate_divider(opt_positive("rate_hz", rate_hz), self.dlpf)
        self.retries = opt_int_in("retries", retries, 0, 100)
        self.backoff_s = opt_positive("backoff_s", backoff_s)
        self.backoff_max_s = max(self.backoff_s, opt_positive("backoff_max_s", backoff_max_s))
        self.check_s = opt_positive("check_s", check_s)
        if not callable(clock):
            raise ValueError(f"clock must be callable, got {clock!r}")
        self._clock = clock
        self.accel_g = ACCEL_RANGES_G[self.afs_sel]
        self.gyro_dps = GYRO_RANGES_DPS[self.fs_sel]
        self.accel_lsb_per_g = ACCEL_LSB_PER_G[self.afs_sel]
        self.gyro_lsb_per_dps = GYRO_LSB_PER_DPS[self.fs_sel]

        # scratch: the burst lands in _buf; _raw is a big-endian int16 view of it
        self._buf = bytearray(DATA_LEN)
        self._raw = np.frombuffer(self._buf, dtype=">i2")
        self._raw_acc = self._raw[0:3]
        self._raw_gyr = self._raw[4:7]
        self.values = np.zeros(6, dtype=np.float32)
        self._val_acc = self.values[0:3]
        self._val_gyr = self.values[3:6]
        self._acc_scale = 1.0 / self.accel_lsb_per_g
        self._gyr_scale = 1.0 / self.gyro_lsb_per_dps

        self.temp_c = 0.0
        self.faults = 0
        self.who_am_i = None
        self.errors = 0          # OSErrors seen, retried ones included
        self.fault_count = 0     # reads that returned stale values
        self.reinit_count = 0    # successful re-initialisations after start-up
        self.last_error = ""     # the last failure, for status reports
        self._online = False
        self._backoff = self.backoff_s
        self._next_init_t = 0.0
        self._next_check_t = 0.0
        try:
            self.init()
        except OSError as e:
            raise IMUUnavailable(f"no MPU6050 answering at address 0x{self.address:02x}: {e}") from e

    # ------------------------------------------------------------ bus helpers
    def _xfer(self, fn, *args):
        """One transaction with ``retries`` immediate retries; re-raises the last OSError."""
        for attempt in range(self.retries + 1):
            try:
                return fn(self.address, *args)
            except OSError:
                self.errors += 1
                if attempt == self.retries:
                    raise

    def _write(self, reg: int, value: int) -> None:
        self._xfer(self.bus.write_byte_data, reg, value)

    def _read_byte(self, reg: int) -> int:
        return int(self._xfer(self.bus.read_byte_data, reg))

    # ------------------------------------------------------------ start-up
    def init(self) -> None:
        """Check WHO_AM_I, wake the chip and configure it. Raises ``OSError`` on a bus
        error and ``IMUError`` for a device that is not an MPU6050."""
        who = self._read_byte(WHO_AM_I)
        if who != WHO_AM_I_MPU6050:
            if who in WHO_AM_I_CLONES:
                if self.who_am_i != who:
                    warnings.warn(f"MPU6050 at address 0x{self.address:02x} answers WHO_AM_I 0x{who:02x}, "
                                  f"a known clone; using it as an MPU6050", RuntimeWarning, stacklevel=3)
            else:
                raise IMUError(f"device at address 0x{self.address:02x} is not an MPU6050: WHO_AM_I reads "
                               f"0x{who:02x}, expected 0x68 (or a clone: 0x70, 0x72, 0x98)")
        self.who_am_i = who
        self._write(PWR_MGMT_1, CLKSEL_PLL_XGYRO)          # wake: SLEEP cleared
        self._write(PWR_MGMT_2, 0x00)                      # no axis in standby
        self._write(SMPLRT_DIV, self.divider)
        self._write(CONFIG, self.dlpf)
        self._write(GYRO_CONFIG, self.fs_sel << FS_SHIFT)
        self._write(ACCEL_CONFIG, self.afs_sel << FS_SHIFT)
        got = self._xfer(self.bus.read_i2c_block_data, SMPLRT_DIV, 4)
        want = [self.divider, self.dlpf, self.fs_sel << FS_SHIFT, self.afs_sel << FS_SHIFT]
        if [int(b) & m for b, m in zip(got, (0xFF, 0x07, 0x18, 0x18))] != want:
            raise OSError(errno.EIO, f"MPU6050 at 0x{self.address:02x}: configuration read back as "
                                     f"{list(got)}, wrote {want}")
        self._online = True
        self._next_check_t = self._clock() + self.check_s

    @property
    def online(self) -> bool:
        return self._online

    # ------------------------------------------------------------ reading
    def _fail(self, exc: BaseException, now: float) -> None:
        self.last_error = f"{type(exc).__name__}: {exc}"
        self._go_offline(now)

    def _go_offline(self, now: float) -> None:
        self._online = False
        self._next_init_t = now + self._backoff
        self._backoff = min(self._backoff * 2.0, self.backoff_max_s)

    def read(self, out: np.ndarray | None = None) -> tuple[np.ndarray, int]:
        """``(values, faults)``: float32 (6,) ax, ay, az [g], gx, gy, gz [deg/s] and the
        fault bits. Never raises. ``values`` is ``self.values`` (overwritten by the
        next read) unless ``out`` is given."""
        now = self._clock()
        if not self._online and now >= self._next_init_t:
            try:
                self.init()
                self.reinit_count += 1
            except Exception as e:          # OSError, IMUError, or a bus gone wrong
                self._fail(e, now)
        fresh = False
        if self._online:
            try:
                data = self._xfer(self.bus.read_i2c_block_data, ACCEL_XOUT_H, DATA_LEN)
                if len(data) != DATA_LEN:
                    raise OSError(errno.EIO, f"short read: {len(data)} of {DATA_LEN} bytes")
                self._buf[:] = bytes(data)
                fresh = True
            except Exception as e:
                self._fail(e, now)
        if fresh:
            raw = self._raw
            np.multiply(self._raw_acc, self._acc_scale, out=self._val_acc)
            np.multiply(self._raw_gyr, self._gyr_scale, out=self._val_gyr)
            self.temp_c = float(raw[3]) / TEMP_LSB_PER_C + TEMP_OFFSET_C
            sat = (int(self._raw_acc.min()) == RAW_MIN or int(self._raw_acc.max()) == RAW_MAX
                   or int(self._raw_gyr.min()) == RAW_MIN or int(self._raw_gyr.max()) == RAW_MAX)
            self.faults = FAULT_SATURATED if sat else 0
            self._backoff = self.backoff_s
            if now >= self._next_check_t:
                self._health_check(now)
        else:
            self.faults = FAULT_STALE | FAULT_OFFLINE
            self.fault_count += 1
        if out is not None:
            out[...] = self.values
            return out, self.faults
        return self.values, self.faults

    def _health_check(self, now: float) -> None:
        """A chip that reset itself (brown-out) reads SLEEP again: re-initialise it."""
        self._next_check_t = now + self.check_s
        try:
            if self._read_byte(PWR_MGMT_1) & SLEEP:
                self.init()
                self.reinit_count += 1
        except Exception as e:
            self._fail(e, now)

    def decode(self, raw14) -> tuple[np.ndarray, float]:
        """Scale 14 raw data bytes (as read from 0x3B) with this driver's ranges:
        (float32 (6,) values, temp_c). For tests and offline use."""
        b = bytes(raw14)
        if len(b) != DATA_LEN:
            raise ValueError(f"raw14 must be {DATA_LEN} bytes, got {len(b)}")
        ax, ay, az, t, gx, gy, gz = struct.unpack(">7h", b)
        v = np.array([ax * self._acc_scale, ay * self._acc_scale, az * self._acc_scale,
                      gx * self._gyr_scale, gy * self._gyr_scale, gz * self._gyr_scale], dtype=np.float32)
        return v, t / TEMP_LSB_PER_C + TEMP_OFFSET_C

    def close(self) -> None:
        close = getattr(self.bus, "close", None)
        if close is not None:
            close()

    def __repr__(self) -> str:
        return (f"MPU6050(address=0x{self.address:02x}, rate_hz={self.rate_hz:g}, accel_g={self.accel_g}, "
                f"gyro_dps={self.gyro_dps}, dlpf={self.dlpf}, online={self._online})")
