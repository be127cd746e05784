"""The rig firmware (device/micropython/rig) on real MicroPython and on CPython.

One scenario script drives the firmware through the ``machine`` stand-in: the
stepper's step pulses move a simulated carriage, which closes the home switch at
the top and loads a spring (the base plate) below a surface height through the
ADC. Commands go in as framed bytes on a UART and the replies are decoded. The
script prints one ``name=value`` line per check; both interpreters must agree.
"""
from __future__ import annotations

import subprocess
import sys

import pytest

from tests.mpyrun import MPY_LIB, STANDIN, requires_mpy, run_mpy

SCRIPT = r'''
import machine
from machine import Pin, PWM, ADC, UART, WDT
from rig.drivers import Stepper, DCMotor, AdcLoad
from rig.firmware import (Rig, put_i32, put_u16, get_i32, get_u16,
                          HOME, MOVE_TO, PRESS, DRAG, LIFT, READ, STREAM, STOP, PING,
                          ACK, NAK, DONE, PONG, SAMPLE)
from tflink import Encoder, Decoder
try:
    import mpy_args
    ARGV = mpy_args.ARGV
except ImportError:
    import sys
    ARGV = sys.argv

SPM = 50                     # steps per mm (small: keeps the test fast)
SURFACE_MM = 12              # the plate's surface, mm below the home switch
K_MN_PER_UM = 2              # plate stiffness, mN per um
STEP, DIR, HOMEPIN, EPIN = 2, 3, 14, 15


class Plant:
    """The carriage: counts step pulses, closes the switch, loads the spring."""
    def __init__(self, start_mm):
        self.steps = start_mm * SPM
        self.seen = 0
        self.dirpin = None
        ADC.values[26] = self.load_counts

    def update(self):
        r = Pin.rising.get(STEP, 0)
        n = r - self.seen
        self.seen = r
        self.steps += n if self.dirpin.value() else -n
        Pin.levels[HOMEPIN] = 1 if self.steps <= 0 else 0

    def load_counts(self):
        pen_um = (self.steps * 1000) // SPM - SURFACE_MM * 1000
        return max(0, pen_um * K_MN_PER_UM)


Pin.rising = {}
Pin.levels = {}
plant = Plant(20)
dirpin = Pin(DIR, Pin.OUT)
plant.dirpin = dirpin
uart = UART(0, rxbuf=1024)
wdts = []

def make_wdt():
    w = WDT(timeout=2000)
    wdts.append(w)
    return w

rig = Rig(uart, Stepper(Pin(STEP, Pin.OUT), dirpin, steps_per_mm=SPM, accel_mm_s2=400),
          DCMotor(PWM(Pin(6)), Pin(7, Pin.OUT), Pin(8, Pin.OUT), max_speed_mm_s=50,
                  timeout_ms=3000),
          AdcLoad(ADC(26)), None, Pin(HOMEPIN, Pin.IN), Pin(EPIN, Pin.IN),
          wdt_factory=make_wdt, travel_mm=40, speed_mm_s=20, home_speed_mm_s=10,
          touch_mn=50, link_timeout_ms=500)

enc = Encoder()
replies = []

def on_reply(d):
    replies.append((d.msg_type, bytes(d.payload[:d.payload_len])))

dec = Decoder(on_frame=on_reply)
now = [0]
seq = [0]
pl = bytearray(16)

def send(t, n=0):
    seq[0] += 1
    uart.feed(bytes(enc.frame(t, seq[0], 0, pl, n)))
    return seq[0]

def run(ms, ping_every=100):
    for i in range(ms):
        now[0] += 1000
        if ping_every and i % ping_every == 0 and i:
            put_i32(pl, 0, now[0] // 1000)
            send(PING, 4)
        rig.poll(now[0])
        plant.update()
        out = uart.take()
        if out:
            dec.feed(out, len(out))

def wait_done(limit_ms=8000, ping_every=100):
    for _ in range(limit_ms // 10):
        run(10, ping_every=0)
        if ping_every:
            put_i32(pl, 0, 0)
            send(PING, 4)
        for t, p in replies:
            if t == DONE:
                return p
    return None

def take(kind):
    out = [p for t, p in replies if t == kind]
    return out

def show(name, v):
    print(name + "=" + str(v))

def answer():
    """ACK or NAK reason of the last command, after a poll."""
    run(2, ping_every=0)
    for t, p in replies:
        if t == NAK:
            return "nak%d" % p[3]
        if t == ACK:
            return "ack"
    return "none"

scen = ARGV[1]

if scen == "commands":
    replies.clear(); put_i32(pl, 0, 5000); put_i32(pl, 4, 0); send(MOVE_TO, 8)
    show("move_before_home", answer())
    replies.clear(); send(HOME)
    show("home_ack", answer())
    replies.clear(); send(READ)
    show("busy", answer())
    d = wait_done()
    show("home_result", d[3])
    show("home_steps", rig.z.pos)
    show("plant_at_switch", plant.steps)
    replies.clear(); put_i32(pl, 0, 41000); put_i32(pl, 4, 0); send(MOVE_TO, 8)
    show("move_beyond", answer())
    replies.clear(); put_i32(pl, 0, -1); put_i32(pl, 4, 0); send(MOVE_TO, 8)
    show("move_negative", answer())
    replies.clear(); put_i32(pl, 0, 5000); put_i32(pl, 4, 0); send(MOVE_TO, 7)
    show("short_payload", answer())
    replies.clear(); send(0x2F)
    show("unknown", answer())
    replies.clear(); put_i32(pl, 0, 8000); put_i32(pl, 4, 20000); send(MOVE_TO, 8)
    show("move_ack", answer())
    d = wait_done()
    show("move_result", d[3])
    show("move_z_um", get_i32(d, 4))
    show("plant_um", plant.steps * 1000 // SPM)
    # press 2 mm past contact with the plate at 12 mm
    replies.clear(); pl[0] = 0; pl[1] = 0; put_i32(pl, 2, 2000); put_i32(pl, 6, 10000)
    send(PRESS, 10)
    show("press_ack", answer())
    d = wait_done()
    show("press_result", d[3])
    show("press_z_um", get_i32(d, 4))
    show("press_load_mn", get_i32(d, 12))
    replies.clear(); put_i32(pl, 0, 3000); send(LIFT, 4)
    d = wait_done()
    show("lift_result", d[3])
    show("lift_z_um", get_i32(d, 4))
    # press to a load of 1.5 N
    replies.clear(); pl[0] = 1; pl[1] = 0; put_i32(pl, 2, 1500); put_i32(pl, 6, 5000)
    send(PRESS, 10)
    d = wait_done()
    show("pressload_result", d[3])
    show("pressload_mn", get_i32(d, 12))
    # drag 10 mm left at 20 mm/s
    replies.clear(); put_i32(pl, 0, -10000); put_i32(pl, 4, 20000); send(DRAG, 8)
    show("drag_ack", answer())
    d = wait_done()
    show("drag_result", d[3])
    show("drag_x_um", get_i32(d, 8))
    replies.clear(); put_i32(pl, 0, 10000); put_i32(pl, 4, 90000); send(DRAG, 8)
    show("drag_too_fast", answer())
    # read and stream
    replies.clear(); send(READ); run(2, ping_every=0)
    s = take(SAMPLE)
    show("read_samples", len(s))
    show("read_z_um", get_i32(s[0], 2))
    show("read_load_mn", get_i32(s[0], 10))
    show("read_flags", s[0][26])
    replies.clear(); put_u16(pl, 0, 10); send(STREAM, 2); run(200)
    show("stream_samples", len(take(SAMPLE)))
    replies.clear(); put_u16(pl, 0, 0); send(STREAM, 2); run(2); replies.clear(); run(100)
    show("stream_off", len(take(SAMPLE)))
    replies.clear(); put_i32(pl, 0, 1234); send(PING, 4); run(2, ping_every=0)
    p = take(PONG)[0]
    show("pong_echo", get_i32(p, 0))
    show("pong_rig_ms", get_i32(p, 4) == rig.t_ms - 2 or get_i32(p, 4) == rig.t_ms - 1)
    show("wdt_started", len(wdts))
    show("wdt_fed", wdts[0].feeds > 100)

elif scen == "stop":
    send(HOME); wait_done()
    replies.clear(); put_i32(pl, 0, 30000); put_i32(pl, 4, 5000); send(MOVE_TO, 8)
    run(300)
    replies.clear(); send(STOP); run(3, ping_every=0)
    show("stop_ack", [t for t, p in replies if t == ACK] != [])
    d = take(DONE)[0]
    show("stop_result", d[3])
    z0 = plant.steps
    run(300)
    show("still_after_stop", plant.steps == z0)
    show("stopped_between", 0 < get_i32(d, 4) < 30000)
    # e-stop: a press is halted; motion is refused until released and homed
    replies.clear(); pl[0] = 0; pl[1] = 0; put_i32(pl, 2, 3000); put_i32(pl, 6, 5000)
    send(PRESS, 10); run(100)
    Pin.levels[EPIN] = 1
    run(5)
    d = take(DONE)[0]
    show("estop_result", d[3])
    z0 = plant.steps
    replies.clear(); put_i32(pl, 0, 1000); put_i32(pl, 4, 0); send(MOVE_TO, 8)
    show("move_in_estop", answer())
    Pin.levels[EPIN] = 0
    replies.clear(); put_i32(pl, 0, 1000); put_i32(pl, 4, 0); send(MOVE_TO, 8)
    show("move_after_release", answer())
    show("estop_still", plant.steps == z0)
    replies.clear(); send(HOME)
    show("home_after_release", answer())
    d = wait_done()
    show("rehome_result", d[3])

elif scen == "imu":
    from machine import I2C
    from mpu6050 import MPU6050

    class FakeMPU:
        def __init__(self):
            self.reg = bytearray(128)
            self.reg[0x75] = 0x68              # WHO_AM_I
            self.reg[0x6B] = 0x40              # asleep at power-up
            self.dead = False
        def read(self, r, n):
            if self.dead:
                raise OSError(5)
            if r == 0x3B:                      # az = +1 g (8192 LSB/g at 4 g), gx = 10 dps
                d = bytearray(14)
                d[4] = 0x20
                d[8] = 655 >> 8
                d[9] = 655 & 0xFF
                return bytes(d)
            return bytes(self.reg[r:r + n])
        def write(self, r, data):
            if self.dead:
                raise OSError(5)
            for i in range(len(data)):
                self.reg[r + i] = data[i]

    dev = FakeMPU()
    I2C.devices[0x68] = dev
    rig.imu = MPU6050(I2C(0), accel_g=4, gyro_dps=500)
    replies.clear(); send(READ); run(2, ping_every=0)
    s = take(SAMPLE)[0]
    show("az_mg", get_u16(s, 18))
    show("gx_ddps", get_u16(s, 20))
    show("imu_flag", s[26] & 16)
    dev.dead = True
    replies.clear(); send(READ); run(2, ping_every=0)
    s = take(SAMPLE)[0]
    show("imu_flag_dead", s[26] & 16)
    show("az_kept", get_u16(s, 18))
    try:
        I2C.devices[0x69] = FakeMPU()
        I2C.devices[0x69].reg[0x75] = 0x12
        MPU6050(I2C(0), addr=0x69)
        show("wrong_whoami", "accepted")
    except OSError as exc:
        show("wrong_whoami", "0x12" in str(exc))

elif scen == "hx711":
    from rig.drivers import HX711
    DOUT, SCK = 10, 11

    class Bridge:
        """HX711 DOUT: low when a conversion is ready, then the 24 bits MSB first,
        one per SCK pulse (read after the pulse's rising edge)."""
        def __init__(self):
            self.word = 0
            self.ready = True
            self.start = 0
        def get(self, pin, default=0):
            if pin != DOUT:
                return default
            k = Pin.rising.get(SCK, 0) - self.start
            if k == 0:
                return 0 if self.ready else 1
            if k > 24:
                return 1
            return (self.word >> (24 - k)) & 1
        def load(self, word):
            self.word = word & 0xFFFFFF
            self.start = Pin.rising.get(SCK, 0)

    br = Bridge()
    Pin.levels = br
    hx = HX711(Pin(DOUT, Pin.IN), Pin(SCK, Pin.OUT), offset=1000, counts_per_n=2000)
    br.load(1000 + 2000 * 3)            # 3 N
    show("hx_3n", hx.read_mn())
    show("hx_pulses", Pin.rising.get(SCK, 0) - br.start)
    br.load(1000 - 2000 // 2)           # -0.5 N (the cell pulled up): two's complement
    show("hx_neg", hx.read_mn())
    br.load(0x7FFFFF)                   # saturated: keep the last value, count a fault
    show("hx_sat", hx.read_mn())
    show("hx_faults", hx.faults)
    br.ready = False
    br.load(1000 + 2000 * 5)
    show("hx_not_ready", hx.read_mn())
    Pin.levels = {}

elif scen == "alloc":
    # the link's per-byte path (decoder) allocates nothing (MicroPython's gc
    # counts it; CPython has no such counter and reports 0)
    import gc
    junk = bytearray(1020)
    for i in range(1020):
        junk[i] = 1 + i % 255
    frame = bytearray(enc.frame(0x2F, 1, 0, pl, 0))   # unknown type: decoded, then refused
    gc.collect()
    a0 = gc.mem_alloc() if hasattr(gc, "mem_alloc") else 0
    rig.dec.feed(junk, len(junk))
    rig.dec.feed(junk, len(junk))
    a1 = gc.mem_alloc() if hasattr(gc, "mem_alloc") else 0
    show("alloc_junk", a1 - a0)
    show("too_long", rig.dec.too_long)
    show("frames_ok", rig.dec.frames_ok)

elif scen == "linkloss":
    send(HOME); wait_done()
    replies.clear(); put_i32(pl, 0, 0); put_i32(pl, 4, 20000); send(DRAG, 0)
    run(2, ping_every=0); replies.clear()
    put_i32(pl, 0, 30000); put_i32(pl, 4, 2000); send(MOVE_TO, 8)
    run(300, ping_every=100)           # host alive: still moving
    show("moving_with_host", rig.state)
    z0 = plant.steps
    run(800, ping_every=0)             # host silent for 800 ms (timeout 500)
    d = take(DONE)
    show("done_sent", len(d))
    show("linkloss_result", d[0][3])
    z1 = plant.steps
    run(500, ping_every=0)
    show("stopped", plant.steps == z1 and z1 > z0)
    show("link_lost_count", rig.link_lost)
    show("wdt_fed_idle", wdts[0].feeds)
    replies.clear(); put_i32(pl, 0, 5000); put_i32(pl, 4, 0); send(MOVE_TO, 8)
    show("after_loss", answer())
    # drag (DC motor) is also halted on link loss
    wait_done()
    replies.clear(); put_i32(pl, 0, 50000); put_i32(pl, 4, 10000); send(DRAG, 8)
    run(200, ping_every=50)
    run(700, ping_every=0)
    d = take(DONE)
    show("drag_loss", d[0][3] if d else -1)
    show("pwm_off", rig.x.pwm.duty_u16())
'''

