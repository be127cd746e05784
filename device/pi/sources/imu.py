"""The foot's IMU: an MPU6050 driver on smbus2 and the IMU sources the runtime opens.

Driver (``MPU6050``), in the style of micropython-lib's IMU drivers: the bus is
injected (anything with smbus2's ``read_byte_data`` / ``write_byte_data`` /
``read_i2c_block_data``: a real ``smbus2.SMBus`` or ``device.sim.FakeMPU6050``),
registers are named constants, and reads go into a scratch buffer::

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

Sources (``open_imu``), chosen by a source string as the camera is::

    open_imu("i2c://1/0x68?rate_hz=200&accel_g=4&gyro_dps=500&dlpf=3")  # smbus2.SMBus(1)
    open_imu("file://imu.npy?loop=0")     # (F, 6) rows, one per read()
    open_imu("sim://walk?seed=3")         # this driver over FakeMPU6050.from_scene
    open_imu("none")                      # no IMU: zeros, no faults

* ``i2c://BUS/ADDR`` (ADDR hex or decimal, default 0x68): options ``rate_hz``
  (default 200), ``accel_g`` (2/4/8/16, default 4), ``gyro_dps`` (250/500/1000/2000,
  default 500), ``dlpf`` (0..6, default 3), ``retries`` (default 2), ``backoff_s``
  (default 0.05). ``open_imu(..., bus=obj)`` uses an already open bus instead.
* ``sim://SCENE`` (a built-in scene name or a .toml path): the same options plus
  ``seed`` (default 0), ``who_am_i`` (to play a clone) and ``realtime`` (default
  false: each ``read()`` shows the scene's next frame and wraps at the end; true:
  the fake follows ``time.monotonic``). ``.bus`` is the FakeMPU6050, for injecting
  faults.
* ``file://PATH.npy``: ax, ay, az [g], gx, gy, gz [deg/s] per row, like
  roboskin/concrete_gyro.npy; options ``loop`` (default true; false holds the last
  row with ``FAULT_ENDED``) and ``rate_hz`` (informational). No temperature
  (``temp_c`` stays 0).

Every source has ``read(out=None) -> (values, faults)`` (never raises; ``values`` is a
float32 (6,) array owned by the source and overwritten by the next read unless
``out`` is given), ``temp_c``, ``faults``, ``fault_count``, ``reinit_count``,
``rate_hz``, ``source``, ``close()`` and context-manager use. Options come in the
query string or as keyword arguments (keywords win); an unknown option or a bad
value is a ``ValueError`` naming it and the source string. A recording or device
that cannot be used at open time raises ``IMUError`` naming it.
"""

from __future__ import annotations

import errno
import math
import re
import struct
import time
import warnings
from pathlib import Path
from typing import Any, Callable
from urllib.parse import parse_qsl, unquote, urlsplit

import numpy as np

__all__ = [
    "IMUError",
    "MPU6050",
    "ImuSource",
    "MPU6050Source",
    "FileImuSource",
    "NoImuSource",
    "open_imu",
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


class IMUError(RuntimeError):
    """The IMU cannot be used: wrong device, nothing answering, bad recording."""


class IMUUnavailable(IMUError):
    """Nothing answers (no I2C bus node, no acknowledge): a hardware state that may
    pass (a loose cable, a bus still coming up), unlike a wrong device."""


# ---------------------------------------------------------------- validation
# a finite number, or a ValueError naming the option (the camera's source options)
from device.pi.sources.camera import _opt_bool  # noqa: E402,F401
from device.pi.sources.camera import _opt_float as _opt_num  # noqa: E402


def _pick(name: str, value: Any, allowed: tuple) -> int:
    v = _opt_num(name, value)
    for i, a in enumerate(allowed):
        if v == a:
            return i
    raise ValueError(f"{name} must be one of {list(allowed)}, got {value!r}")


def _opt_int(name: str, value: Any, lo: int, hi: int) -> int:
    if isinstance(value, str):
        s = value.strip().lower()
        try:
            value = int(s, 16) if s.startswith("0x") else int(s, 10)
        except ValueError:
            raise ValueError(f"{name} must be an int in [{lo}, {hi}], got {value!r}") from None
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name} must be an int in [{lo}, {hi}], got {value!r}")
    if not lo <= int(value) <= hi:
        raise ValueError(f"{name} must be in [{lo}, {hi}], got {value!r}")
    return int(value)


