"""Stand-ins for the leg runtime's hardware, shared by the runtime tests
(tests/device/pi/runtime/test_*.py, tests/device/pi/test_main.py): a pyserial-like
port that records what is written and when, scripted cameras, an IMU that reads
zeros, and helpers that build and run a :class:`LegRuntime` on them."""
from __future__ import annotations

import threading
import time

import numpy as np

from device.pi import protocol as P
from device.pi.runtime.config import LegConfig
from device.pi.runtime.load import load_models
from device.pi.runtime.loop import LegRuntime
from device.pi.sources.camera import CameraError, Frame, open_camera

__all__ = ["FPS", "RecordingPort", "SimCamera", "ListCamera", "NullImu", "make_runtime",
           "run_for", "faults_written"]

#: the frame rate the stand-in runtimes run at
FPS = 120.0


class RecordingPort:
    """A pyserial-like port: records every byte written with the time it was taken;
    ``inbox`` holds bytes the 'MCU' sends; ``accept`` False takes no bytes (or
    raises SerialTimeoutException when ``raise_timeout``)."""

    def __init__(self, raise_timeout=False, capacity=None):
        self.chunks: list[tuple[float, bytes]] = []
        self.inbox = bytearray()
        self.accept = True
        self.raise_timeout = raise_timeout
        self.capacity = capacity          # bytes per write at most
        self.lock = threading.Lock()
        self.refused = 0

    def write(self, data):
        if not self.accept:
            self.refused += 1
            if self.raise_timeout:
                import serial
                raise serial.SerialTimeoutException("Write timeout")
            return 0
        b = bytes(data if self.capacity is None else data[:self.capacity])
        self.chunks.append((time.monotonic(), b))
        return len(b)

    @property
    def in_waiting(self):
        return len(self.inbox)

    def read(self, n):
        with self.lock:
            b = bytes(self.inbox[:n])
            del self.inbox[:n]
        return b

    def send(self, msg, seq=0):
        with self.lock:
            self.inbox += msg.encode(seq, 0)

    def frames(self):
        """[(t_written, message)] for every complete frame, timed by its last byte."""
        dec = P.FrameDecoder()
        out = []
        for t, b in self.chunks:
            for raw in dec.feed(b):
                out.append((t, P.decode_message(raw)))
        assert dec.crc_errors == 0 and dec.too_long == 0
        return out


class SimCamera:
    """sim://SCENE with a script: ``stall_at`` (frame index: read() blocks
    ``stall_s``), ``unplug_at`` (read() raises from there; the factory then fails
    ``failed_opens`` times before the camera 'comes back')."""

    def __init__(self, scene="press-hard", stall_at=None, stall_s=0.3, unplug_at=None,
                 failed_opens=2, end=None):
        self.scene, self.stall_at, self.stall_s = scene, stall_at, stall_s
        self.unplug_at, self.failed_opens, self.end = unplug_at, failed_opens, end
        self.onset = None
        self.cam = None
        self.opens = 0
        self.unplugged = False
        self.served = 0

    def factory(self):
        if self.unplugged:
            if self.failed_opens > 0:
                self.failed_opens -= 1
                raise CameraError(2, "no such camera device", "/dev/video0")
            self.unplugged = False
            self.unplug_at = None
        if self.cam is None:
            self.cam = open_camera(f"sim://{self.scene}")
        self.opens += 1
        return self

    def read(self):
        if self.end is not None and self.served >= self.end:
            return None
        if self.stall_at is not None and self.served == self.stall_at:
            self.stall_at = None
            self.onset = time.monotonic()
            time.sleep(self.stall_s)
        if self.unplug_at is not None and self.served >= self.unplug_at:
            if not self.unplugged:
                self.onset = time.monotonic()
            self.unplugged = True
            raise CameraError(5, "camera grab failed (unplugged?)", "/dev/video0")
        fr = self.cam.read()
        if fr is None:                 # loop the clip
            self.cam = open_camera(f"sim://{self.scene}")
            fr = self.cam.read()
        self.served += 1
        return fr

    def close(self):
        pass


class NullImu:
    """An IMU that always reads zeros, with no fault."""

    def __init__(self):
        self.v = np.zeros(6, np.float32)

    def read(self, out=None):
        if out is not None:
            out[:] = self.v
            return out, 0
        return self.v, 0


def make_runtime(tmp_path, cam=None, imu=None, port=None, cfg=None, **kw):
    """(runtime, camera, port): a LegRuntime on a SimCamera, a NullImu and a
    RecordingPort unless given, with the rule alone (``tmp_path`` holds no models)
    and a fast camera reopen."""
    cfg = cfg or LegConfig()
    cfg.camera.reopen_min_s = 0.02
    cfg.camera.reopen_max_s = 0.1
    cam = cam or SimCamera()
    models = load_models(tmp_path, "int8", 133, cfg)        # empty folder: rule fallback
    port = port or RecordingPort()
    rt = LegRuntime(cfg, cam.factory, imu or NullImu(), port, models, lossless=True, fps=FPS,
                    notify=lambda s: None, **kw)
    return rt, cam, port


def run_for(rt, seconds=None, frames=None, hook=None):
    """Step ``rt`` until it stops, ``frames`` frames or ``seconds`` (60 by default)
    have passed, calling ``hook(rt)`` after each step; then close it."""
    rt.start()
    t_end = time.monotonic() + (seconds or 60)
    try:
        while not rt.stopped and time.monotonic() < t_end:
            rt.step()
            if hook is not None:
                hook(rt)
            if frames is not None and rt.frames >= frames:
                break
    finally:
        rt.close()


def faults_written(port):
    """[(t_written, Fault)] of every FAULT packet on the port."""
    return [(t, m) for t, m in port.frames() if isinstance(m, P.Fault)]


class ListCamera:
    """A camera that serves ``images`` once, in order, then ends."""

    def __init__(self, images):
        self.images = list(images)
        self.i = 0

    def factory(self):
        return self

    def read(self):
        if self.i >= len(self.images):
            return None
        self.i += 1
        return Frame(self.i - 1, (self.i - 1) / FPS, self.images[self.i - 1])

    def close(self):
        pass