EXPECT = {
    "commands": {
        "move_before_home": "nak2", "home_ack": "ack", "busy": "ack", "home_result": "0",
        "home_steps": "0", "plant_at_switch": "0", "move_beyond": "nak1",
        "move_negative": "nak1", "short_payload": "nak4", "unknown": "nak5",
        "move_ack": "ack", "move_result": "0", "move_z_um": "8000", "plant_um": "8000",
        "press_ack": "ack", "press_result": "0",
        "lift_result": "0", "pressload_result": "0",
        "drag_ack": "ack", "drag_result": "0", "drag_x_um": "-10000",
        "drag_too_fast": "nak1", "read_samples": "1", "stream_off": "0",
        "pong_echo": "1234", "pong_rig_ms": "True", "wdt_started": "1", "wdt_fed": "True",
    },
    "stop": {
        "stop_ack": "True", "stop_result": "1", "still_after_stop": "True",
        "stopped_between": "True", "estop_result": "5", "move_in_estop": "nak6",
        "move_after_release": "nak6", "estop_still": "True", "home_after_release": "ack",
        "rehome_result": "0",
    },
    "imu": {"az_mg": "1000", "gx_ddps": "100", "imu_flag": "0", "imu_flag_dead": "16",
            "az_kept": "1000", "wrong_whoami": "True"},
    "hx711": {"hx_3n": "3000", "hx_pulses": "25", "hx_neg": "-500", "hx_sat": "-500",
              "hx_faults": "1", "hx_not_ready": "-500"},
    "alloc": {"alloc_junk": "0", "frames_ok": "0"},
    "linkloss": {
        "moving_with_host": "2", "done_sent": "1", "linkloss_result": "3", "stopped": "True",
        "link_lost_count": "1", "after_loss": "ack", "drag_loss": "3", "pwm_off": "0",
    },
}


