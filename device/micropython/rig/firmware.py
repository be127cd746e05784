"""RP2040 firmware of the data-collection rig (docs/rig.md).

The rig's command loop: homing and soft limits on the z stepper, presses and
drags, the run state and its supervision, and a command link in the surface
link's framing. The axes and the load cell are the drivers in
:mod:`rig.drivers`; the IMU is the shared MPU6050 driver. Hardware comes in
through the constructors (``main.py`` builds the real ``machine`` objects), and
time comes in through ``Rig.poll(now_us)``, so the tests step the firmware
without real time, on MicroPython and on CPython alike.

Positions are integers: micrometres on the wire, steps inside the stepper; loads
are millinewtons. The link allocates nothing per byte.
"""

from mpcompat import const, ticks_diff  # noqa: F401
from tflink import Decoder, Encoder      # the surface link's framing (device/micropython)

# -- message types (0x20-0x3F, the rig link's range) ----------------------------------
# host -> rig
HOME = const(0x21)
MOVE_TO = const(0x22)
PRESS = const(0x23)
DRAG = const(0x24)
LIFT = const(0x25)
READ = const(0x26)
STREAM = const(0x27)
STOP = const(0x28)
PING = const(0x29)
# rig -> host
ACK = const(0x30)
NAK = const(0x31)
DONE = const(0x32)
PONG = const(0x33)
SAMPLE = const(0x34)

# NAK reasons
R_OUT_OF_RANGE = const(1)
R_NOT_HOMED = const(2)
R_BUSY = const(3)
R_BAD_PAYLOAD = const(4)
R_UNKNOWN = const(5)
R_ESTOP = const(6)

# DONE results
OK = const(0)
STOPPED = const(1)
LIMIT = const(2)
LINK_LOST = const(3)
TIMEOUT = const(4)
ESTOPPED = const(5)
HOME_FAILED = const(6)

# states
IDLE = const(0)
HOMING = const(1)
MOVING = const(2)
PRESSING = const(3)
DRAGGING = const(4)
ESTOP = const(5)

# SAMPLE flags
F_HOMED = const(1)
F_MOVING = const(2)
F_CONTACT = const(4)
F_ESTOP = const(8)
F_IMU_FAULT = const(16)
F_LOAD_FAULT = const(32)
F_LIMIT = const(64)

PRESS_DEPTH = const(0)
PRESS_LOAD = const(1)

#: expected payload length per command (-1: any)
_CMD_LEN = {HOME: 0, MOVE_TO: 8, PRESS: 10, DRAG: 8, LIFT: 4, READ: 0, STREAM: 2, STOP: 0,
            PING: 4}


def put_u16(b, o, v):
    b[o] = v & 0xFF
    b[o + 1] = (v >> 8) & 0xFF


def put_i32(b, o, v):
    v &= 0xFFFFFFFF
    b[o] = v & 0xFF
    b[o + 1] = (v >> 8) & 0xFF
    b[o + 2] = (v >> 16) & 0xFF
    b[o + 3] = (v >> 24) & 0xFF


def get_u16(b, o):
    return b[o] | (b[o + 1] << 8)


def get_u32(b, o):
    return b[o] | (b[o + 1] << 8) | (b[o + 2] << 16) | (b[o + 3] << 24)


def get_i32(b, o):
    v = get_u32(b, o)
    return v - 0x100000000 if v & 0x80000000 else v


def _clamp16(v):
    return -32768 if v < -32768 else (32767 if v > 32767 else v)


