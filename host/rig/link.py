"""The PC side of the rig link (docs/rig.md): message types, payloads and a
client that talks to the RP2040 firmware over any pyserial port.

Framing is the surface link's (``device.pi.protocol``). A reader thread decodes
every frame as it arrives: ACK/NAK/DONE go to whoever waits for that command,
SAMPLEs are kept with the host time they arrived, PONGs feed the clock-offset
estimate. A keep-alive PING every ``keepalive_s`` keeps the firmware's link
watchdog quiet; if the host goes silent, the firmware stops the motors.
"""
from __future__ import annotations

import struct
import threading
import time
from dataclasses import dataclass

from device.pi.protocol import FrameDecoder, encode_frame
from device.errors import TacfootError

# host -> rig
HOME, MOVE_TO, PRESS, DRAG, LIFT, READ, STREAM, STOP, PING = range(0x21, 0x2A)
# rig -> host
ACK, NAK, DONE, PONG, SAMPLE = range(0x30, 0x35)
CMD_NAMES = {HOME: "home", MOVE_TO: "move_to", PRESS: "press", DRAG: "drag", LIFT: "lift",
             READ: "read", STREAM: "stream", STOP: "stop", PING: "ping"}
REASONS = {1: "out of range", 2: "not homed", 3: "busy", 4: "bad payload",
           5: "unknown command", 6: "emergency stop"}
RESULTS = {0: "ok", 1: "stopped", 2: "limit", 3: "link lost", 4: "timeout",
           5: "emergency stop", 6: "home failed"}
STATES = {0: "idle", 1: "homing", 2: "moving", 3: "pressing", 4: "dragging", 5: "estop"}
FLAGS = {1: "homed", 2: "moving", 4: "contact", 8: "estop", 16: "imu_fault",
         32: "load_fault", 64: "limit_switch"}
PRESS_DEPTH, PRESS_LOAD = 0, 1

_DONE = struct.Struct("<HBBiii")
_SAMPLE = struct.Struct("<Hiii6hBB")
_PONG = struct.Struct("<IIH")


class RigError(TacfootError, RuntimeError):
    """The rig refused a command, failed one, or the link is gone."""


class RigRefused(RigError):
    def __init__(self, cmd: int, reason: int):
        self.cmd, self.reason = cmd, reason
        super().__init__(f"rig refused {CMD_NAMES.get(cmd, hex(cmd))}: "
                         f"{REASONS.get(reason, f'reason {reason}')}")


class LinkLost(RigError):
    pass


@dataclass(frozen=True)
class Done:
    cmd: int
    result: int
    z_mm: float
    x_mm: float
    load_n: float

    @property
    def ok(self) -> bool:
        return self.result == 0

    @property
    def result_name(self) -> str:
        return RESULTS.get(self.result, f"result {self.result}")


@dataclass(frozen=True)
class Sample:
    t_rig_ms: float        # rig clock
    t_host_s: float        # host clock when it arrived
    z_mm: float
    x_mm: float
    load_n: float
    imu: tuple             # ax, ay, az [g], gx, gy, gz [deg/s]
    flags: int
    state: int


def decode_sample(t_ms: int, payload: bytes, t_host_s: float) -> Sample:
    frac, z, x, load, ax, ay, az, gx, gy, gz, flags, state = _SAMPLE.unpack(payload[:28])
    return Sample(t_ms + frac / 1000.0, t_host_s, z / 1000.0, x / 1000.0, load / 1000.0,
                  (ax / 1000.0, ay / 1000.0, az / 1000.0, gx / 10.0, gy / 10.0, gz / 10.0),
                  flags, state)


def decode_done(payload: bytes) -> tuple[int, Done]:
    seq, cmd, result, z, x, load = _DONE.unpack(payload[:16])
    return seq, Done(cmd, result, z / 1000.0, x / 1000.0, load / 1000.0)


def um(mm: float) -> int:
    return int(round(mm * 1000.0))


