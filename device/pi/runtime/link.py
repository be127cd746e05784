"""The serial side of the leg runtime: a writer that never blocks and a reader of
the locomotion MCU's GAIT context and COMMANDs.

The frames themselves (COBS + header + CRC) come from :mod:`device.pi.protocol`.

Writing: drop / coalesce policy
-------------------------------
The runtime hands every packet to :meth:`LinkWriter.send` and calls
:meth:`LinkWriter.pump` once per loop. ``pump`` writes only what the port accepts
right now (:func:`try_write`: a port that takes nothing gives 0 bytes, never a wait),
so a slow, full or blocked port can never stall the frame loop. pyserial's own
``write()`` cannot be trusted for this: with ``write_timeout=0`` on a device
(``serialposix``) or ``socket://``, a full buffer makes ``os.write`` / ``send`` raise
EAGAIN, which ``write()`` swallows and retries for ever (a pty whose peer stopped
reading froze the loop at 74 % CPU, deaf to SIGTERM). So for those two ports
:func:`try_write` makes the one non-blocking system call itself.
What waits is held in one slot per kind:

* ``fault``: a FIFO, never dropped. At most :data:`FAULT_QUEUE` wait; beyond that
  the newest waiting FAULT is replaced by the newer one (each FAULT carries the
  whole current fault state, so the MCU still gets the latest) and
  ``faults_coalesced`` counts it. Sent first.
* ``status``: newest only (reply to COMMAND request-status). Sent second.
* ``surface``: newest only; an unsent SURFACE replaced by a newer one is counted
  in ``packets_dropped``. The gait wants the present, not a backlog.
* ``imu`` and ``heartbeat``: newest only, counted the same way.

A frame already partly written is always finished first, so the byte stream
stays framed. When bytes are waiting and the port accepted none for
``stall_ms``, :attr:`LinkWriter.stalled` is true (the runtime's link fault).

Reading: :class:`LinkReader` reads every byte that is waiting (never waits), at
most :data:`READ_BUDGET` bytes per pass, feeds the frame decoder and returns the
decoded GAIT / COMMAND messages. It reads until the port has nothing more, rather
than the count ``in_waiting`` reports: pyserial's ``socket://`` reports 1 whenever
anything is waiting. Each message comes with the time it was sent, on the runtime's
clock (:class:`SenderClock`), so a context read late counts as old. At most
:data:`MAX_MESSAGES` messages are returned per pass, the newest: an MCU that floods
the link (or a backlog read at once) costs the loop a bounded amount per pass, and
the older messages beyond the bound are dropped and counted (``messages_dropped``).
"""
from __future__ import annotations

import os
import time
from collections import deque

import serial

from device.checks import serial_url
from device.pi import protocol
from device.errors import TacfootError

#: FAULT packets that may wait before newer ones replace the newest waiting one
FAULT_QUEUE = 64
#: kinds in the order they are served
KINDS = ("fault", "status", "surface", "imu", "heartbeat")
#: bytes asked of the port per read
READ_CHUNK = 512
#: bytes read from the port per poll at most (a 100 Hz GAIT stream is ~2 kB/s)
READ_BUDGET = 16384
#: messages handed to the loop per poll at most, the newest: a 921600-baud UART at its
#: fullest carries ~51 COMMANDs (15 bytes each) per pass at 120 passes a second, so a
#: pass five times as long as its period still drops none; a backlog read at once
#: (up to READ_BUDGET, ~1,100 COMMANDs) is cut to this
MAX_MESSAGES = 256


class LinkError(TacfootError, OSError):
    """The serial port cannot be opened."""


def open_port(url: str, baudrate: int = 921600):
    """A pyserial port for a device path or URL (``/dev/serial0``, ``loop://``,
    ``socket://host:port``), opened non-blocking: reads return what is waiting,
    writes take what fits."""
    try:
        port = serial.serial_for_url(serial_url(url), baudrate=baudrate, timeout=0,
                                     write_timeout=0, do_not_open=True)
        if url.startswith("loop://"):
            # loop:// refuses every write when write_timeout is 0; its queue is
            # bounded instead and try_write only offers what fits
            port.write_timeout = None
        port.open()
        if isinstance(getattr(port, "fd", None), int):
            os.set_blocking(port.fd, False)     # pyserial opens O_NONBLOCK; make sure
    except (serial.SerialException, ValueError, OSError) as exc:
        raise LinkError(f"--serial {url!r}: cannot open: {exc}") from None
    return port