MAIN = r"""
import machine
from rig import main as m
from rig.firmware import READ, SAMPLE
from tflink import Encoder, Decoder
r = m.build()
print("pins", r.z.step_pin.id, r.z.dir_pin.id, r.x.pwm.pin.id, r.x.in1.id, r.x.in2.id,
      r.load.dout.id, r.load.sck.id, r.home_switch.pin.id, r.estop_pin.pin.id)
machine.Pin.levels = {14: 0, 15: 0}              # switches closed (to ground)
print("switches", r.home_switch.value(), r.estop_pin.value())
print("wdt_ms", r.wdt_factory().timeout)
got = []
dec = Decoder(on_frame=lambda d: got.append((d.msg_type, bytes(d.payload[:d.payload_len]))))
class Link:                                     # stand in for UsbStream
    def __init__(self):
        self.rx = bytes(Encoder().frame(READ, 1, 0, bytearray(1), 0))
    def readinto(self, buf):
        n = len(self.rx)
        buf[:n] = self.rx
        self.rx = b""
        return n
    def write(self, b):
        dec.feed(b, len(b))
r.stream = Link()
machine.Pin.levels = {14: 1, 15: 1}              # switches open
r.poll(0)
s = [p for t, p in got if t == SAMPLE][0]
print("imu_fault_flag", s[26] & 16)
"""


