"""Wire protocol v1: the surface link (Pi <-> gait MCU) and the framing the rig
link shares. The byte tables are in docs/protocol.md; this module is the CPython
side (device/micropython/tflink.py is the MicroPython side).

    frame  = COBS(header + payload + crc) + b"\\x00"
    header = version u8 | msg_type u8 | seq u16 | t_ms u32      (little-endian)
    crc    = CRC-16/CCITT-FALSE over header + payload, u16 little-endian

Nothing on the hot path raises: encoding clamps out-of-range values (NaN/inf
become 0 and set a fault bit), and :class:`FrameDecoder` skips and counts every
kind of bad input (CRC errors, over-long frames, broken COBS, newer versions,
unknown types). Only pure standard library, so the host monitor and the rig code
can import it without numpy.
"""
from __future__ import annotations

import binascii
import enum
import math
import struct
from dataclasses import dataclass

from device.pi.faults import (FAULT_BAD_FRAME, FAULT_CAMERA, FAULT_CLAMPED,  # noqa: F401  (the wire's fault bits)
                              FAULT_FRAME_SIZE_CHANGED, FAULT_IMU, FAULT_LINK, FAULT_LOCALISER,
                              FAULT_MODEL, FAULT_NAMES, FAULT_NO_DOME, FAULT_NO_REFERENCE,
                              FAULT_NONFINITE, FAULT_PINS_LOST, FAULT_TOO_FEW_PINS, fault_names)

VERSION = 1
HEADER = struct.Struct("<BBHI")
HEADER_LEN = HEADER.size          # 8
CRC_LEN = 2
MIN_FRAME = HEADER_LEN + CRC_LEN  # a frame with an empty payload
MAX_FRAME = 64                    # decoded bytes (header + payload + crc)


class MsgType(enum.IntEnum):
    """The surface link's message types: 0x01-0x0F Pi -> MCU, 0x10-0x1F MCU -> Pi
    (0x20-0x3F are the rig link's, host/rig/link.py). Each has one class below."""
    SURFACE = 0x01
    IMU_SUMMARY = 0x02
    HEARTBEAT = 0x03
    FAULT = 0x04
    GAIT = 0x10
    COMMAND = 0x11


SURFACE_CLASSES = ("no-touch", "hard", "soft", "slippery")   # class_id 0..3
CLASS_UNKNOWN = 0xFF
TEXTURE_NONE = 0xFF

PHASE_STANCE = 0
PHASE_SWING = 1
GAIT_FLAG_CLAMPED = 1
GAIT_FLAG_NONFINITE = 2

CMD_REZERO = 1
CMD_SET_RATE = 2
CMD_REQUEST_STATUS = 3
COMMAND_NAMES = {CMD_REZERO: "rezero", CMD_SET_RATE: "set_rate",
                 CMD_REQUEST_STATUS: "request_status"}


# -- CRC and COBS ----------------------------------------------------------------

def _crc_table() -> tuple[int, ...]:
    table = []
    for i in range(256):
        c = i << 8
        for _ in range(8):
            c = ((c << 1) ^ 0x1021) if c & 0x8000 else (c << 1)
        table.append(c & 0xFFFF)
    return tuple(table)


_CRC_TABLE = _crc_table()


