# tacfoot surface link consumer for the locomotion MCU (MicroPython; runs on CPython).
#
#   link = SurfaceLink(machine.UART(0, 921600), stale_ms=150)
#   while True:
#       link.poll()                    # non-blocking: reads what the UART holds
#       s = link.state()               # latest SurfaceState, s.age_ms, s.stale
#       ...choose a gait preset; if s.stale use the safe default...
#       link.send_gait(PHASE_STANCE, 45.0, (-200, 0, 0))
#
# Message layouts: docs/protocol.md. Values are kept as the integers on the wire
# (fixed point, the scale is in the name: load_n_x100 is hundredths of a newton),
# so polling allocates nothing per byte and no floats on the way in.
from tflink import Decoder, Encoder

from mpcompat import const, ticks_diff, ticks_ms  # noqa: F401

MSG_SURFACE = const(0x01)
MSG_IMU_SUMMARY = const(0x02)
MSG_HEARTBEAT = const(0x03)
MSG_FAULT = const(0x04)
MSG_GAIT = const(0x10)
MSG_COMMAND = const(0x11)

SURFACE_LEN = const(18)
IMU_LEN = const(17)
HEARTBEAT_LEN = const(11)
FAULT_LEN = const(6)
# the Pi -> MCU messages this consumer reads, and the payload each needs
_PAYLOAD_LEN = {MSG_SURFACE: SURFACE_LEN, MSG_IMU_SUMMARY: IMU_LEN,
                MSG_HEARTBEAT: HEARTBEAT_LEN, MSG_FAULT: FAULT_LEN}

CLASS_NO_TOUCH = const(0)
CLASS_HARD = const(1)
CLASS_SOFT = const(2)
CLASS_SLIPPERY = const(3)
CLASS_UNKNOWN = const(255)

PHASE_STANCE = const(0)
PHASE_SWING = const(1)

CMD_REZERO = const(1)
CMD_SET_RATE = const(2)
CMD_REQUEST_STATUS = const(3)
# the frame rates CMD_SET_RATE may ask for: the Pi's bound on every frame rate
# (device/checks.py FPS_MIN_HZ..FPS_MAX_HZ); the Pi ignores any other
RATE_MIN_FPS = const(1)
RATE_MAX_FPS = const(1000)
# CMD_REQUEST_STATUS is sent at most once per this many ms (the default of
# SurfaceLink's status_min_ms): the Pi answers with a HEARTBEAT, which it also sends
# on its own 5 times a second, and a FAULT comes at once on any change anyway
STATUS_MIN_MS = const(50)

FAULT_FRAME = const(0x0080)         # the frame was implausible: its SURFACE says no contact
FAULT_CAMERA = const(0x0100)
FAULT_IMU = const(0x0200)
FAULT_MODEL = const(0x0400)
FAULT_PINS_LOST = const(0x0800)
FAULT_LINK = const(0x1000)
FAULT_CLAMPED = const(0x4000)
FAULT_NONFINITE = const(0x8000)

GAIT_FLAG_CLAMPED = const(1)
GAIT_FLAG_NONFINITE = const(2)


def _u16(b, i):
    return b[i] | (b[i + 1] << 8)


def _i16(b, i):
    v = b[i] | (b[i + 1] << 8)
    return v - 0x10000 if v & 0x8000 else v


def _decoder_count(name):
    """A read-only property: the decoder's counter ``name``."""
    return property(lambda self: getattr(self.decoder, name))


class SurfaceState:
    """The latest SURFACE message, as wire integers. ``valid`` is False until the
    first one arrives; ``stale`` is True when none arrived for ``stale_ms``."""

    def __init__(self):
        self.valid = False
        self.stale = True
        self.age_ms = -1            # -1 until the first SURFACE
        self.rx_ms = 0              # local ticks_ms when it arrived
        self.seq = 0
        self.t_ms = 0               # the Pi's timestamp
        self.class_id = CLASS_UNKNOWN
        self.probs_u8 = bytearray(4)    # class probabilities, 255 = 1.0
        self.contact = False
        self.slip = False
        self.slip_conf_u8 = 0
        self.texture_id = 255
        self.shear_dir_deg_x100 = 0
        self.shear_px_x100 = 0
        self.load_n_x100 = 0        # pressure estimate (normal load)
        self.pins = 0
        self.faults = 0


