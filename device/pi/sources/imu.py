"""The foot's IMU sources, chosen by a source string as the camera is.

The driver is :class:`device.pi.sources.mpu6050.MPU6050`.

``open_imu``::

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
  row with ``FAULT_ENDED``; when it loops, the first wrap is said once on stderr)
  and ``rate_hz`` (informational). No temperature (``temp_c`` stays 0). A value
  beyond the sensor's widest range (16 g, 2000 deg/s) is held at full scale and
  its row reads with ``FAULT_SATURATED``.

Every source has ``read(out=None) -> (values, faults)`` (never raises; ``values`` is a
float32 (6,) array owned by the source and overwritten by the next read unless
``out`` is given), ``temp_c``, ``faults``, ``fault_count``, ``reinit_count``,
``rate_hz``, ``source``, ``close()`` and context-manager use. Options come in the
query string or as keyword arguments (keywords win); an unknown option or a bad
value is a ``ValueError`` naming it and the source string. A recording or device
that cannot be used at open time raises ``IMUError`` naming it.
"""

from __future__ import annotations

import logging
import re
import time
from pathlib import Path
from urllib.parse import parse_qsl, unquote, urlsplit

import numpy as np

from device.pi.sources.mpu6050 import (ACCEL_RANGES_G, FAULT_ENDED, FAULT_OFFLINE, FAULT_SATURATED, FAULT_STALE,
                                       GYRO_RANGES_DPS, MPU6050, IMUError, IMUUnavailable)
from device.closing import Closing
from device.pi.sources.options import opt_bool, opt_choice, opt_int_in, opt_positive, parse_options
from device.errors import InputError

_log = logging.getLogger(__name__)

__all__ = ["ImuSource", "MPU6050Source", "RetryingImuSource", "FileImuSource", "NoImuSource", "open_imu",
           "FULL_SCALE"]

#: the MPU6050's widest ranges per column (ax, ay, az g; gx, gy, gz deg/s): a
#: recorded value beyond them is no reading the sensor can give
FULL_SCALE = np.array([max(ACCEL_RANGES_G)] * 3 + [max(GYRO_RANGES_DPS)] * 3, dtype=np.float64)


# ---------------------------------------------------------------- sources
class ImuSource(Closing):
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
        except EOFError:                # a zero-length or cut-short file
            raise IMUError(f"cannot read IMU recording {str(path)!r} (source {self.source!r}): "
                           f"the file is empty or cut short") from None
        except (OSError, ValueError) as e:
            raise IMUError(f"cannot read IMU recording {str(path)!r} (source {self.source!r}): {e}") from None
        if (not isinstance(data, np.ndarray) or data.ndim != 2 or data.shape[1] != 6
                or data.shape[0] < 1 or data.dtype.kind not in "iuf"):
            raise IMUError(f"IMU recording {str(path)!r} must be a numeric (F, 6) array, "
                           f"got {getattr(data, 'dtype', type(data).__name__)}"
                           f"{getattr(data, 'shape', '')}")
        bad = ~np.isfinite(data)
        if bad.any():
            r, c = np.argwhere(bad)[0]
            raise IMUError(f"IMU recording {str(path)!r} has a non-finite value at [{r}, {c}]: {data[r, c]!r}")
        # no MPU6050 reads beyond its widest range: a value past it (1e308 would
        # even become inf as float32) is held at full scale, and its row reads
        # with FAULT_SATURATED, as the driver reports a saturated axis
        data = np.asarray(data, dtype=np.float64)
        clipped = np.clip(data, -FULL_SCALE, FULL_SCALE)
        self.saturated = (clipped != data).any(axis=1)                # (F,) bool
        self.data = np.ascontiguousarray(clipped, dtype=np.float32)
        self.n_frames = int(self.data.shape[0])
        self.loop = loop
        self.rate_hz = rate_hz
        self.index = 0      # row the next read() returns
        self.wraps = 0      # times the recording ran out and started again

    def read(self, out=None):
        if self.index >= self.n_frames:
            if self.loop:
                self.index = 0
                self.wraps += 1
                if self.wraps == 1:     # said once: the rows repeat from here on
                    _log.warning("warning: IMU source %r: the recording's %d rows ran out; "
                                 "looping from its first row (give ?loop=0 to hold the last "
                                 "row with the imu_ended fault)", self.source, self.n_frames)
            else:
                self.faults = FAULT_ENDED
                return self._ret(out)
        np.copyto(self.values, self.data[self.index])
        self.faults = FAULT_SATURATED if self.saturated[self.index] else 0
        self.index += 1
        return self._ret(out)