def crc16(data, crc: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, xorout 0): the CRC
    binascii.crc_hqx computes, from the given start value."""
    if isinstance(data, (bytes, bytearray, memoryview)):
        return binascii.crc_hqx(data, crc)
    t = _CRC_TABLE
    for b in data:
        crc = ((crc << 8) & 0xFFFF) ^ t[((crc >> 8) ^ b) & 0xFF]
    return crc


def cobs_encode(data) -> bytes:
    """COBS-encode ``data`` (no zero bytes in the result; the delimiter is not added)."""
    data = bytes(data)
    if len(data) < 0xFE:
        # no block can reach 254 bytes: each zero ends a block, coded by its length + 1
        out = bytearray()
        for block in data.split(b"\x00"):
            out.append(len(block) + 1)
            out += block
        return bytes(out)
    out = bytearray([0])
    code_at, code = 0, 1
    last = len(data) - 1
    for i, b in enumerate(data):
        if b == 0:
            out[code_at] = code
            code_at, code = len(out), 1
            out.append(0)
            continue
        out.append(b)
        code += 1
        if code == 0xFF:
            out[code_at] = code
            if i == last:               # a full block at the end: no empty block after it
                return bytes(out)
            code_at, code = len(out), 1
            out.append(0)
    out[code_at] = code
    return bytes(out)


def cobs_decode(data) -> bytes:
    """Invert :func:`cobs_encode`. Raises ValueError naming the offset on bad input."""
    data = bytes(data)
    out = bytearray()
    i, n = 0, len(data)
    while i < n:
        code = data[i]
        if code == 0:
            raise ValueError(f"cobs: zero byte at offset {i}")
        end = i + code
        if end > n:
            raise ValueError(f"cobs: block at offset {i} (code {code}) runs past the end ({n})")
        block = data[i + 1:end]
        if 0 in block:
            raise ValueError(f"cobs: zero byte inside the block at offset {i}")
        out += block
        i = end
        if code != 0xFF and i < n:
            out.append(0)
    return bytes(out)


def encode_frame(msg_type: int, payload: bytes, seq: int, t_ms: int) -> bytes:
    """Wire bytes of one frame, delimiter included. seq and t_ms wrap (u16, u32);
    a bad msg_type or an over-long payload is a programming error (ValueError)."""
    if not 0 <= int(msg_type) <= 0xFF:
        raise ValueError(f"msg_type must be 0..255, got {msg_type!r}")
    body = HEADER.pack(VERSION, int(msg_type), int(seq) & 0xFFFF, int(t_ms) & 0xFFFFFFFF)
    body += bytes(payload)
    if len(body) + CRC_LEN > MAX_FRAME:
        raise ValueError(f"payload of {len(payload)} bytes makes a {len(body) + CRC_LEN}-byte "
                         f"frame (at most {MAX_FRAME})")
    body += struct.pack("<H", crc16(body))
    return cobs_encode(body) + b"\x00"


# -- decoding --------------------------------------------------------------------

@dataclass(frozen=True)
class RawFrame:
    version: int
    msg_type: int
    seq: int
    t_ms: int
    payload: bytes


class FrameDecoder:
    """Stream decoder: ``feed(bytes)`` returns the frames completed by those bytes.

    Never raises on any input. Bad frames are dropped and counted:
    ``crc_errors``, ``too_long`` (more than ``max_frame`` decoded bytes),
    ``malformed`` (broken COBS, shorter than a header + CRC, version 0),
    ``newer_version`` (version > 1), ``unknown_type`` (a type outside ``known_types``,
    when given). ``drops`` counts sequence numbers skipped between good frames
    (gaps of more than ``max_gap`` are treated as a sender restart, ``restarts``).
    A decoder resynchronises at the next 0x00.
    """

    def __init__(self, max_frame: int = MAX_FRAME, known_types=None, max_gap: int = 1000):
        self.max_frame = int(max_frame)
        # COBS adds one byte per 254; anything longer than this cannot fit
        self._max_wire = self.max_frame + self.max_frame // 254 + 1
        self.known_types = None if known_types is None else frozenset(known_types)
        self.max_gap = int(max_gap)
        self._buf = bytearray()
        self._overflow = False
        self.frames_ok = self.crc_errors = self.too_long = self.malformed = 0
        self.newer_version = self.unknown_type = self.drops = self.restarts = 0
        self.bytes_in = 0
        self._last_seq = None

    @property
    def counters(self) -> dict:
        return {k: getattr(self, k) for k in ("frames_ok", "crc_errors", "too_long", "malformed",
                                              "newer_version", "unknown_type", "drops",
                                              "restarts", "bytes_in")}

    def feed(self, data) -> list[RawFrame]:
        out = []
        data = bytes(data)
        self.bytes_in += len(data)
        start = 0
        while True:
            z = data.find(0, start)
            chunk = data[start:] if z < 0 else data[start:z]
            if not self._overflow:
                if len(self._buf) + len(chunk) > self._max_wire:
                    self._overflow = True
                    self._buf.clear()
                else:
                    self._buf += chunk
            if z < 0:
                return out
            self._end_frame(out)
            start = z + 1

    def _end_frame(self, out: list) -> None:
        if self._overflow:
            self.too_long += 1
            self._overflow = False
            return
        if not self._buf:
            return                       # back-to-back delimiters: nothing to count
        try:
            body = cobs_decode(self._buf)
        except ValueError:
            self.malformed += 1
            self._buf.clear()
            return
        self._buf.clear()
        if len(body) > self.max_frame:
            self.too_long += 1
            return
        if len(body) < MIN_FRAME:
            self.malformed += 1
            return
        if crc16(body[:-CRC_LEN]) != (body[-2] | (body[-1] << 8)):
            self.crc_errors += 1
            return
        version, msg_type, seq, t_ms = HEADER.unpack_from(body)
        if version > VERSION:
            self.newer_version += 1
            return
        if version < 1:
            self.malformed += 1
            return
        if self.known_types is not None and msg_type not in self.known_types:
            self.unknown_type += 1
            return
        self.frames_ok += 1
        if self._last_seq is not None:
            gap = (seq - self._last_seq - 1) & 0xFFFF
            if gap > self.max_gap:
                self.restarts += 1
            else:
                self.drops += gap
        self._last_seq = seq
        out.append(RawFrame(version, msg_type, seq, t_ms, body[HEADER_LEN:-CRC_LEN]))


# -- quantisation helpers (never raise) ---------------------------------------------

def _quant(value, scale: float, lo: int, hi: int) -> tuple[int, int]:
    """round(value * scale) clamped to lo..hi, and the fault bits it earned. A value
    within half a step of an end is that end, not clamped (a probability of
    1.0000000000000002 is 255, as 1.0 is)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        return max(lo, min(hi, 0)), FAULT_NONFINITE
    if not math.isfinite(v):
        return max(lo, min(hi, 0)), FAULT_NONFINITE
    q = v * scale
    if q < lo - 0.5:
        return lo, FAULT_CLAMPED
    if q > hi + 0.5:
        return hi, FAULT_CLAMPED
    return max(lo, min(hi, int(round(q)))), 0