def _raw_writer(port):
    """The non-blocking system call under a pyserial port, or None: ``os.write`` on
    a device's file descriptor (opened O_NONBLOCK), ``send`` on a ``socket://``
    socket (non-blocking). Other ports (``loop://``, rfc2217, stand-ins) use their
    ``write``."""
    fd = getattr(port, "fd", None)
    if isinstance(fd, int) and fd >= 0 and type(port).__module__ == "serial.serialposix":
        return lambda data: os.write(fd, data)
    sock = getattr(port, "_socket", None)
    if sock is not None and type(port).__module__ == "serial.urlhandler.protocol_socket":
        return sock.send
    return None


def try_write(port, data) -> int:
    """Write what the port accepts now, never waiting; the count of bytes taken (0
    when none)."""
    raw = _raw_writer(port)
    if raw is not None:
        try:
            return int(raw(data))
        except (BlockingIOError, InterruptedError):
            return 0
    q = getattr(port, "queue", None)          # pyserial loop://: a bounded queue
    if q is not None and getattr(q, "maxsize", 0) > 0:
        room = q.maxsize - q.qsize()
        if room <= 0:
            return 0
        data = data[:room]
    try:
        n = port.write(data)
    except serial.SerialTimeoutException:
        return 0
    except BlockingIOError:
        return 0
    return len(data) if n is None else int(n)


class LinkWriter:
    """Non-blocking writer with the drop / coalesce policy of the module docstring."""

    def __init__(self, port, stall_ms: float = 50.0, clock=time.monotonic):
        self.port = port
        self.stall_s = float(stall_ms) / 1e3
        self.clock = clock
        self._faults: deque = deque()
        self._slots: dict[str, tuple[int, bytes] | None] = {k: None for k in KINDS[1:]}
        self._cur: memoryview | None = None
        self._cur_type = 0
        self._off = 0
        self._last_progress = clock()
        self.packets_sent = 0
        self.packets_dropped = 0
        self.faults_coalesced = 0
        self.bytes_written = 0
        self.write_errors = 0
        self.sent_by_type: dict[int, int] = {}
        #: (clock time, msg_type) of the last packet whose last byte was written
        self.last_sent: tuple[float, int] | None = None

    @property
    def pending(self) -> int:
        """Packets waiting (including one partly written)."""
        return (len(self._faults) + sum(v is not None for v in self._slots.values())
                + (self._cur is not None))

    @property
    def stalled(self) -> bool:
        return (self.pending > 0 and self.clock() - self._last_progress > self.stall_s)

    def send(self, kind: str, msg_type: int, frame: bytes) -> None:
        """Queue one encoded frame of ``kind`` (see :data:`KINDS`)."""
        if not self.pending:
            self._last_progress = self.clock()
        if kind == "fault":
            if len(self._faults) >= FAULT_QUEUE:
                self._faults[-1] = (msg_type, frame)
                self.faults_coalesced += 1
            else:
                self._faults.append((msg_type, frame))
            return
        if kind not in self._slots:
            raise ValueError(f"kind must be one of {list(KINDS)}, got {kind!r}")
        if self._slots[kind] is not None:
            self.packets_dropped += 1
        self._slots[kind] = (msg_type, frame)

    def _next(self) -> bool:
        if self._faults:
            item = self._faults.popleft()
        else:
            item = None
            for k in KINDS[1:]:
                if self._slots[k] is not None:
                    item, self._slots[k] = self._slots[k], None
                    break
        if item is None:
            return False
        self._cur_type, frame = item
        self._cur = memoryview(frame)
        self._off = 0
        return True

    def pump(self) -> int:
        """Write what the port takes now; bytes written."""
        total = 0
        while self._cur is not None or self._next():
            try:
                n = try_write(self.port, self._cur[self._off:])
            except Exception:           # a port that vanished: count, retry next pump
                self.write_errors += 1
                n = 0
            if n <= 0:
                break
            now = self.clock()
            self._last_progress = now
            self._off += n
            total += n
            if self._off >= len(self._cur):
                self.packets_sent += 1
                self.sent_by_type[self._cur_type] = self.sent_by_type.get(self._cur_type, 0) + 1
                self.last_sent = (now, self._cur_type)
                self._cur = None
        self.bytes_written += total
        return total

    def counters(self) -> dict:
        return {"packets_sent": self.packets_sent, "packets_dropped": self.packets_dropped,
                "faults_coalesced": self.faults_coalesced, "bytes_written": self.bytes_written,
                "write_errors": self.write_errors, "pending": self.pending}


