"""``--rig sim://``: the rig firmware behind a pty, driving a simulated frame.

The firmware (device/micropython/rig, the code that runs on the RP2040) runs
under CPython in a thread. Its link is the master side of a pty, so the host
driver opens the slave with pyserial and talks real serial bytes. Its pins are
the last inch swapped: step pulses move a simulated carriage that closes the
home switch at the top and presses the sensor into a base plate, the load cell
reads the contact load of the simulator's physics (Hertz, skin and plate springs
in series), and the H-bridge's PWM moves the x axis.

``--camera sim://`` then renders what the carriage did: :class:`SimRigCamera`
samples the carriage at the camera's frame rate while recording, and turns the
trace into a simulator scene (one timeline step per frame) whose frames the
simulator renders.

URL options: ``sim://?start_mm=10&surface_mm=20&plate=hard&drop_at_press=2&drop_s=1.5``
(carriage start, plate surface below the home switch, the plate until the trial
file names one, and a link drop: the pty stops carrying bytes 0.1 s after the
host's ``drop_at_press``-th PRESS command, or ``drop_at_s`` after opening, for
``drop_s``).
"""
from __future__ import annotations

import math
import os
import sys
import threading
import time
import tty
from dataclasses import replace
from pathlib import Path
from urllib.parse import parse_qsl, urlsplit

import numpy as np

MPY_DIR = Path(__file__).resolve().parents[2] / "device" / "micropython"

STEPS_PER_MM = 100
TRAVEL_MM = 40
X_MAX_SPEED_MM_S = 50


def _firmware():
    if str(MPY_DIR) not in sys.path:
        sys.path.insert(0, str(MPY_DIR))
    from rig import drivers, firmware
    return firmware, drivers


class _Pin:
    def __init__(self, level=0):
        self.level = level

    def value(self, v=None):
        if v is None:
            return self.level
        self.level = 1 if v else 0


class _StepPin(_Pin):
    def __init__(self, carriage):
        super().__init__()
        self.c = carriage

    def value(self, v=None):
        if v is None:
            return self.level
        v = 1 if v else 0
        if v and not self.level:
            self.c.steps += 1 if self.c.dir_pin.level else -1
        self.level = v


class _SwitchPin:
    def __init__(self, fn):
        self.fn = fn

    def value(self, v=None):
        return 1 if self.fn() else 0


class _PWM:
    def __init__(self):
        self.duty = 0

    def duty_u16(self, d=None):
        if d is None:
            return self.duty
        self.duty = int(d)


class _Load:
    """The load cell: reads the carriage's contact load."""

    def __init__(self, carriage):
        self.c = carriage
        self.faults = 0

    def read_mn(self):
        return int(self.c.load_n() * 1000)


class _Imu:
    def __init__(self, carriage, seed=0):
        self.c = carriage
        self.rng = np.random.default_rng(seed)

    def read(self):
        n = self.rng.standard_normal(6)
        vib = 0.05 if self.c.sliding() else 0.0
        return (0.01 * n[0] + vib * n[3], 0.01 * n[1], 1.0 + 0.01 * n[2] + vib * n[4],
                0.3 * n[3], 0.3 * n[4], 0.3 * n[5], 25.0)


class Carriage:
    """The simulated frame: true z (down from the home switch) and x, and the
    base plate under the sensor."""

    def __init__(self, start_mm: float, surface_mm: float, plate: str = "hard",
                 profile: str = "roboskin"):
        from device.profile import load_profile
        self.steps = int(round(start_mm * STEPS_PER_MM))
        self.surface_mm = float(surface_mm)
        self.profile = load_profile(profile)
        self.dir_pin = _Pin()
        self.pwm = _PWM()
        self.in1 = _Pin()
        self.in2 = _Pin()
        self.x_mm = 0.0
        self.set_plate(plate)
        self.lock = threading.Lock()

    def set_plate(self, preset: str) -> None:
        from device.sim.scene import PRESETS
        if preset not in PRESETS:
            raise ValueError(f"sim plate {preset!r}: must be one of {sorted(PRESETS)}")
        self.plate = preset
        self.k_plate = PRESETS[preset].stiffness_n_per_mm

    @property
    def z_mm(self) -> float:
        return self.steps / STEPS_PER_MM

    def depth_mm(self) -> float:
        """Commanded depth into the plate (negative: above it)."""
        return self.z_mm - self.surface_mm

    def load_n(self) -> float:
        # the simulator's contact model (device/sim/physics.py)
        p = self.profile
        d = max(self.depth_mm(), 0.0)
        d *= self.k_plate / (self.k_plate + p.skin_stiffness_n_per_mm)
        return 4.0 / 3.0 * p.modulus_n_per_mm2 * math.sqrt(p.dome_radius_mm) * d ** 1.5

    def x_speed_mm_s(self) -> float:
        if not (self.in1.level or self.in2.level):
            return 0.0
        v = self.pwm.duty / 65535.0 * X_MAX_SPEED_MM_S
        return v if self.in1.level else -v

    def sliding(self) -> bool:
        return self.x_speed_mm_s() != 0.0 and self.load_n() > 0

    def advance(self, dt_s: float) -> None:
        self.x_mm += self.x_speed_mm_s() * dt_s