@requires_mpy
def test_board_entry_point_wires_the_documented_pins():
    res = run_mpy(MAIN, libs=[MPY_LIB], timeout=60)
    assert res.returncode == 0, res.stderr
    lines = dict(line.split(" ", 1) for line in res.stdout.splitlines())
    # docs/rig.md, "Wiring": STEP 2, DIR 3, ENA 6, IN1 7, IN2 8, DOUT 10, SCK 11, home 14, e-stop 15
    assert lines["pins"].split() == ["2", "3", "6", "7", "8", "10", "11", "14", "15"]
    assert lines["switches"] == "1 1"            # active low
    assert lines["wdt_ms"] == "2000"
    assert lines["imu_fault_flag"] == "16"       # no MPU6050 on the bus: flagged, not printed
    assert "rig" not in res.stdout.replace("imu_fault_flag", "")   # nothing else on stdout


def _parse(out: str) -> dict:
    return dict(line.split("=", 1) for line in out.splitlines() if "=" in line)


def _check(scen: str, got: dict) -> None:
    for k, v in EXPECT[scen].items():
        assert got.get(k) == v, f"{scen}: {k} = {got.get(k)!r}, expected {v!r}\n{got}"


def _check_numbers(got: dict) -> None:
    # "busy" is the READ sent during homing: READ is always answered (not refused)
    # press: contact at 12 mm + 2 mm; the plate spring gives ~2 mm * 2 mN/um
    # contact is found at the touch threshold (50 mN = 25 um in), then 2 mm more
    assert 14000 <= int(got["press_z_um"]) <= 14100
    assert 4000 <= int(got["press_load_mn"]) <= 4200
    assert int(got["lift_z_um"]) == int(got["press_z_um"]) - 2000 - 3000   # contact - 3 mm
    assert 1500 <= int(got["pressload_mn"]) <= 1700
    assert int(got["read_z_um"]) > 12000 and int(got["read_load_mn"]) >= 1500
    assert int(got["read_flags"]) & 1 and int(got["read_flags"]) & 4     # homed, contact
    assert 18 <= int(got["stream_samples"]) <= 22                        # 200 ms at 10 ms


def _cpython(scen: str) -> dict:
    code = f"import sys; sys.path[:0] = [{str(STANDIN)!r}, {str(MPY_LIB)!r}]\n" + SCRIPT
    res = subprocess.run([sys.executable, "-c", code, scen], capture_output=True, text=True,
                         timeout=120)
    assert res.returncode == 0, res.stderr
    return _parse(res.stdout)


@pytest.mark.parametrize("scen", list(EXPECT))
def test_firmware_on_cpython(scen):
    got = _cpython(scen)
    _check(scen, got)
    if scen == "commands":
        _check_numbers(got)


@requires_mpy
@pytest.mark.parametrize("scen", list(EXPECT))
def test_firmware_on_micropython(scen):
    res = run_mpy(SCRIPT, libs=[MPY_LIB], args=[scen], timeout=120)
    assert res.returncode == 0, res.stderr
    got = _parse(res.stdout)
    _check(scen, got)
    if scen == "commands":
        _check_numbers(got)
    assert got == _cpython(scen), "MicroPython and CPython disagree"