def _opt_pos(name: str, value: Any) -> float:
    v = _opt_num(name, value)
    if v <= 0:
        raise ValueError(f"{name} must be > 0, got {value!r}")
    return v


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
        self.address = _opt_int("address", address, 0x00, 0x7F)
        self.dlpf = _opt_int("dlpf", dlpf, 0, 6)
        self.afs_sel = _pick("accel_g", accel_g, ACCEL_RANGES_G)
        self.fs_sel = _pick("gyro_dps", gyro_dps, GYRO_RANGES_DPS)
        self.divider, self.rate_hz = sample_rate_divider(_opt_pos("rate_hz", rate_hz), self.dlpf)
        self.retries = _opt_int("retries", retries, 0, 100)
        self.backoff_s = _opt_pos("backoff_s", backoff_s)
        self.backoff_max_s = max(self.backoff_s, _opt_pos("backoff_max_s", backoff_max_s))
        self.check_s = _opt_pos("check_s", check_s)
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


# ---------------------------------------------------------------- sources
class ImuSource:
    """Base class of what ``open_imu`` returns."""

    source: str = ""
    rate_hz: float | None = None

    def __init__(self) -> None:
        self.values = np.zeros(6, dtype=np.float32)
        self.temp_c = 0.0
        self.faults = 0
        self.fault_count = 0
        self.reinit_count = 0
        self.closed = False

    def read(self, out: np.ndarray | None = None) -> tuple[np.ndarray, int]:
        raise NotImplementedError

    def _ret(self, out):
        if out is not None:
            out[...] = self.values
            return out, self.faults
        return self.values, self.faults

    def close(self) -> None:
        self.closed = True

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.source!r})"


class NoImuSource(ImuSource):
    """``none``: no IMU fitted. Zeros, no faults."""

    def __init__(self, source: str = "none"):
        super().__init__()
        self.source = source

    def read(self, out=None):
        return self._ret(out)


class MPU6050Source(ImuSource):
    """The MPU6050 driver over a bus: ``i2c://`` (smbus2) or ``sim://`` (FakeMPU6050).
    For ``sim://`` each ``read()`` shows the next motion row (wrapping at the end)
    unless ``realtime`` lets the fake follow the clock. ``.driver`` and ``.bus`` are
    exposed (tests inject faults through ``.bus``)."""

    def __init__(self, driver: MPU6050, source: str, *, step_rows: bool = False):
        super().__init__()
        self.driver = driver
        self.bus = driver.bus
        self.source = source
        self.rate_hz = driver.rate_hz
        self.values = driver.values
        self._step = step_rows
        self._row = 0

    def read(self, out=None):
        if self.closed:
            self.faults = FAULT_STALE | FAULT_OFFLINE
            return self._ret(out)
        if self._step:
            self.bus.seek(self._row)
            self._row = (self._row + 1) % self.bus.n_frames
        _, self.faults = self.driver.read()
        d = self.driver
        self.temp_c, self.fault_count, self.reinit_count = d.temp_c, d.fault_count, d.reinit_count
        return self._ret(out)

    def close(self) -> None:
        if not self.closed:
            self.driver.close()
        super().close()