def _int_field(value, lo: int, hi: int, default: int) -> tuple[int, int]:
    try:
        v = int(value)
    except (TypeError, ValueError, OverflowError):
        return default, FAULT_NONFINITE
    if v < lo:
        return lo, FAULT_CLAMPED
    if v > hi:
        return hi, FAULT_CLAMPED
    return v, 0


def _wrap_deg(value) -> tuple[int, int]:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return 0, FAULT_NONFINITE
    if not math.isfinite(v):
        return 0, FAULT_NONFINITE
    return int(round((v % 360.0) * 100.0)) % 36000, 0


class _Fields:
    """Quantises one message's fields, OR-ing the fault bits each earns into
    ``faults`` (the wire's FAULT_CLAMPED / FAULT_NONFINITE)."""
    __slots__ = ("faults",)

    def __init__(self):
        self.faults = 0

    def _keep(self, qe: tuple[int, int]) -> int:
        self.faults |= qe[1]
        return qe[0]

    def num(self, value, scale: float, lo: int, hi: int) -> int:
        return self._keep(_quant(value, scale, lo, hi))

    def whole(self, value, lo: int, hi: int, default: int = 0) -> int:
        return self._keep(_int_field(value, lo, hi, default))

    def deg(self, value) -> int:
        return self._keep(_wrap_deg(value))

    def nums(self, values, n: int, scale: float, lo: int, hi: int,
             scalar_is_first: bool = False) -> list[int]:
        """``n`` values of a sequence; a shorter or longer one, or no sequence, is
        padded with 0 and flagged (with ``scalar_is_first`` a lone number is the
        first value, the rest 0, unflagged)."""
        if _is_seq(values):
            v = list(values)
        else:
            v = [values] + [0.0] * (n - 1) if scalar_is_first else []
        if len(v) != n:
            self.faults |= FAULT_NONFINITE
            v = (v[:n] + [0.0] * n)[:n]
        return [self.num(x, scale, lo, hi) for x in v]