class SenderClock:
    """The time a frame was sent, on the local clock, from its header's ``t_ms`` (the
    sender's milliseconds).

    The offset between the two clocks is the smallest (local arrival - sender time)
    seen: the frame that came fastest. It may rise by at most ``drift`` s per s, so
    the estimate follows two crystals drifting apart, while a frame read late by a
    backlog keeps its age. A step of more than ``resync_s`` (the sender restarted,
    or its tick counter wrapped) starts the estimate again. A sender that stamps 0
    has no clock: its frames are taken as sent when they arrive."""

    def __init__(self, drift: float = 1e-3, resync_s: float = 30.0):
        self.drift = float(drift)
        self.resync_s = float(resync_s)
        self.offset: float | None = None
        self._t_last = 0.0

    def sent_at(self, t_ms: int, now: float) -> float:
        if not t_ms:
            return now
        t = t_ms / 1000.0
        sample = now - t
        if self.offset is None or sample < self.offset or sample - self.offset > self.resync_s:
            self.offset = sample
        else:
            self.offset = min(sample, self.offset + self.drift * max(0.0, now - self._t_last))
        self._t_last = now
        return min(now, t + self.offset)


class LinkReader:
    """Reads what is waiting on the port and decodes GAIT / COMMAND messages."""

    def __init__(self, port, max_frame: int = 64, clock=time.monotonic,
                 budget: int = READ_BUDGET, max_messages: int = MAX_MESSAGES):
        self.port = port
        self.protocol = protocol
        self.decoder = protocol.FrameDecoder(max_frame=max_frame)
        self.clock = clock
        self.budget = int(budget)
        self.max_messages = int(max_messages)
        self.sender_clock = SenderClock()
        self.read_errors = 0
        self.bytes_read = 0
        self.messages_dropped = 0       # beyond max_messages in one poll, the oldest

    def _read_waiting(self) -> bytes:
        """Every byte waiting now, up to the budget. ``in_waiting`` is only asked
        whether anything waits; the reads go on until the port gives nothing."""
        got = bytearray()
        while len(got) < self.budget:
            n = self.port.in_waiting
            if not n:
                break
            chunk = self.port.read(min(max(int(n), READ_CHUNK), self.budget - len(got)))
            if not chunk:
                break
            got += chunk
        return bytes(got)

    def poll_timed(self) -> list:
        """[(message, t_sent)]: the decoded messages from the MCU (frames of other
        kinds are skipped), each with the local clock time it was sent; at most
        ``max_messages``, the newest (the older ones are counted in
        ``messages_dropped``)."""
        try:
            data = self._read_waiting()
        except Exception:
            self.read_errors += 1
            return []
        if not data:
            return []
        self.bytes_read += len(data)
        now = self.clock()
        out = []
        for raw in self.decoder.feed(data):
            msg = self.protocol.decode_message(raw)
            if msg is not None:
                out.append((msg, self.sender_clock.sent_at(raw.t_ms, now)))
        if len(out) > self.max_messages:
            self.messages_dropped += len(out) - self.max_messages
            del out[:len(out) - self.max_messages]
        return out