class RetryingImuSource(ImuSource):
    """An IMU that was not answering at start-up. Reads return zeros with
    ``imu_stale | imu_offline`` set while ``open_imu(source)`` is retried with a
    back-off that doubles from ``backoff_s`` to ``backoff_max_s``; once it opens,
    reads come from it. The runtime uses it so a missing IMU is a FAULT, not a
    refusal to start (a wrong device or a bad option still refuses)."""

    def __init__(self, source: str, first_error: BaseException, *, backoff_s: float = 0.5,
                 backoff_max_s: float = 5.0, clock=time.monotonic, opener=None):
        super().__init__()
        self.source = source
        self.last_error = str(first_error)
        self.faults = FAULT_STALE | FAULT_OFFLINE
        self._clock = clock
        self._open = opener or (lambda: open_imu(source))
        self._backoff = float(backoff_s)
        self._backoff_max = float(backoff_max_s)
        self._next_t = clock() + self._backoff
        self.inner: ImuSource | None = None

    def read(self, out=None):
        if self.inner is not None:
            return self.inner.read(out)
        now = self._clock()
        if now >= self._next_t:
            try:
                self.inner = self._open()
                self.reinit_count += 1
                return self.inner.read(out)
            except IMUUnavailable as e:
                self.last_error = str(e)
            except Exception as e:     # a wrong device appearing later: keep faulting
                self.last_error = f"{type(e).__name__}: {e}"
            self._backoff = min(self._backoff * 2.0, self._backoff_max)
            self._next_t = now + self._backoff
        self.fault_count += 1
        return self._ret(out)

    def close(self) -> None:
        if self.inner is not None:
            self.inner.close()
        super().close()


class FileImuSource(ImuSource):
    """``file://imu.npy``: an (F, 6) recording (ax, ay, az g, gx, gy, gz deg/s), one
    row per ``read()``. ``loop`` (default true) wraps at the end; without it the
    last row is held with ``FAULT_ENDED``. There is no temperature (``temp_c`` 0)."""

    def __init__(self, path, *, loop: bool = True, rate_hz: float | None = None, source: str | None = None):
        super().__init__()
        path = Path(path)
        self.source = source if source is not None else f"file://{path}"
        try:
            data = np.load(path, allow_pickle=False)
        except FileNotFoundError:
            raise IMUError(f"IMU recording not found: {str(path)!r} (source {self.source!r})") from None
        except (OSError, ValueError) as e:
            raise IMUError(f"cannot read IMU recording {str(path)!r} (source {self.source!r}): {e}") from None
        if data.ndim != 2 or data.shape[1] != 6 or data.shape[0] < 1 or data.dtype.kind not in "iuf":
            raise IMUError(f"IMU recording {str(path)!r} must be a numeric (F, 6) array, "
                           f"got {data.dtype}{data.shape}")
        bad = ~np.isfinite(data)
        if bad.any():
            r, c = np.argwhere(bad)[0]
            raise IMUError(f"IMU recording {str(path)!r} has a non-finite value at [{r}, {c}]: {data[r, c]!r}")
        self.data = np.ascontiguousarray(data, dtype=np.float32)
        self.n_frames = int(self.data.shape[0])
        self.loop = loop
        self.rate_hz = rate_hz
        self.index = 0      # row the next read() returns

    def read(self, out=None):
        if self.index >= self.n_frames:
            if self.loop:
                self.index = 0
            else:
                self.faults = FAULT_ENDED
                return self._ret(out)
        np.copyto(self.values, self.data[self.index])
        self.index += 1
        self.faults = 0
        return self._ret(out)


_DRIVER_OPTS = {
    "rate_hz": _opt_pos,
    "accel_g": lambda n, v: ACCEL_RANGES_G[_pick(n, v, ACCEL_RANGES_G)],
    "gyro_dps": lambda n, v: GYRO_RANGES_DPS[_pick(n, v, GYRO_RANGES_DPS)],
    "dlpf": lambda n, v: _opt_int(n, v, 0, 6),
    "retries": lambda n, v: _opt_int(n, v, 0, 100),
    "backoff_s": _opt_pos,
}
_SIM_OPTS = {**_DRIVER_OPTS, "seed": lambda n, v: _opt_int(n, v, 0, 2**63 - 1),
             "realtime": _opt_bool, "who_am_i": lambda n, v: _opt_int(n, v, 0, 0xFF)}
_FILE_OPTS = {"loop": _opt_bool, "rate_hz": _opt_pos}


def _options(source: str, query: str, kwargs: dict, spec: dict) -> dict:
    merged = {**dict(parse_qsl(query, keep_blank_values=True)), **kwargs}
    unknown = sorted(set(merged) - set(spec))
    if unknown:
        raise ValueError(f"unknown option {unknown[0]!r} for IMU source {source!r}; known: {sorted(spec)}")
    out = {}
    for k, v in merged.items():
        try:
            out[k] = spec[k](k, v)
        except ValueError as e:
            raise ValueError(f"{e} (IMU source {source!r})") from None
    return out