# -- typed messages ------------------------------------------------------------

class Message:
    """A typed message: a dataclass of its fields, registered by :func:`message`
    with its ``msg_type`` (a :class:`MsgType`), its ``name`` and its payload
    ``layout`` (a ``struct.Struct``). A subclass writes ``pack`` (never raises:
    clamps and flags) and ``unpack`` (a payload of at least ``layout.size`` bytes)."""
    msg_type: MsgType
    name: str
    layout: struct.Struct

    def encode(self, seq: int, t_ms: int) -> bytes:
        """Wire bytes of this message (delimiter included); never raises."""
        return encode_frame(self.msg_type, self.pack(), seq, t_ms)

    @classmethod
    def decode(cls, payload: bytes):
        """This message from ``payload``, or None when it is shorter than the layout
        (extra trailing bytes are ignored: room for v1 additions). Never raises."""
        if len(payload) < cls.layout.size:
            return None
        return cls.unpack(payload)

    def names(self) -> dict:
        """Names of coded fields, for :func:`message_dict` (none by default)."""
        return {}


MESSAGES: dict[MsgType, type[Message]] = {}     # the one table, filled by @message


def message(msg_type: MsgType, layout: str):
    """Class decorator: give a message class its type, name and payload layout and
    record it in :data:`MESSAGES` (one class per type)."""
    msg_type = MsgType(msg_type)

    def register(cls):
        if msg_type in MESSAGES:
            raise ValueError(f"msg_type {msg_type.name} (0x{msg_type:02X}) already has "
                             f"class {MESSAGES[msg_type].__name__}, not {cls.__name__}")
        cls.msg_type, cls.name, cls.layout = msg_type, msg_type.name.lower(), struct.Struct(layout)
        MESSAGES[msg_type] = cls
        return cls
    return register


@message(MsgType.SURFACE, "<BBBBBBBBHHHHH")        # 18 bytes
@dataclass
class Surface(Message):
    """SURFACE (0x01, Pi -> MCU): the surface decision for one window."""
    class_id: int = CLASS_UNKNOWN                # 0..3 (SURFACE_CLASSES), 255 unknown
    probs: tuple = (0.0, 0.0, 0.0, 0.0)          # class probabilities 0..1, sent as u8/255
    contact: bool = False
    slip: bool = False
    slip_conf: float = 0.0                       # 0..1, sent as u8/255
    shear_dir_deg: float = 0.0                   # 0..360, sent in 0.01 deg
    shear_px: float = 0.0                        # |average vector|, 0..655.35 px, 0.01 px
    load_n: float = 0.0                          # pressure estimate (normal load), 0.01 N
    pins: int = 0                                # pins found, 0..65535
    faults: int = 0                              # fault bits (u16)
    texture_id: int = TEXTURE_NONE               # 0..254, 255 none

    def pack(self) -> bytes:
        k = _Fields()
        cid = k.whole(self.class_id, 0, 255, CLASS_UNKNOWN)
        probs = k.nums(self.probs, 4, 255.0, 0, 255)
        flags = (1 if _truthy(self.contact) else 0) | (2 if _truthy(self.slip) else 0)
        conf = k.num(self.slip_conf, 255.0, 0, 255)
        tex = k.whole(self.texture_id, 0, 255, TEXTURE_NONE)
        rest = (k.deg(self.shear_dir_deg), k.num(self.shear_px, 100.0, 0, 0xFFFF),
                k.num(self.load_n, 100.0, 0, 0xFFFF), k.whole(self.pins, 0, 0xFFFF))
        faults = k.whole(self.faults, 0, 0xFFFF)
        return self.layout.pack(cid, *probs, flags, conf, tex, *rest, faults | k.faults)

    @classmethod
    def unpack(cls, p: bytes) -> "Surface":
        cid, p0, p1, p2, p3, flags, conf, tex, d, mag, load, pins, faults = cls.layout.unpack_from(p)
        return cls(cid, (p0 / 255, p1 / 255, p2 / 255, p3 / 255), bool(flags & 1),
                   bool(flags & 2), conf / 255, d / 100, mag / 100, load / 100, pins, faults, tex)

    @property
    def class_name(self) -> str:
        c = self.class_id
        return SURFACE_CLASSES[c] if isinstance(c, int) and 0 <= c < 4 else "unknown"

    def names(self) -> dict:
        return {"class_name": self.class_name}


