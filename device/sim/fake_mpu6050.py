"""A stand-in for an MPU6050 on an I2C bus.

``FakeMPU6050`` behaves like an ``smbus2.SMBus`` with one MPU6050 attached, so an
IMU driver written against smbus2 runs unchanged against it::

    bus = FakeMPU6050(motion, fps=200.0)            # motion: (F, 6) g and deg/s
    imu = MPU6050Driver(bus)                        # the driver under test
    bus.seek(10)                                    # pin frame 10 for a test

What is emulated (MPU-6000/6050 Register Map rev 4.2):

* WHO_AM_I (0x75) reads ``who_am_i`` (0x68; clones answer 0x70, 0x72 or 0x98).
* Power-on / DEVICE_RESET state: every register 0x00 except PWR_MGMT_1 = 0x40
  (SLEEP). While SLEEP is set the data registers read zeros. Writing 0x80
  (DEVICE_RESET) to PWR_MGMT_1 restores the power-on state; the bit self-clears.
  TEMP_DIS (PWR_MGMT_1 bit 3) makes the temperature read zero; the STBY_* bits of
  PWR_MGMT_2 make the matching axis read zero.
* SMPLRT_DIV, CONFIG (DLPF_CFG), GYRO_CONFIG (FS_SEL), ACCEL_CONFIG (AFS_SEL) are
  stored and used. Outputs are scaled by the configured full-scale range and
  saturate at -32768 / 32767. The sample rate is the gyro output rate (8 kHz when
  DLPF_CFG is 0 or 7, else 1 kHz) / (1 + SMPLRT_DIV): under a clock, the data
  registers only change at sample instants. The low-pass filter itself is not
  modelled (the motion rows are used as they are).
* Data registers 0x3B..0x48: big-endian two's complement ACCEL_X/Y/Z, TEMP,
  GYRO_X/Y/Z. TEMP = (temp_c - 36.53) * 340. A burst read is one consistent
  sample (the chip's shadow registers); single-byte reads work too. Register
  addresses auto-increment in block reads and writes. Writes to read-only
  registers are ignored, as on the chip.
* Not emulated: FIFO, interrupts (INT_STATUS reads 0), I2C master / external
  sensors, self-test, cycle mode.

Which motion row is returned:

* ``clock`` (default ``time.monotonic``) gives seconds; time is measured from
  construction (``t = clock() - clock_at_construction``), quantised down to the
  configured sample period, and ``row = int(t * fps)`` clamped to the last row.
* ``seek(i)`` pins row ``i`` whatever the clock says (deterministic tests);
  ``seek(None)`` returns to the clock.
* ``clock=None`` means there is no clock: the fake starts pinned at row 0 and only
  ``seek`` moves it.

Noise (``noise_g``, ``noise_dps``: standard deviations) is Gaussian and
deterministic: it depends only on ``seed`` and the sample (the row when pinned,
the sample instant under a clock), never on how many reads were made. With zero
noise (the default) a decoded reading equals the motion value to within half an
LSB, unless it saturates.

Faults: ``inject("eio", count=n)`` / ``inject("eremoteio", count=n)`` make the next
n transactions raise ``OSError`` errno 5 / 121 without taking effect;
``inject("stuck")`` makes every transaction raise ``OSError`` errno 110 (ETIMEDOUT)
until ``unstick()``. A transaction to an address other than ``address`` raises
``OSError`` errno 121, as smbus2 does when nothing acknowledges. The same faults
can be given to the constructor: ``faults={"eio": 2}``, ``stuck=True``.
"""

from __future__ import annotations

import errno
import math
import struct
import threading
import time
from collections import deque
from pathlib import Path
from typing import Callable, Iterable, Mapping

import numpy as np

from device.checks import finite_number, positive_number, whole_number
from device.closing import Closing

__all__ = [
    "FakeMPU6050",
    "SceneMotion",
    "MPU6050_ADDR",
    "WHO_AM_I_MPU6050",
    "WHO_AM_I_CLONES",
    "GYRO_LSB_PER_DPS",
    "ACCEL_LSB_PER_G",
    "TEMP_LSB_PER_C",
    "TEMP_OFFSET_C",
]