class SurfaceLink:
    """Non-blocking consumer of the surface link on a machine.UART.

    ``poll()`` reads at most ``max_bytes`` through a fixed buffer and returns the
    number of valid frames processed. Counters: decoder.crc_errors, .too_long,
    .malformed, .newer_version (via properties of the same name), plus
    unknown_type, short_payload and drops (sequence numbers missed)."""

    def __init__(self, uart, stale_ms=150, rx_chunk=64, max_frame=64, clock=None,
                 status_min_ms=STATUS_MIN_MS):
        self.uart = uart
        self.stale_ms = stale_ms
        self.clock = clock if clock is not None else ticks_ms
        self._rx = bytearray(rx_chunk)
        self._tx_payload = bytearray(16)
        self._tx_mv = memoryview(self._tx_payload)
        self.decoder = Decoder(max_frame, self._on_frame)
        self.encoder = Encoder(max_frame)
        self._state = SurfaceState()
        self.tx_seq = 0
        self.unknown_type = 0
        self.short_payload = 0
        self.drops = 0
        self._last_seq = -1
        self._now = 0
        # latest of the other Pi -> MCU messages, as wire integers
        self.fault_bits = 0         # from FAULT (also OR-ed in from HEARTBEAT)
        self.fault_raised = 0
        self.pins_lost = 0
        self.heartbeat_rx_ms = 0
        self.heartbeats = 0
        self.pi_uptime_s = 0
        self.pi_rate_fps_x10 = 0
        self.imu = [0, 0, 0, 0, 0, 0]   # acc mg x, y, z; gyro 0.1 deg/s x, y, z
        self.imu_samples = 0
        self.rates_refused = 0      # CMD_SET_RATE outside RATE_MIN_FPS..RATE_MAX_FPS, not sent
        self.status_min_ms = status_min_ms
        self.status_refused = 0     # CMD_REQUEST_STATUS within status_min_ms of the last, not sent
        self._status_ms = 0         # ticks_ms of the last CMD_REQUEST_STATUS sent
        self._status_sent = False

    # -- counters of the decoder -----------------------------------------------
    frames_ok = _decoder_count("frames_ok")
    crc_errors = _decoder_count("crc_errors")
    too_long = _decoder_count("too_long")
    malformed = _decoder_count("malformed")
    newer_version = _decoder_count("newer_version")

    # -- receiving ----------------------------------------------------------------
    def poll(self, max_bytes=512):
        """Read what the UART holds (up to max_bytes) and decode it."""
        self._now = self.clock()
        done = 0
        got = 0
        rx = self._rx
        while got < max_bytes:
            n = self.uart.readinto(rx)
            if not n:
                break
            got += n
            done += self.decoder.feed(rx, n)
        return done

    def feed(self, buf, n):
        """Decode bytes obtained some other way (an IRQ ring buffer, a test)."""
        self._now = self.clock()
        return self.decoder.feed(buf, n)

    def _on_frame(self, d):
        seq = d.seq
        if self._last_seq >= 0:
            gap = (seq - self._last_seq - 1) & 0xFFFF
            if gap < 1000:
                self.drops += gap
        self._last_seq = seq
        t = d.msg_type
        p = d.payload
        need = _PAYLOAD_LEN.get(t)
        if need is None:
            self.unknown_type += 1
            return
        if d.payload_len < need:
            self.short_payload += 1
            return
        if t == MSG_SURFACE:
            s = self._state
            s.valid = True
            s.rx_ms = self._now
            s.seq = seq
            s.t_ms = d.t_ms
            s.class_id = p[0]
            pr = s.probs_u8
            pr[0] = p[1]
            pr[1] = p[2]
            pr[2] = p[3]
            pr[3] = p[4]
            s.contact = bool(p[5] & 1)
            s.slip = bool(p[5] & 2)
            s.slip_conf_u8 = p[6]
            s.texture_id = p[7]
            s.shear_dir_deg_x100 = _u16(p, 8)
            s.shear_px_x100 = _u16(p, 10)
            s.load_n_x100 = _u16(p, 12)
            s.pins = _u16(p, 14)
            s.faults = _u16(p, 16)
        elif t == MSG_IMU_SUMMARY:
            im = self.imu
            for i in range(6):
                im[i] = _i16(p, 2 * i)
            self.imu_samples = p[14]
        elif t == MSG_HEARTBEAT:
            self.heartbeats += 1
            self.heartbeat_rx_ms = self._now
            self.pi_uptime_s = _u16(p, 0) | (_u16(p, 2) << 16)
            self.pi_rate_fps_x10 = _u16(p, 4)
            self.fault_bits = _u16(p, 9)
        else:                       # MSG_FAULT
            self.fault_bits = _u16(p, 0)
            self.fault_raised = _u16(p, 2)
            self.pins_lost = _u16(p, 4)

    def state(self, now_ms=None):
        """The latest SurfaceState with age_ms and stale brought up to date."""
        s = self._state
        now = self.clock() if now_ms is None else now_ms
        if s.valid:
            s.age_ms = ticks_diff(now, s.rx_ms)
            s.stale = s.age_ms > self.stale_ms or s.age_ms < 0
        else:
            s.stale = True
        return s

    # -- sending ---------------------------------------------------------------------
    def _send(self, msg_type, n):
        wire = self.encoder.frame(msg_type, self.tx_seq, self.clock(), self._tx_mv, n)
        self.tx_seq = (self.tx_seq + 1) & 0xFFFF
        return self.uart.write(wire)

    def send_gait(self, phase, load_n, vel_mm_s):
        """GAIT context: phase (PHASE_STANCE/PHASE_SWING), expected load in N,
        expected foot velocity in mm/s (a number for x, or an (x, y, z) tuple).
        Out-of-range values are clamped and NaN/inf sent as 0, flagged in the
        flags byte; never raises."""
        flags = 0
        b = self._tx_payload
        ph, f = _clamp_int(phase, 0, 1, PHASE_STANCE)
        flags |= f
        b[0] = ph
        q, f = _quant(load_n, 10, 0, 0xFFFF)
        flags |= f
        b[1] = q & 0xFF
        b[2] = q >> 8
        try:
            k = len(vel_mm_s)
        except TypeError:
            k = -1
        for i in range(3):
            if k < 0:
                v = vel_mm_s if i == 0 else 0
            elif i < k:
                v = vel_mm_s[i]
            else:
                v = 0
            q, f = _quant(v, 1, -32768, 32767)
            flags |= f
            q &= 0xFFFF
            b[3 + 2 * i] = q & 0xFF
            b[4 + 2 * i] = q >> 8
        if k >= 0 and k != 3:
            flags |= GAIT_FLAG_NONFINITE    # not an (x, y, z): missing axes sent as 0
        b[9] = flags
        return self._send(MSG_GAIT, 10)

    def send_command(self, command, arg=0):
        """COMMAND: CMD_REZERO, CMD_SET_RATE (arg: frames per second) or
        CMD_REQUEST_STATUS. Values are clamped to the field; never raises. A rate
        outside RATE_MIN_FPS..RATE_MAX_FPS (the Pi's bound) is not sent: it counts
        in rates_refused and 0 is returned. A status request less than
        status_min_ms after the last one sent (by this link's clock) is not sent
        either: it counts in status_refused and 0 is returned."""
        c, _ = _clamp_int(command, 0, 255, 0)
        a, f = _clamp_int(arg, 0, 0xFFFF, 0)
        if c == CMD_SET_RATE and (f or a < RATE_MIN_FPS or a > RATE_MAX_FPS):
            self.rates_refused += 1
            return 0
        if c == CMD_REQUEST_STATUS:
            now = self.clock()
            if self._status_sent and 0 <= ticks_diff(now, self._status_ms) < self.status_min_ms:
                self.status_refused += 1
                return 0
            self._status_sent = True
            self._status_ms = now
        b = self._tx_payload
        b[0] = c
        b[1] = a & 0xFF
        b[2] = a >> 8
        return self._send(MSG_COMMAND, 3)


def _quant(v, scale, lo, hi):
    """round(v * scale) clamped to lo..hi, and GAIT flag bits it earned."""
    try:
        v = float(v)
        if v - v != 0:                  # NaN or inf (the value itself, not v * scale:
            return (0 if lo <= 0 <= hi else lo), GAIT_FLAG_NONFINITE   # a huge finite
        x = v * scale                   # value that overflows is clamped, as on the Pi)
    except (TypeError, ValueError, OverflowError):
        return (0 if lo <= 0 <= hi else lo), GAIT_FLAG_NONFINITE
    if x < lo - 0.5:                    # within half a step of an end: that end, unflagged
        return lo, GAIT_FLAG_CLAMPED
    if x > hi + 0.5:
        return hi, GAIT_FLAG_CLAMPED
    return max(lo, min(hi, int(round(x)))), 0


def _clamp_int(v, lo, hi, default):
    try:
        x = int(v)
    except (TypeError, ValueError, OverflowError):
        return default, GAIT_FLAG_NONFINITE
    if x < lo:
        return lo, GAIT_FLAG_CLAMPED
    if x > hi:
        return hi, GAIT_FLAG_CLAMPED
    return x, 0