_DRIVER_OPTS = {
    "rate_hz": opt_positive,
    "accel_g": lambda n, v: ACCEL_RANGES_G[opt_choice(n, v, ACCEL_RANGES_G)],
    "gyro_dps": lambda n, v: GYRO_RANGES_DPS[opt_choice(n, v, GYRO_RANGES_DPS)],
    "dlpf": lambda n, v: opt_int_in(n, v, 0, 6),
    "retries": lambda n, v: opt_int_in(n, v, 0, 100),
    "backoff_s": opt_positive,
}
_SIM_OPTS = {**_DRIVER_OPTS, "seed": lambda n, v: opt_int_in(n, v, 0, 2**63 - 1),
             "realtime": opt_bool, "who_am_i": lambda n, v: opt_int_in(n, v, 0, 0xFF)}
_FILE_OPTS = {"loop": opt_bool, "rate_hz": opt_positive}


def _driver(bus, address, source, opts, **extra) -> MPU6050:
    try:
        return MPU6050(bus, address, **opts, **extra)
    except ValueError as e:
        raise InputError(f"{e} (IMU source {source!r})") from None


def open_imu(source: str, *, bus=None, **opts) -> ImuSource:
    """Open the IMU named by ``source`` (see the module docstring). ``bus`` replaces
    the ``smbus2.SMBus`` an ``i2c://`` source would open (tests, shared buses)."""
    if not isinstance(source, str) or not source.strip():
        raise InputError(f"IMU source must be a non-empty string such as 'i2c://1/0x68', got {source!r}")
    s = source.strip()
    if s.lower() == "none":
        if opts:
            raise InputError(f"IMU source 'none' takes no options, got {sorted(opts)}")
        return NoImuSource(s)
    if "://" not in s:
        raise InputError(f"unknown IMU source {source!r}; use i2c://BUS/ADDR, file://PATH.npy, sim://SCENE or none")
    scheme, rest = s.split("://", 1)
    scheme = scheme.lower()
    if scheme == "i2c":
        parts = urlsplit(s)
        m = re.fullmatch(r"(\d+)", parts.netloc or "")
        addr_s = parts.path.strip("/") or "0x68"
        if m is None or not re.fullmatch(r"0[xX][0-9a-fA-F]{1,2}|\d{1,3}", addr_s):
            raise InputError(f"bad IMU source {source!r}: expected i2c://BUS/ADDR such as i2c://1/0x68")
        bus_no = int(m.group(1))
        address = int(addr_s, 0)
        if not 0x08 <= address <= 0x77:
            raise InputError(f"bad IMU source {source!r}: address 0x{address:02x} is outside 0x08..0x77")
        o = parse_options("IMU", source, dict(parse_qsl(parts.query, keep_blank_values=True)), opts, _DRIVER_OPTS)
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
            raise InputError(f"bad IMU source {source!r}: sim:// needs a scene name or path, e.g. sim://walk")
        o = parse_options("IMU", source, dict(parse_qsl(parts.query, keep_blank_values=True)), opts, _SIM_OPTS)
        seed = o.pop("seed", 0)
        realtime = o.pop("realtime", False)
        fake_kw = {"who_am_i": o.pop("who_am_i")} if "who_am_i" in o else {}
        from device.sim.fake_mpu6050 import FakeMPU6050     # lazy: the Pi never needs the simulator
        try:
            fake = FakeMPU6050.from_scene(scene, seed=seed, clock=time.monotonic if realtime else None, **fake_kw)
        except (FileNotFoundError, ValueError) as e:       # ConfigError is a ValueError
            raise InputError(f"bad IMU source {source!r}: {e}") from None
        drv = _driver(fake, fake.address, source, o)
        return MPU6050Source(drv, source, step_rows=not realtime)
    if scheme == "file":
        path_str, query = rest, ""
        if "?" in rest and not Path(unquote(rest)).exists():
            path_str, query = rest.split("?", 1)
        path_str = unquote(path_str)
        if not path_str:
            raise InputError(f"bad IMU source {source!r}: file:// needs a path to an (F, 6) .npy")
        o = parse_options("IMU", source, dict(parse_qsl(query, keep_blank_values=True)), opts, _FILE_OPTS)
        return FileImuSource(path_str, source=source, **o)
    raise InputError(f"unknown IMU source scheme {scheme!r} in {source!r}; use i2c://, file://, sim:// or none")