# -- the rig -------------------------------------------------------------------------------
class Rig:
    """Command handling, motion supervision and sample streaming.

    stream:       the link, with readinto(buf) -> n or None and write(buf)
    stepper:      Stepper (z)
    motor:        DCMotor (x)
    load:         HX711 or AdcLoad
    imu:          object with read() -> (ax, ay, az g, gx, gy, gz dps, temp_c), or None
    home_switch:  Pin, reads 1 when the carriage is at the top switch
    estop:        Pin, reads 1 while the emergency stop is pressed (or None)
    wdt_factory:  callable returning a started machine.WDT (called at the first motion)
    """

    def __init__(self, stream, stepper, motor, load, imu=None, home_switch=None, estop=None,
                 wdt_factory=None, travel_mm=40, speed_mm_s=10, home_speed_mm_s=5,
                 touch_mn=50, link_timeout_ms=1000, max_frame=64):
        self.stream = stream
        self.z = stepper
        self.x = motor
        self.load = load
        self.imu = imu
        self.home_switch = home_switch
        self.estop_pin = estop
        self.wdt_factory = wdt_factory
        self.wdt = None
        spm = stepper.steps_per_mm
        self.travel_steps = travel_mm * spm
        self.travel_um = travel_mm * 1000
        self.speed_steps = speed_mm_s * spm
        self.home_speed_steps = home_speed_mm_s * spm
        self.max_speed_um_s = motor.max_speed_um_s
        self.touch_mn = touch_mn
        self.link_timeout_us = link_timeout_ms * 1000
        self.homed = False
        self.state = IDLE
        self.cmd_type = 0         # the motion command in progress
        self.cmd_seq = 0
        self.press_mode = 0
        self.press_target = 0     # um past contact, or mN
        self.press_speed = 0
        self.contact_z = -1       # steps where the last press touched
        self.load_mn = 0
        self.stream_period_us = 0
        self._stream_left_us = 0
        self.t_ms = 0             # rig clock
        self._t_us = 0            # sub-millisecond part of the rig clock
        self._last_us = None
        self._last_rx_ms = 0
        self._tx_seq = 0
        self.link_lost = 0        # times the link timed out during a motion
        self.imu_faults = 0
        self._imu = (0, 0, 0, 0, 0, 0)
        self._rxbuf = bytearray(64)
        self._rx_mv = memoryview(self._rxbuf)
        self._pl = bytearray(48)
        self._pl_mv = memoryview(self._pl)
        self.enc = Encoder(max_frame)
        self.dec = Decoder(max_frame, on_frame=self._on_frame)

    # -- time and the main loop ----------------------------------------------------------
    def poll(self, now_us):
        """One pass of the main loop: read the link, run the axes, supervise, stream."""
        if self._last_us is None:
            self._last_us = now_us
        dt = ticks_diff(now_us, self._last_us)
        self._last_us = now_us
        if dt < 0:
            dt = 0
        if dt > 50000:            # a long gap (a stall): do not jump the ramps
            dt = 50000
        self._t_us += dt
        if self._t_us >= 1000:
            ms = self._t_us // 1000
            self.t_ms += ms
            self._t_us -= ms * 1000
        n = self.stream.readinto(self._rxbuf)
        if n:
            self.dec.feed(self._rxbuf, n)
        if self.estop_pin is not None and self.estop_pin.value():
            if self.state != ESTOP:
                self._halt(ESTOPPED)
                self.state = ESTOP
                self.homed = False
        self.z.tick(dt)
        self.x.tick(dt)
        self.load_mn = self.load.read_mn()
        self._supervise()
        if self.wdt is not None:
            self.wdt.feed()
        if self.stream_period_us:
            self._stream_left_us -= dt
            if self._stream_left_us <= 0:
                self._stream_left_us += self.stream_period_us
                if self._stream_left_us < 0:
                    self._stream_left_us = self.stream_period_us
                self.send_sample()

    def _moving(self):
        return self.state in (HOMING, MOVING, PRESSING, DRAGGING)

    def _supervise(self):
        st = self.state
        if st in (IDLE, ESTOP):
            return
        if (self.t_ms - self._last_rx_ms) * 1000 > self.link_timeout_us:
            self.link_lost += 1
            self._halt(LINK_LOST)
            return
        sw = self.home_switch.value() if self.home_switch is not None else 0
        if st == HOMING:
            if sw:
                self.z.halt()
                self.z.pos = 0
                self.z.target = 0
                self.z.lo = 0
                self.z.hi = self.travel_steps
                self.homed = True
                self._finish(OK)
            elif not self.z.moving:
                self._finish(HOME_FAILED)
            return
        if sw and self.z.dir < 0 and self.z.moving and self.z.target > 0:
            self._halt(LIMIT)     # the top switch outside homing: never drive into it
            return
        if st == MOVING:
            if not self.z.moving:
                self._finish(OK)
        elif st == PRESSING:
            if self.contact_z < 0 and self.load_mn >= self.touch_mn:
                self.contact_z = self.z.pos
                if self.press_mode == PRESS_DEPTH:
                    tgt = self.contact_z + (self.press_target * self.z.steps_per_mm) // 1000
                    if tgt > self.travel_steps:
                        tgt = self.travel_steps
                    self.z.move_to(tgt, self.press_speed)
            if self.press_mode == PRESS_LOAD and self.load_mn >= self.press_target:
                self.z.halt()
                self._finish(OK)
            elif not self.z.moving:
                if self.contact_z < 0 or (self.press_mode == PRESS_LOAD):
                    self._finish(LIMIT)   # reached the end of travel first
                else:
                    self._finish(OK)
        elif st == DRAGGING:
            if not self.x.running:
                self._finish(TIMEOUT if self.x.timed_out else OK)

    def _halt(self, result):
        self.z.halt()
        self.x.stop()
        if self._moving():
            self._finish(result)

    def _finish(self, result):
        p = self._pl
        put_u16(p, 0, self.cmd_seq)
        p[2] = self.cmd_type
        p[3] = result
        put_i32(p, 4, self.z_um())
        put_i32(p, 8, self.x.x_um)
        put_i32(p, 12, self.load_mn)
        self.state = IDLE
        self.cmd_type = 0
        self._send(DONE, 16)

    def z_um(self):
        return (self.z.pos * 1000) // self.z.steps_per_mm

    # -- the link -------------------------------------------------------------------------
    def _send(self, msg_type, n):
        self._tx_seq = (self._tx_seq + 1) & 0xFFFF
        wire = self.enc.frame(msg_type, self._tx_seq, self.t_ms, self._pl_mv, n)
        self.stream.write(wire)

    def _ack(self, seq, t):
        p = self._pl
        put_u16(p, 0, seq)
        p[2] = t
        self._send(ACK, 3)

    def _nak(self, seq, t, reason):
        p = self._pl
        put_u16(p, 0, seq)
        p[2] = t
        p[3] = reason
        self._send(NAK, 4)

    def send_sample(self):
        p = self._pl
        flags = 0
        if self.homed:
            flags |= F_HOMED
        if self._moving():
            flags |= F_MOVING
        if self.load_mn >= self.touch_mn:
            flags |= F_CONTACT
        if self.state == ESTOP:
            flags |= F_ESTOP
        if self.home_switch is not None and self.home_switch.value():
            flags |= F_LIMIT
        if self.load.faults:
            flags |= F_LOAD_FAULT
        if self.imu is not None:
            try:
                r = self.imu.read()
                self._imu = (int(r[0] * 1000), int(r[1] * 1000), int(r[2] * 1000),
                             int(r[3] * 10), int(r[4] * 10), int(r[5] * 10))
            except (OSError, ValueError):
                self.imu_faults += 1
            if getattr(self.imu, "faults", 0):     # the shared driver never raises
                self.imu_faults += 1
                flags |= F_IMU_FAULT
        put_u16(p, 0, self._t_us)
        put_i32(p, 2, self.z_um())
        put_i32(p, 6, self.x.x_um)
        put_i32(p, 10, self.load_mn)
        for k in range(6):
            put_u16(p, 14 + 2 * k, _clamp16(self._imu[k]) & 0xFFFF)
        p[26] = flags
        p[27] = self.state
        self._send(SAMPLE, 28)

    def _on_frame(self, d):
        self._last_rx_ms = self.t_ms
        t = d.msg_type
        seq = d.seq
        pl = d.payload
        n = d.payload_len
        want = _CMD_LEN.get(t)
        if want is None:
            self._nak(seq, t, R_UNKNOWN)
            return
        if n != want:
            self._nak(seq, t, R_BAD_PAYLOAD)
            return
        if t == PING:
            p = self._pl
            for k in range(4):
                p[k] = pl[k]
            put_i32(p, 4, self.t_ms)
            put_u16(p, 8, self._t_us)
            self._send(PONG, 10)
            return
        if t == READ:
            self._ack(seq, t)
            self.send_sample()
            return
        if t == STREAM:
            ms = get_u16(pl, 0)
            self.stream_period_us = ms * 1000
            self._stream_left_us = 0
            self._ack(seq, t)
            return
        if t == STOP:
            self._ack(seq, t)
            self._halt(STOPPED)
            return
        # motion commands
        if self.state == ESTOP:
            if self.estop_pin is not None and self.estop_pin.value():
                self._nak(seq, t, R_ESTOP)
                return
            if t != HOME:
                self._nak(seq, t, R_ESTOP)
                return
            self.state = IDLE
        if self._moving():
            self._nak(seq, t, R_BUSY)
            return
        if t != HOME and not self.homed:
            self._nak(seq, t, R_NOT_HOMED)
            return
        spm = self.z.steps_per_mm
        if t == HOME:
            self.homed = False
            self.z.lo = None                  # no soft limits until the switch is found
            self.z.hi = None
            self.z.pos = self.travel_steps + self.travel_steps // 5   # unknown: assume the bottom
            self.z.move_to(-self.travel_steps // 10, self.home_speed_steps)
            self._start(HOMING, t, seq)
        elif t == MOVE_TO:
            z = get_i32(pl, 0)
            v = get_u32(pl, 4)
            if z < 0 or z > self.travel_um or v > 1000000:
                self._nak(seq, t, R_OUT_OF_RANGE)
                return
            self.z.move_to((z * spm) // 1000, self._speed(v))
            self._start(MOVING, t, seq)
        elif t == PRESS:
            mode = pl[0]
            target = get_i32(pl, 2)
            v = get_u32(pl, 6)
            if mode > PRESS_LOAD or target <= 0 or v > 1000000 or \
                    (mode == PRESS_DEPTH and target > self.travel_um):
                self._nak(seq, t, R_OUT_OF_RANGE)
                return
            self.press_mode = mode
            self.press_target = target
            self.press_speed = self._speed(v)
            self.contact_z = -1
            self.z.move_to(self.travel_steps, self.press_speed)
            self._start(PRESSING, t, seq)
        elif t == DRAG:
            dist = get_i32(pl, 0)
            v = get_u32(pl, 4)
            if dist == 0 or v == 0 or v > self.max_speed_um_s or dist > 1000000 or dist < -1000000:
                self._nak(seq, t, R_OUT_OF_RANGE)
                return
            self.x.run(dist, v)
            self._start(DRAGGING, t, seq)
        elif t == LIFT:
            clear = get_u32(pl, 0)
            if clear > self.travel_um:
                self._nak(seq, t, R_OUT_OF_RANGE)
                return
            top = self.contact_z if self.contact_z >= 0 else self.z.pos
            tgt = top - (clear * spm) // 1000
            if tgt < 0:
                tgt = 0
            self.z.move_to(tgt, self.speed_steps)
            self._start(MOVING, t, seq)

    def _speed(self, v_um_s):
        if v_um_s == 0:
            return self.speed_steps
        return (v_um_s * self.z.steps_per_mm) // 1000

    def _start(self, state, t, seq):
        if self.wdt is None and self.wdt_factory is not None:
            self.wdt = self.wdt_factory()
        self.state = state
        self.cmd_type = t
        self.cmd_seq = seq
        self._ack(seq, t)

