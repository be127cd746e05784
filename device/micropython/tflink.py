# tacfoot wire framing v1, MicroPython side (runs unchanged on CPython).
#
#   frame  = COBS(header + payload + crc) + 0x00
#   header = version u8 | msg_type u8 | seq u16 | t_ms u32   (little-endian)
#   crc    = CRC-16/CCITT-FALSE over header + payload, u16 little-endian
#
# The byte tables are in docs/protocol.md; device/pi/protocol.py is the CPython
# side. Everything here works in buffers allocated once in the constructor: the
# decoder undoes COBS byte by byte as bytes arrive (no per-byte allocation), so a
# frame is checked the moment its 0x00 delimiter arrives.
from array import array

from mpcompat import const

VERSION = const(1)
HEADER_LEN = const(8)
CRC_LEN = const(2)
MIN_FRAME = const(10)
MAX_FRAME = const(64)


def _make_table():
    t = array("H", [0] * 256)
    for i in range(256):
        c = i << 8
        for _ in range(8):
            if c & 0x8000:
                c = ((c << 1) ^ 0x1021) & 0xFFFF
            else:
                c = (c << 1) & 0xFFFF
        t[i] = c
    return t


_TABLE = _make_table()


def crc16(buf, n, crc=0xFFFF):
    """CRC-16/CCITT-FALSE of buf[0:n], continuing from ``crc``."""
    t = _TABLE
    crc &= 0xFFFF
    for i in range(n):
        # crc >> 8 and buf[i] are both < 256, so the index needs no mask
        crc = ((crc << 8) & 0xFFFF) ^ t[(crc >> 8) ^ buf[i]]
    return crc


class Encoder:
    """Builds wire frames in preallocated buffers. ``frame()`` returns a memoryview
    of the encoded bytes (delimiter included), valid until the next call."""

    def __init__(self, max_frame=MAX_FRAME):
        self.max_frame = max_frame
        self._raw = bytearray(max_frame)
        self._out = bytearray(max_frame + max_frame // 254 + 2)
        self._out_mv = memoryview(self._out)

    def frame(self, msg_type, seq, t_ms, payload_mv, n):
        raw = self._raw
        if n < 0 or HEADER_LEN + n + CRC_LEN > self.max_frame:
            raise ValueError("payload length %d: frame would exceed %d bytes" % (n, self.max_frame))
        raw[0] = VERSION
        raw[1] = msg_type & 0xFF
        raw[2] = seq & 0xFF
        raw[3] = (seq >> 8) & 0xFF
        raw[4] = t_ms & 0xFF
        raw[5] = (t_ms >> 8) & 0xFF
        raw[6] = (t_ms >> 16) & 0xFF
        raw[7] = (t_ms >> 24) & 0xFF
        for i in range(n):
            raw[HEADER_LEN + i] = payload_mv[i]
        m = HEADER_LEN + n
        c = crc16(raw, m)
        raw[m] = c & 0xFF
        raw[m + 1] = c >> 8
        m += CRC_LEN
        # COBS
        out = self._out
        code_at = 0
        code = 1
        j = 1
        for i in range(m):
            b = raw[i]
            if b == 0:
                out[code_at] = code
                code_at = j
                j += 1
                code = 1
            else:
                out[j] = b
                j += 1
                code += 1
                if code == 0xFF and i < m - 1:
                    out[code_at] = code
                    code_at = j
                    j += 1
                    code = 1
        out[code_at] = code
        out[j] = 0
        return self._out_mv[:j + 1]


class Decoder:
    """Non-blocking stream decoder. ``feed(buf, n)`` takes buf[0:n] and returns
    how many valid frames completed. After each valid frame ``on_frame(self)`` is
    called (if given); the latest valid frame stays in .msg_type, .seq, .t_ms,
    .payload (memoryview, valid until the next feed) and .payload_len.

    Never raises on any bytes. Bad frames are dropped and counted: crc_errors,
    too_long (more than max_frame decoded bytes), malformed (COBS broken by the
    delimiter, or shorter than header + CRC, or version 0), newer_version."""

    def __init__(self, max_frame=MAX_FRAME, on_frame=None):
        self.max_frame = max_frame
        self.on_frame = on_frame
        self._buf = bytearray(max_frame)
        self._mv = memoryview(self._buf)
        self._n = 0          # decoded bytes so far
        self._rem = 0        # bytes left in the current COBS block
        self._code = 0x100   # code of the current block; 0x100: none yet this frame
        self.frames_ok = 0
        self.crc_errors = 0
        self.too_long = 0
        self.malformed = 0
        self.newer_version = 0
        self.msg_type = 0
        self.seq = 0
        self.t_ms = 0
        self.payload_len = 0
        self.payload = self._mv[HEADER_LEN:HEADER_LEN]

    def reset(self):
        """Forget a partly received frame."""
        self._n = 0
        self._rem = 0
        self._code = 0x100

    def feed(self, buf, n):
        done = 0
        out = self._buf
        cap = self.max_frame
        k = self._n          # decoded bytes so far; k > cap means "too long"
        rem = self._rem
        code = self._code
        for i in range(n):
            b = buf[i]
            if rem and b:                        # a data byte (the common case)
                rem -= 1
                if k < cap:
                    out[k] = b
                    k += 1
                elif k == cap:                   # one past: marks the frame too long
                    k += 1
            elif b:                              # a code byte starts a block
                if code < 0xFF:                  # the previous block implied a zero
                    if k < cap:
                        out[k] = 0
                        k += 1
                    elif k == cap:
                        k += 1
                code = b
                rem = b - 1
            else:                                # the delimiter
                if k > cap:
                    self.too_long += 1
                elif rem:
                    self.malformed += 1          # the frame ended inside a block
                elif code != 0x100:              # not an idle 0x00
                    done += self._finish(k)
                k = 0
                rem = 0
                code = 0x100
        self._n = k
        self._rem = rem
        self._code = code
        return done

    def _finish(self, k):
        b = self._buf
        if k < MIN_FRAME:
            self.malformed += 1
            return 0
        m = k - CRC_LEN
        if crc16(b, m) != (b[m] | (b[m + 1] << 8)):
            self.crc_errors += 1
            return 0
        if b[0] > VERSION:
            self.newer_version += 1
            return 0
        if b[0] == 0:
            self.malformed += 1
            return 0
        self.msg_type = b[1]
        self.seq = b[2] | (b[3] << 8)
        self.t_ms = b[4] | (b[5] << 8) | (b[6] << 16) | (b[7] << 24)
        self.payload_len = m - HEADER_LEN
        self.payload = self._mv[HEADER_LEN:m]
        self.frames_ok += 1
        if self.on_frame is not None:
            self.on_frame(self)
        return 1