# ---------------------------------------------------------------- register map
MPU6050_ADDR = 0x68          # AD0 low; 0x69 with AD0 high
SELF_TEST_X = 0x0D
SELF_TEST_Y = 0x0E
SELF_TEST_Z = 0x0F
SELF_TEST_A = 0x10
SMPLRT_DIV = 0x19
CONFIG = 0x1A
GYRO_CONFIG = 0x1B
ACCEL_CONFIG = 0x1C
FIFO_EN = 0x23
INT_PIN_CFG = 0x37
INT_ENABLE = 0x38
INT_STATUS = 0x3A
ACCEL_XOUT_H = 0x3B
ACCEL_XOUT_L = 0x3C
ACCEL_YOUT_H = 0x3D
ACCEL_YOUT_L = 0x3E
ACCEL_ZOUT_H = 0x3F
ACCEL_ZOUT_L = 0x40
TEMP_OUT_H = 0x41
TEMP_OUT_L = 0x42
GYRO_XOUT_H = 0x43
GYRO_XOUT_L = 0x44
GYRO_YOUT_H = 0x45
GYRO_YOUT_L = 0x46
GYRO_ZOUT_H = 0x47
GYRO_ZOUT_L = 0x48
EXT_SENS_DATA_00 = 0x49
EXT_SENS_DATA_23 = 0x60
SIGNAL_PATH_RESET = 0x68
USER_CTRL = 0x6A
PWR_MGMT_1 = 0x6B
PWR_MGMT_2 = 0x6C
FIFO_COUNTH = 0x72
FIFO_COUNTL = 0x73
FIFO_R_W = 0x74
WHO_AM_I = 0x75

DATA_FIRST = ACCEL_XOUT_H
DATA_LAST = GYRO_ZOUT_L
DATA_LEN = DATA_LAST - DATA_FIRST + 1     # 14

# PWR_MGMT_1 bits
DEVICE_RESET = 0x80
SLEEP = 0x40
CYCLE = 0x20
TEMP_DIS = 0x08
CLKSEL_MASK = 0x07
# PWR_MGMT_2 standby bits
STBY_XA = 0x20
STBY_YA = 0x10
STBY_ZA = 0x08
STBY_XG = 0x04
STBY_YG = 0x02
STBY_ZG = 0x01
# field masks
DLPF_CFG_MASK = 0x07
FS_SEL_MASK = 0x18
AFS_SEL_MASK = 0x18
FS_SEL_SHIFT = 3
AFS_SEL_SHIFT = 3

PWR_MGMT_1_RESET = SLEEP
WHO_AM_I_MPU6050 = 0x68
WHO_AM_I_CLONES = (0x70, 0x72, 0x98)   # MPU6500-, MPU9250-style and other clones

GYRO_LSB_PER_DPS = (131.0, 65.5, 32.8, 16.4)        # FS_SEL 0..3: 250..2000 deg/s
GYRO_RANGE_DPS = (250, 500, 1000, 2000)
ACCEL_LSB_PER_G = (16384.0, 8192.0, 4096.0, 2048.0)  # AFS_SEL 0..3: 2..16 g
ACCEL_RANGE_G = (2, 4, 8, 16)
TEMP_LSB_PER_C = 340.0
TEMP_OFFSET_C = 36.53

GYRO_RATE_DLPF_OFF_HZ = 8000.0   # DLPF_CFG 0 or 7
GYRO_RATE_DLPF_ON_HZ = 1000.0

I2C_SMBUS_BLOCK_MAX = 32         # as smbus2
RAW_MIN = -32768
RAW_MAX = 32767

_READ_ONLY = frozenset(
    [INT_STATUS, FIFO_COUNTH, FIFO_COUNTL, WHO_AM_I]
    + list(range(ACCEL_XOUT_H, EXT_SENS_DATA_23 + 1))
)

FAULT_ERRNO = {
    "eio": errno.EIO,               # 5
    "eremoteio": errno.EREMOTEIO,   # 121 (no ACK)
}
STUCK_ERRNO = errno.ETIMEDOUT       # 110

_NOT_PINNED = object()


def _to_raw(value: float, lsb_per_unit: float) -> int:
    """Scale, round to nearest and saturate to int16 (finite for any finite input)."""
    scaled = value * lsb_per_unit
    if scaled >= RAW_MAX:
        return RAW_MAX
    if scaled <= RAW_MIN:
        return RAW_MIN
    return int(round(scaled))