@message(MsgType.IMU_SUMMARY, "<hhhhhhHBH")        # 17 bytes
@dataclass
class ImuSummary(Message):
    """IMU summary (0x02, Pi -> MCU): means over the window, in mg and 0.1 deg/s."""
    acc_mg: tuple = (0.0, 0.0, 0.0)              # mean acceleration, mg, i16
    gyro_dps: tuple = (0.0, 0.0, 0.0)            # mean rate, deg/s, sent in 0.1 deg/s, i16
    acc_peak_mg: float = 0.0                     # peak |a| in the window, mg, u16
    samples: int = 0                             # samples averaged, 0..255
    faults: int = 0

    def pack(self) -> bytes:
        k = _Fields()
        acc = k.nums(self.acc_mg, 3, 1.0, -32768, 32767)
        gyro = k.nums(self.gyro_dps, 3, 10.0, -32768, 32767)
        peak = k.num(self.acc_peak_mg, 1.0, 0, 0xFFFF)
        n = k.whole(self.samples, 0, 255)
        faults = k.whole(self.faults, 0, 0xFFFF)
        return self.layout.pack(*acc, *gyro, peak, n, faults | k.faults)

    @classmethod
    def unpack(cls, p: bytes) -> "ImuSummary":
        ax, ay, az, gx, gy, gz, peak, n, faults = cls.layout.unpack_from(p)
        return cls((float(ax), float(ay), float(az)), (gx / 10, gy / 10, gz / 10), float(peak),
                   n, faults)


@message(MsgType.HEARTBEAT, "<IHHbH")        # 11 bytes
@dataclass
class Heartbeat(Message):
    """HEARTBEAT (0x03, Pi -> MCU), about once a second."""
    uptime_s: int = 0                            # u32
    rate_fps: float = 0.0                        # camera frame rate, sent in 0.1 fps
    frames_dropped: int = 0                      # u16, saturates
    temp_c: int = -128                           # CPU temperature, i8, -128 unknown
    faults: int = 0

    def pack(self) -> bytes:
        k = _Fields()
        up = k.whole(self.uptime_s, 0, 0xFFFFFFFF)
        rate = k.num(self.rate_fps, 10.0, 0, 0xFFFF)
        dropped = k.whole(self.frames_dropped, 0, 0xFFFF)
        temp = k.num(self.temp_c, 1.0, -128, 127)
        faults = k.whole(self.faults, 0, 0xFFFF)
        return self.layout.pack(up, rate, dropped, temp, faults | k.faults)

    @classmethod
    def unpack(cls, p: bytes) -> "Heartbeat":
        up, rate, dropped, temp, faults = cls.layout.unpack_from(p)
        return cls(up, rate / 10, dropped, temp, faults)