class _PtyStream:
    """The firmware's end of the link: the pty master, non-blocking; while the
    link is 'dropped' nothing passes either way."""

    def __init__(self, fd, sim):
        self.fd = fd
        self.sim = sim
        os.set_blocking(fd, False)

    def readinto(self, buf):
        if self.sim.dropped():
            try:
                os.read(self.fd, 4096)          # bytes sent into a dead cable
            except (BlockingIOError, OSError):
                pass
            return 0
        try:
            data = os.read(self.fd, len(buf))
        except (BlockingIOError, OSError):
            return 0
        buf[:len(data)] = data
        self.sim.tap(data)
        return len(data)

    def write(self, buf):
        if self.sim.dropped():
            return len(buf)
        data = bytes(buf)
        while data:
            try:
                n = os.write(self.fd, data)
            except BlockingIOError:
                time.sleep(0.0005)
                continue
            except OSError:
                return 0
            data = data[n:]
        return len(buf)


_CURRENT: "SimRig | None" = None


def current() -> "SimRig | None":
    """The sim rig of this process (what ``--camera sim://`` films)."""
    return _CURRENT


class SimRig:
    """The firmware on a thread, behind a pty. ``port`` is the slave's path."""

    def __init__(self, url: str = "sim://", seed: int = 0):
        global _CURRENT
        opts = dict(parse_qsl(urlsplit(url).query))
        known = {"start_mm", "surface_mm", "drop_at_s", "drop_at_press", "drop_s", "plate"}
        for k in opts:
            if k not in known:
                raise ValueError(f"--rig {url}: unknown option {k!r} (known: {sorted(known)})")
        try:
            num = {k: float(v) for k, v in opts.items() if k != "plate"}
        except ValueError as exc:
            raise ValueError(f"--rig {url}: {exc}") from None
        self.carriage = Carriage(num.get("start_mm", 10.0), num.get("surface_mm", 20.0),
                                 opts.get("plate", "hard"))
        self.surface_given = "surface_mm" in num     # else the trial file's rig.surface_mm
        self.drop_at_s = num.get("drop_at_s")
        self.drop_s = num.get("drop_s", 1.5)
        self.drop_at_press = int(num.get("drop_at_press", 0))
        self.presses = 0
        from device.pi.protocol import FrameDecoder
        self._sniff = FrameDecoder()
        fw, drv = _firmware()
        c = self.carriage
        self.firmware = fw.Rig(
            None, drv.Stepper(_StepPin(c), c.dir_pin, steps_per_mm=STEPS_PER_MM, accel_mm_s2=400),
            drv.DCMotor(c.pwm, c.in1, c.in2, max_speed_mm_s=X_MAX_SPEED_MM_S, timeout_ms=10000),
            _Load(c), _Imu(c, seed), _SwitchPin(lambda: c.steps <= 0), None,
            travel_mm=TRAVEL_MM, speed_mm_s=20, home_speed_mm_s=20, touch_mn=50,
            link_timeout_ms=1000)
        self._t0 = time.monotonic()
        self._stop = threading.Event()
        self._open_pty()
        self._thread = threading.Thread(target=self._loop, daemon=True, name="sim-rig")
        self._thread.start()
        _CURRENT = self

    def _open_pty(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)
        self.port = os.ttyname(slave)
        self._slave_fd = slave              # keep open so the master never sees EIO
        self._master = master
        self.firmware.stream = _PtyStream(master, self)

    def reconnect(self) -> str:
        """A new pty for the same firmware (the USB device re-enumerating)."""
        old_m, old_s = self._master, self._slave_fd
        self._open_pty()
        for fd in (old_m, old_s):
            try:
                os.close(fd)
            except OSError:
                pass
        return self.port

    def tap(self, data: bytes) -> None:
        """Watch the host's commands (for ``drop_at_press``)."""
        if not self.drop_at_press:
            return
        for fr in self._sniff.feed(data):
            if fr.msg_type == 0x23:                       # PRESS
                self.presses += 1
                if self.presses == self.drop_at_press and self.drop_at_s is None:
                    self.drop_at_s = time.monotonic() - self._t0 + 0.1

    def dropped(self) -> bool:
        if self.drop_at_s is None:
            return False
        t = time.monotonic() - self._t0
        return self.drop_at_s <= t < self.drop_at_s + self.drop_s

    def _loop(self) -> None:
        fw = self.firmware
        last = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            with self.carriage.lock:
                fw.poll(int(now * 1e6) & 0x3FFFFFFF)
                self.carriage.advance(now - last)
                self.last_poll_s = now          # host time of the rig clock fw.t_ms
            last = now
            time.sleep(0.0005)

    def state(self) -> tuple:
        c = self.carriage
        with c.lock:
            return c.depth_mm(), c.x_mm, c.plate

    def close(self) -> None:
        global _CURRENT
        self._stop.set()
        self._thread.join(timeout=1.0)
        for fd in (self._master, self._slave_fd):
            try:
                os.close(fd)
            except OSError:
                pass
        if _CURRENT is self:
            _CURRENT = None