def _motion_array(motion) -> np.ndarray:
    try:
        arr = np.array(motion, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"motion must be a numeric array of shape (F, 6), got {motion!r:.80}") from None
    if arr.ndim != 2 or arr.shape[1] != 6 or arr.shape[0] < 1:
        raise ValueError(f"motion must have shape (F, 6) with F >= 1, got shape {arr.shape}")
    bad = ~np.isfinite(arr)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise ValueError(f"motion must be finite, got motion[{r}, {c}] = {float(arr[r, c])!r}")
    return arr


class SceneMotion:
    """A simulated scene's IMU rows (``truth["imu"]``) read a block at a time, so a
    scene of any length takes the same memory: ``motion[i]`` (a (6,) float64 copy)
    and ``motion[i, k]``, ``shape`` (F, 6), ``len``."""

    def __init__(self, sim):
        self.sim = sim
        self.shape = (int(sim.n_frames), 6)

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, key):
        i, k = key if isinstance(key, tuple) else (key, slice(None))
        i = int(i) + (self.shape[0] if int(i) < 0 else 0)
        lo, truth = self.sim.truth_block(i)
        return np.array(truth["imu"][i - lo, k], dtype=np.float64)


class FakeMPU6050(Closing):
    """An smbus2.SMBus stand-in with one MPU6050 on it. See the module docstring.

    Parameters
    ----------
    motion : array (F, 6): ax, ay, az [g], gx, gy, gz [deg/s], one row per frame.
    fps : frames per second of ``motion`` (> 0).
    address : 7-bit I2C address the chip answers on (0x68, or 0x69 with AD0 high).
    who_am_i : WHO_AM_I value (0x68 genuine; 0x70, 0x72, 0x98 for clones).
    temp_c : die temperature reported, degrees C.
    clock : callable returning seconds, or None for no clock (pinned at row 0).
    noise_g, noise_dps : standard deviation of accelerometer / gyro noise.
    seed : seed for the noise.
    faults : mapping ``{"eio": n, "eremoteio": n}`` injected at construction.
    stuck : start with a stuck bus.
    """

    def __init__(
        self,
        motion,
        fps: float,
        *,
        address: int = MPU6050_ADDR,
        who_am_i: int = WHO_AM_I_MPU6050,
        temp_c: float = 25.0,
        clock: Callable[[], float] | None = time.monotonic,
        noise_g: float = 0.0,
        noise_dps: float = 0.0,
        seed: int = 0,
        faults: Mapping[str, int] | None = None,
        stuck: bool = False,
    ):
        arr = motion if isinstance(motion, SceneMotion) else _motion_array(motion)
        fps_f = positive_number("fps", fps)
        temp = finite_number("temp_c", temp_c)
        if clock is not None and not callable(clock):
            raise ValueError(f"clock must be callable or None, got {clock!r}")

        self.motion = arr
        if isinstance(arr, np.ndarray):
            self.motion.setflags(write=False)
        self.fps = fps_f
        self.address = whole_number("address", address, 0x00, 0x7F)
        self.who_am_i = whole_number("who_am_i", who_am_i, 0x00, 0xFF)
        self.temp_c = temp
        self.noise_g = finite_number("noise_g", noise_g, 0)
        self.noise_dps = finite_number("noise_dps", noise_dps, 0)
        self.seed = whole_number("seed", seed, 0, 2**63 - 1)

        self._clock = clock
        self._t0 = clock() if clock is not None else 0.0
        self._pinned: int | None = 0 if clock is None else None
        self._regs = bytearray(256)
        self._faults: deque[int] = deque()
        self._stuck = False
        self._closed = False
        self._lock = threading.Lock()
        self.transactions = 0      # transactions attempted (including failed ones)
        self.errors = 0            # transactions that raised OSError
        self._reset_registers()
        for kind, count in (faults or {}).items():
            self.inject(kind, count=count)
        if stuck:
            self.inject("stuck")

    @classmethod
    def from_npy(cls, path, fps: float, **kwargs) -> "FakeMPU6050":
        """Build from a recorded ``(F, 6)`` .npy file (e.g. roboskin/concrete_gyro.npy)."""
        return cls(np.load(Path(path), allow_pickle=False), fps, **kwargs)

    @classmethod
    def from_scene(cls, scene, seed: int = 0, **kwargs) -> "FakeMPU6050":
        """Readings from a simulator scene's motion (name, path or Scene): steps,
        drag vibration and slip jerks, with ``imu_noise`` if the scene names it."""
        from .scene import Scene, load_scene
        from .simulator import Simulator
        sc = scene if isinstance(scene, Scene) else load_scene(scene)
        return cls(SceneMotion(Simulator(sc, seed=seed)), sc.fps, **kwargs)

    # ------------------------------------------------------------ test controls
    @property
    def n_frames(self) -> int:
        return int(self.motion.shape[0])

    def seek(self, frame_index: int | None) -> None:
        """Pin the motion row returned by the data registers; None follows the clock."""
        if frame_index is None:
            if self._clock is None:
                raise ValueError("frame_index=None needs a clock, but clock is None")
            self._pinned = None
            return
        self._pinned = whole_number("frame_index", frame_index, 0, self.n_frames - 1)

    def inject(self, kind: str, count: int | None = None) -> None:
        """Inject a bus fault: "eio" / "eremoteio" for the next ``count`` (default 1)
        transactions, or "stuck" until :meth:`unstick`."""
        if kind == "stuck":
            if count is not None:
                raise ValueError(f"count is not used with kind='stuck' (it lasts until unstick()), got count={count!r}")
            self._stuck = True
            return
        if kind not in FAULT_ERRNO:
            raise ValueError(f"kind must be one of {sorted(FAULT_ERRNO) + ['stuck']}, got {kind!r}")
        n = 1 if count is None else whole_number("count", count, 0, 10**9)
        self._faults.extend([FAULT_ERRNO[kind]] * n)

    def unstick(self) -> None:
        """Free a stuck bus. Pending eio/eremoteio faults are kept."""
        self._stuck = False

    def clear_faults(self) -> None:
        self._faults.clear()
        self._stuck = False

    @property
    def pending_faults(self) -> int:
        return len(self._faults)

    # ----------------------------------------------------------- derived config
    @property
    def asleep(self) -> bool:
        return bool(self._regs[PWR_MGMT_1] & SLEEP)

    @property
    def gyro_lsb_per_dps(self) -> float:
        return GYRO_LSB_PER_DPS[(self._regs[GYRO_CONFIG] & FS_SEL_MASK) >> FS_SEL_SHIFT]

    @property
    def accel_lsb_per_g(self) -> float:
        return ACCEL_LSB_PER_G[(self._regs[ACCEL_CONFIG] & AFS_SEL_MASK) >> AFS_SEL_SHIFT]

    @property
    def gyro_output_rate_hz(self) -> float:
        dlpf = self._regs[CONFIG] & DLPF_CFG_MASK
        return GYRO_RATE_DLPF_OFF_HZ if dlpf in (0, 7) else GYRO_RATE_DLPF_ON_HZ

    @property
    def sample_rate_hz(self) -> float:
        return self.gyro_output_rate_hz / (1 + self._regs[SMPLRT_DIV])

    def register(self, reg: int) -> int:
        """The stored value of a register, without a bus transaction (for tests)."""
        return self._regs[whole_number("reg", reg, 0, 0xFF)]

    # ------------------------------------------------------------- smbus2 API
    def read_byte_data(self, i2c_addr: int, register: int, force=None) -> int:
        return self._read(i2c_addr, register, 1)[0]

    def write_byte_data(self, i2c_addr: int, register: int, value: int, force=None) -> None:
        value = whole_number("value", value, 0, 0xFF)
        self._write(i2c_addr, register, [value])

    def read_i2c_block_data(self, i2c_addr: int, register: int, length: int, force=None) -> list[int]:
        length = whole_number("length", length, 1, I2C_SMBUS_BLOCK_MAX)
        return self._read(i2c_addr, register, length)

    def write_i2c_block_data(self, i2c_addr: int, register: int, data: Iterable[int], force=None) -> None:
        data = list(data)
        if not 1 <= len(data) <= I2C_SMBUS_BLOCK_MAX:
            raise ValueError(f"data length must be 1..{I2C_SMBUS_BLOCK_MAX}, got {len(data)}")
        data = [whole_number(f"data[{i}]", v, 0, 0xFF) for i, v in enumerate(data)]
        self._write(i2c_addr, register, data)

    def close(self) -> None:
        self._closed = True

    @property
    def closed(self) -> bool:
        return self._closed

    # -------------------------------------------------------------- internals
    def _reset_registers(self) -> None:
        self._regs[:] = bytes(256)
        self._regs[PWR_MGMT_1] = PWR_MGMT_1_RESET
        self._regs[WHO_AM_I] = self.who_am_i

    def _begin(self, i2c_addr, register) -> int:
        """Checks common to every transaction; raises the injected faults."""
        if self._closed:
            raise ValueError("I2C transaction on a closed bus")
        i2c_addr = whole_number("i2c_addr", i2c_addr, 0x00, 0x7F)
        register = whole_number("register", register, 0x00, 0xFF)
        self.transactions += 1
        if self._stuck:
            self.errors += 1
            raise OSError(STUCK_ERRNO, "Connection timed out (fake I2C bus stuck)")
        if i2c_addr != self.address:
            self.errors += 1
            raise OSError(errno.EREMOTEIO, f"Remote I/O error (no device at 0x{i2c_addr:02x})")
        if self._faults:
            self.errors += 1
            e = self._faults.popleft()
            raise OSError(e, f"{errno.errorcode.get(e, e)} (injected fault)")
        return register

    def _read(self, i2c_addr, register, length) -> list[int]:
        with self._lock:
            reg = self._begin(i2c_addr, register)
            addrs = [(reg + i) & 0xFF for i in range(length)]
            sample = None
            if any(DATA_FIRST <= a <= DATA_LAST for a in addrs):
                sample = self._sample_bytes()
            out = []
            for a in addrs:
                if sample is not None and DATA_FIRST <= a <= DATA_LAST:
                    out.append(sample[a - DATA_FIRST])
                else:
                    out.append(self._regs[a])
            return out

    def _write(self, i2c_addr, register, data) -> None:
        with self._lock:
            reg = self._begin(i2c_addr, register)
            for i, v in enumerate(data):
                a = (reg + i) & 0xFF
                if a in _READ_ONLY:
                    continue
                if a == PWR_MGMT_1 and v & DEVICE_RESET:
                    self._reset_registers()
                    continue
                if a == SIGNAL_PATH_RESET:
                    continue            # self-clearing reset bits
                self._regs[a] = v

    def _current(self) -> tuple[int, tuple]:
        """(row, noise key) for the sample the data registers hold now."""
        if self._pinned is not None:
            return self._pinned, (0, self._pinned)
        t = float(self._clock()) - self._t0
        if not math.isfinite(t) or t < 0:
            t = 0.0
        rate = self.sample_rate_hz
        k = math.floor(t * rate + 1e-9)
        t_q = k / rate
        row = min(int(t_q * self.fps + 1e-9), self.n_frames - 1)
        return row, (1, k)

    def _sample_bytes(self) -> bytes:
        if self.asleep:
            return bytes(DATA_LEN)
        row, key = self._current()
        values = self.motion[row].copy()
        if self.noise_g > 0 or self.noise_dps > 0:
            rng = np.random.default_rng([self.seed, *key])
            n = rng.standard_normal(6)
            values[:3] += n[:3] * self.noise_g
            values[3:] += n[3:] * self.noise_dps
        a_lsb = self.accel_lsb_per_g
        g_lsb = self.gyro_lsb_per_dps
        pm1 = self._regs[PWR_MGMT_1]
        pm2 = self._regs[PWR_MGMT_2]
        ax, ay, az = (0 if pm2 & stby else _to_raw(v, a_lsb)
                      for v, stby in zip(values[:3], (STBY_XA, STBY_YA, STBY_ZA)))
        gx, gy, gz = (0 if pm2 & stby else _to_raw(v, g_lsb)
                      for v, stby in zip(values[3:], (STBY_XG, STBY_YG, STBY_ZG)))
        temp = 0 if pm1 & TEMP_DIS else _to_raw(self.temp_c - TEMP_OFFSET_C, TEMP_LSB_PER_C)
        return struct.pack(">hhhhhhh", ax, ay, az, temp, gx, gy, gz)

    def __repr__(self) -> str:
        return (f"FakeMPU6050(frames={self.n_frames}, fps={self.fps}, address=0x{self.address:02x}, "
                f"who_am_i=0x{self.who_am_i:02x}, asleep={self.asleep})")