@message(MsgType.FAULT, "<HHH")        # 6 bytes
@dataclass
class Fault(Message):
    """FAULT (0x04, Pi -> MCU): sent when a fault is raised or cleared."""
    faults: int = 0                              # bits active now
    raised: int = 0                              # bits that became active since the last FAULT
    pins_lost: int = 0                           # reference pins not found, u16

    def pack(self) -> bytes:
        k = _Fields()
        faults = k.whole(self.faults, 0, 0xFFFF)
        raised = k.whole(self.raised, 0, 0xFFFF)
        lost = k.whole(self.pins_lost, 0, 0xFFFF)
        return self.layout.pack(faults | k.faults, raised, lost)

    @classmethod
    def unpack(cls, p: bytes) -> "Fault":
        return cls(*cls.layout.unpack_from(p))


@message(MsgType.GAIT, "<BHhhhB")        # 10 bytes
@dataclass
class Gait(Message):
    """GAIT context (0x10, MCU -> Pi): what the gait expects of this foot."""
    phase: int = PHASE_STANCE                    # 0 stance, 1 swing
    load_n: float = 0.0                          # expected normal load, 0..6553.5 N in 0.1 N
    vel_mm_s: tuple = (0.0, 0.0, 0.0)            # expected foot velocity x, y, z, mm/s, i16
    flags: int = 0                               # GAIT_FLAG_CLAMPED | GAIT_FLAG_NONFINITE

    def pack(self) -> bytes:
        k = _Fields()
        phase = k.whole(self.phase, 0, 1, PHASE_STANCE)
        load = k.num(self.load_n, 10.0, 0, 0xFFFF)
        vel = k.nums(self.vel_mm_s, 3, 1.0, -32768, 32767, scalar_is_first=True)
        flags, _ = _int_field(self.flags, 0, 255, 0)
        flags |= (GAIT_FLAG_CLAMPED if k.faults & FAULT_CLAMPED else 0) | \
                 (GAIT_FLAG_NONFINITE if k.faults & FAULT_NONFINITE else 0)
        return self.layout.pack(phase, load, *vel, flags)

    @classmethod
    def unpack(cls, p: bytes) -> "Gait":
        phase, load, vx, vy, vz, flags = cls.layout.unpack_from(p)
        return cls(phase, load / 10, (float(vx), float(vy), float(vz)), flags)


@message(MsgType.COMMAND, "<BH")        # 3 bytes
@dataclass
class Command(Message):
    """COMMAND (0x11, MCU -> Pi): re-zero, set rate (fps) or request status."""
    command: int = CMD_REQUEST_STATUS
    arg: int = 0                                 # CMD_SET_RATE: frames per second; else 0

    def pack(self) -> bytes:
        cmd, _ = _int_field(self.command, 0, 255, 0)
        arg, _ = _int_field(self.arg, 0, 0xFFFF, 0)
        return self.layout.pack(cmd, arg)

    @classmethod
    def unpack(cls, p: bytes) -> "Command":
        return cls(*cls.layout.unpack_from(p))

    def names(self) -> dict:
        return {"command_name": COMMAND_NAMES.get(self.command, "unknown")}


SURFACE_LINK_TYPES = frozenset(MsgType)


def decode_message(frame: RawFrame):
    """The typed message in ``frame``, or None for an unknown type or a payload
    shorter than its layout (:meth:`Message.decode`). Never raises."""
    cls = MESSAGES.get(frame.msg_type)
    return None if cls is None else cls.decode(frame.payload)


def message_dict(msg: Message) -> dict:
    """A JSON-ready dict of a typed message (fault bits also by name)."""
    d = {"type": msg.name}
    for k, v in msg.__dict__.items():
        d[k] = list(v) if isinstance(v, tuple) else v
    d.update(msg.names())
    for k in ("faults", "raised"):
        if k in d:
            d[k + "_names"] = fault_names(d[k])
    return d


def _is_seq(v) -> bool:
    return isinstance(v, (tuple, list)) or (hasattr(v, "__len__") and hasattr(v, "__iter__")
                                            and not isinstance(v, (str, bytes)))


def _truthy(v) -> bool:
    try:
        return bool(v)
    except Exception:
        return False