def _driver(bus, address, source, opts, **extra) -> MPU6050:
    try:
        return MPU6050(bus, address, **opts, **extra)
    except ValueError as e:
        raise ValueError(f"{e} (IMU source {source!r})") from None


def open_imu(source: str, *, bus=None, **opts) -> ImuSource:
    """Open the IMU named by ``source`` (see the module docstring). ``bus`` replaces
    the ``smbus2.SMBus`` an ``i2c://`` source would open (tests, shared buses)."""
    if not isinstance(source, str) or not source.strip():
        raise ValueError(f"IMU source must be a non-empty string such as 'i2c://1/0x68', got {source!r}")
    s = source.strip()
    if s.lower() == "none":
        if opts:
            raise ValueError(f"IMU source 'none' takes no options, got {sorted(opts)}")
        return NoImuSource(s)
    if "://" not in s:
        raise ValueError(f"unknown IMU source {source!r}; use i2c://BUS/ADDR, file://PATH.npy, sim://SCENE or none")
    scheme, rest = s.split("://", 1)
    scheme = scheme.lower()
    if scheme == "i2c":
        parts = urlsplit(s)
        m = re.fullmatch(r"(\d+)", parts.netloc or "")
        addr_s = parts.path.strip("/") or "0x68"
        if m is None or not re.fullmatch(r"0[xX][0-9a-fA-F]{1,2}|\d{1,3}", addr_s):
            raise ValueError(f"bad IMU source {source!r}: expected i2c://BUS/ADDR such as i2c://1/0x68")
        bus_no = int(m.group(1))
        address = int(addr_s, 0)
        if not 0x08 <= address <= 0x77:
            raise ValueError(f"bad IMU source {source!r}: address 0x{address:02x} is outside 0x08..0x77")
        o = _options(source, parts.query, opts, _DRIVER_OPTS)
        own_bus = bus is None
        if own_bus:
            try:
                import smbus2
                bus = smbus2.SMBus(bus_no)
            except (OSError, ImportError) as e:
                raise IMUUnavailable(f"cannot open I2C bus {bus_no} (/dev/i2c-{bus_no}) for IMU source "
                               f"{source!r}: {e}") from None
        try:
            drv = _driver(bus, address, source, o)
        except IMUError as e:
            if own_bus:
                bus.close()
            raise type(e)(f"{e} (IMU source {source!r}, I2C bus {bus_no})") from None
        return MPU6050Source(drv, source)
    if scheme == "sim":
        parts = urlsplit(s)
        scene = unquote(parts.netloc + parts.path)
        if not scene:
            raise ValueError(f"bad IMU source {source!r}: sim:// needs a scene name or path, e.g. sim://walk")
        o = _options(source, parts.query, opts, _SIM_OPTS)
        seed = o.pop("seed", 0)
        realtime = o.pop("realtime", False)
        fake_kw = {"who_am_i": o.pop("who_am_i")} if "who_am_i" in o else {}
        from device.sim.fake_mpu6050 import FakeMPU6050     # lazy: the Pi never needs the simulator
        try:
            fake = FakeMPU6050.from_scene(scene, seed=seed, clock=time.monotonic if realtime else None, **fake_kw)
        except (FileNotFoundError, ValueError) as e:       # ConfigError is a ValueError
            raise ValueError(f"bad IMU source {source!r}: {e}") from None
        drv = _driver(fake, fake.address, source, o)
        return MPU6050Source(drv, source, step_rows=not realtime)
    if scheme == "file":
        path_str, query = rest, ""
        if "?" in rest and not Path(unquote(rest)).exists():
            path_str, query = rest.split("?", 1)
        path_str = unquote(path_str)
        if not path_str:
            raise ValueError(f"bad IMU source {source!r}: file:// needs a path to an (F, 6) .npy")
        o = _options(source, query, opts, _FILE_OPTS)
        return FileImuSource(path_str, source=source, **o)
    raise ValueError(f"unknown IMU source scheme {scheme!r} in {source!r}; use i2c://, file://, sim:// or none")