class SimRigCamera:
    """The camera for ``sim://`` with a sim rig: while recording, samples the
    carriage at ``fps``; ``stop()`` renders the trace with the simulator."""

    def __init__(self, rig: SimRig, fps: float = 60.0, scene: str = "press-hard",
                 seed: int = 0):
        from device.sim import load_scene
        self.rig = rig
        self.fps = float(fps)
        self.template = load_scene(scene)
        self.seed = seed
        self.width, self.height = self.template.width, self.template.height
        self.profile = self.template.profile.name
        self._trace: list = []
        self._stop = threading.Event()
        self._thread = None

    def start(self) -> None:
        self._trace = []
        self._stop.clear()
        self._thread = threading.Thread(target=self._sample, daemon=True, name="sim-camera")
        self._thread.start()

    def _sample(self) -> None:
        period = 1.0 / self.fps
        nxt = time.monotonic()
        while not self._stop.is_set():
            t = time.monotonic()
            d, x, plate = self.rig.state()
            self._trace.append((t, d, x, plate))
            nxt += period
            time.sleep(max(0.0, nxt - time.monotonic()))

    def stop(self) -> tuple[np.ndarray, np.ndarray]:
        """(frames (F, H, W) uint8, t_s (F,) host clock)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        tr = self._trace
        if not tr:
            return np.zeros((0, self.height, self.width), np.uint8), np.zeros(0)
        from device.sim import Simulator
        from device.sim.scene import Action
        actions = []
        prev_x = tr[0][2]
        for _, d, x, plate in tr:
            dt = 1.0 / self.fps
            dx = x - prev_x
            prev_x = x
            if abs(dx) > 1e-9:
                actions.append(Action("drag", dt, direction_deg=0.0 if dx > 0 else 180.0,
                                      speed_mm_s=abs(dx) * self.fps, surface=plate))
            elif d >= 0:
                actions.append(Action("lower", dt, depth_mm=d, surface=plate))
            else:
                actions.append(Action("lift", dt, height_mm=-d, surface=plate))
        scene = replace(self.template, timeline=tuple(actions), fps=self.fps,
                        hover_mm=max(0.0, -tr[0][1]), name="rig")
        sim = Simulator(scene, seed=self.seed)
        frames = np.empty((sim.n_frames, sim.height, sim.width), np.uint8)
        for i in range(sim.n_frames):
            sim.render(i, frames[i])
        self.last_truth = sim.truth
        return frames, np.array([t for t, *_ in tr])

    def close(self) -> None:
        self._stop.set()