class RigClient:
    """Commands and samples over a pyserial-like port (read(n) with a timeout,
    write(bytes)). ``clock`` is the host clock every sample is stamped with. The
    rig answers every keep-alive PING, so a wait that hears nothing for
    ``silence_s`` gives up with LinkLost at once."""

    def __init__(self, port, clock=time.monotonic, keepalive_s: float = 0.2,
                 ack_timeout_s: float = 2.0, silence_s: float = 1.5):
        self.port = port
        self.clock = clock
        self.keepalive_s = keepalive_s
        self.ack_timeout_s = ack_timeout_s
        self.silence_s = silence_s          # no byte for this long while waiting: link lost
        self.decoder = FrameDecoder()
        self.samples: list[Sample] = []
        self.pongs: list[tuple[float, float, float]] = []   # (t0 host, t rig mid, t3 host)
        self._pending_ping: dict[int, float] = {}
        self._replies: dict[int, list] = {}
        self._cv = threading.Condition()
        self._seq = 0
        self._wlock = threading.Lock()
        self.error: BaseException | None = None
        self.last_rx_s = self.clock()
        self._stop = threading.Event()
        self._reader = threading.Thread(target=self._read_loop, daemon=True, name="rig-reader")
        self._pinger = threading.Thread(target=self._ping_loop, daemon=True, name="rig-ping")
        self._reader.start()
        self._pinger.start()

    # -- plumbing ----------------------------------------------------------------------
    def _write(self, msg_type: int, payload: bytes = b"") -> int:
        with self._wlock:
            self._seq = (self._seq + 1) & 0xFFFF
            seq = self._seq
            t_ms = int(self.clock() * 1000) & 0xFFFFFFFF
            try:
                self.port.write(encode_frame(msg_type, payload, seq, t_ms))
            except Exception as exc:       # serial.SerialException, OSError
                self._fail(exc)
                raise LinkLost(f"rig link write failed: {exc}") from None
        return seq

    def _fail(self, exc: BaseException) -> None:
        with self._cv:
            if self.error is None:
                self.error = exc
            self._cv.notify_all()

    def _read_loop(self) -> None:
        while not self._stop.is_set():
            try:
                # read(1) returns at the first byte (pyserial's read(n) would wait for
                # n bytes or the timeout, which delays the PONG time stamps)
                data = self.port.read(1)
                if data:
                    waiting = getattr(self.port, "in_waiting", 0)
                    if waiting:
                        data += self.port.read(waiting)
            except Exception as exc:       # unplugged: serial raises, a pty gives EIO
                if not self._stop.is_set():
                    self._fail(exc)
                return
            if not data:
                continue
            now = self.clock()
            self.last_rx_s = now
            for fr in self.decoder.feed(data):
                self._dispatch(fr, now)

    def _dispatch(self, fr, now: float) -> None:
        t, p = fr.msg_type, fr.payload
        if t == SAMPLE and len(p) >= 28:
            self.samples.append(decode_sample(fr.t_ms, p, now))
        elif t == PONG and len(p) >= 10:
            echo, rig_ms, frac = _PONG.unpack(p[:10])
            t0 = self._pending_ping.pop(echo, None)
            if t0 is not None:
                with self._cv:
                    self.pongs.append((t0, rig_ms + frac / 1000.0, now))
                    self._cv.notify_all()
        elif t in (ACK, NAK, DONE) and len(p) >= 3:
            seq = p[0] | (p[1] << 8)
            with self._cv:
                self._replies.setdefault(seq, []).append((t, p))
                self._cv.notify_all()

    def _ping_loop(self) -> None:
        while not self._stop.wait(self.keepalive_s):
            try:
                self.ping()
            except RigError:
                return

    def ping(self) -> None:
        echo = int(self.clock() * 1e6) & 0xFFFFFFFF
        self._pending_ping[echo] = self.clock()
        self._write(PING, struct.pack("<I", echo))

    def _wait(self, seq: int, kinds: tuple, timeout: float):
        end = self.clock() + timeout
        with self._cv:
            while True:
                for i, (t, p) in enumerate(self._replies.get(seq, [])):
                    if t in kinds:
                        self._replies[seq].pop(i)
                        return t, p
                if self.error is not None:
                    raise LinkLost(f"rig link lost: {self.error}")
                silent = self.clock() - self.last_rx_s
                if silent > self.silence_s:
                    raise LinkLost(f"rig silent for {silent:.1f} s")
                left = end - self.clock()
                if left <= 0:
                    return None
                self._cv.wait(min(left, 0.05))

    # -- commands ----------------------------------------------------------------------
    def send(self, cmd: int, payload: bytes = b"") -> int:
        """Send a command; return its seq once ACKed. Raises RigRefused on a NAK and
        LinkLost when no answer comes within ack_timeout_s."""
        seq = self._write(cmd, payload)
        got = self._wait(seq, (ACK, NAK), self.ack_timeout_s)
        if got is None:
            raise LinkLost(f"no answer to {CMD_NAMES.get(cmd)} within {self.ack_timeout_s:g} s")
        t, p = got
        if t == NAK:
            raise RigRefused(cmd, p[3] if len(p) > 3 else 0)
        return seq

    def wait_done(self, seq: int, timeout: float) -> Done:
        got = self._wait(seq, (DONE,), timeout)
        if got is None:
            if self.clock() - self.last_rx_s > 1.0:
                raise LinkLost(f"rig silent for {self.clock() - self.last_rx_s:.1f} s")
            raise RigError(f"command {seq} not done within {timeout:g} s")
        return decode_done(got[1])[1]

    def run(self, cmd: int, payload: bytes = b"", timeout: float = 30.0) -> Done:
        """Send a motion command and wait for it to finish; a result other than ok
        raises RigError naming it."""
        done = self.wait_done(self.send(cmd, payload), timeout)
        if not done.ok:
            err = LinkLost if done.result == 3 else RigError
            raise err(f"{CMD_NAMES.get(cmd)} ended: {done.result_name} "
                      f"(z {done.z_mm:.2f} mm, load {done.load_n:.2f} N)")
        return done

    def home(self, timeout: float = 60.0) -> Done:
        return self.run(HOME, timeout=timeout)

    def move_to(self, z_mm: float, speed_mm_s: float = 0.0, timeout: float = 30.0) -> Done:
        return self.run(MOVE_TO, struct.pack("<iI", um(z_mm), um(speed_mm_s)), timeout)

    def press_depth(self, depth_mm: float, speed_mm_s: float, timeout: float = 30.0) -> Done:
        return self.run(PRESS, struct.pack("<BBiI", PRESS_DEPTH, 0, um(depth_mm),
                                           um(speed_mm_s)), timeout)

    def press_load(self, load_n: float, speed_mm_s: float, timeout: float = 30.0) -> Done:
        return self.run(PRESS, struct.pack("<BBiI", PRESS_LOAD, 0, um(load_n),
                                           um(speed_mm_s)), timeout)

    def drag(self, distance_mm: float, speed_mm_s: float, timeout: float = 30.0) -> Done:
        return self.run(DRAG, struct.pack("<iI", um(distance_mm), um(speed_mm_s)), timeout)

    def lift(self, clearance_mm: float, timeout: float = 30.0) -> Done:
        return self.run(LIFT, struct.pack("<I", um(clearance_mm)), timeout)

    def stream(self, period_ms: int) -> None:
        self.send(STREAM, struct.pack("<H", int(period_ms)))

    def stop(self) -> None:
        self.send(STOP)

    def read(self, timeout: float = 1.0) -> Sample:
        n = len(self.samples)
        self.send(READ)
        end = self.clock() + timeout
        while self.clock() < end:
            if len(self.samples) > n:
                return self.samples[-1]
            time.sleep(0.002)
        raise RigError("no sample after READ")

    # -- clock -------------------------------------------------------------------------
    def sync_clock(self, n: int = 10, gap_s: float = 0.01) -> dict:
        """Estimate the rig clock's offset from the host clock, NTP-style: for each
        ping, offset = rig time - (host send + host receive) / 2; the estimate is
        the one with the shortest round trip. Returns offset_ms (rig - host), rtt_ms
        of that ping and spread_ms (how much the estimates disagree)."""
        start = len(self.pongs)
        for _ in range(n):
            self.ping()
            time.sleep(gap_s)
        end = self.clock() + 1.0
        while len(self.pongs) - start < n and self.clock() < end:
            time.sleep(0.005)
        got = self.pongs[start:]
        if not got:
            raise LinkLost("no PONG from the rig: is it running the rig firmware?")
        est = sorted(((t3 - t0) * 1000.0, rig - (t0 + t3) * 500.0) for t0, rig, t3 in got)
        rtt, off = est[0]
        offs = [o for _, o in est]
        self.offset_ms = off
        return {"offset_ms": off, "rtt_ms": rtt, "spread_ms": max(offs) - min(offs),
                "pings": len(got)}

    def close(self) -> None:
        self._stop.set()
        try:
            self.port.close()
        except Exception:
            pass
        self._reader.join(timeout=1.0)
        self._pinger.join(timeout=1.0)
