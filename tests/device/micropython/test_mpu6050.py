"""device/micropython/mpu6050.py, the MicroPython twin of the Pi's MPU6050 driver.

The same scenario script runs on REAL MicroPython (WebAssembly port, machine
stand-in + tests/mpy/fake_mpu_regs.py) and under CPython; the assertions on what it
observed are made here, on both outputs. Under CPython the twin is also run
against device.sim's FakeMPU6050 and compared with the Pi driver reading by reading.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.mpyrun import MPY_LIB, cpython_path, requires_mpy, run_mpy

SCRIPT = r"""
import json
import machine
from machine import I2C
from fake_mpu_regs import FakeMPURegs
import mpu6050
from mpu6050 import MPU6050, MPU6050Error

import sys
R = {"impl": sys.implementation.name}
T = [0]
def clk():
    return T[0]

def fresh(who=0x68):
    d = FakeMPURegs(who)
    I2C.devices.clear()
    I2C.devices[0x68] = d
    return d

# start-up sequence
d = fresh()
imu = MPU6050(I2C(0), rate_hz=200, accel_g=4, gyro_dps=500, dlpf=3)
R["startup_log"] = [list(e) for e in d.log]
R["startup_regs"] = [d.regs[r] for r in (0x19, 0x1A, 0x1B, 0x1C, 0x6B, 0x6C)]

# WHO_AM_I
who = {}
for w in (0x68, 0x70, 0x72, 0x98, 0x12, 0x00, 0x69):
    d = fresh(w)
    try:
        m = MPU6050(I2C(0))
        who[str(w)] = ["ok", m.clone, m.who_am_i]
    except OSError as e:            # MPU6050Error is an OSError (the rig catches those)
        who[str(w)] = [type(e).__name__, str(e), len([x for x in d.log if x[0] == "w"])]
R["who"] = who

# wrong address
fresh()
try:
    MPU6050(I2C(0), addr=0x69)
    R["wrong_addr"] = ["none", "no error"]
except OSError as e:
    R["wrong_addr"] = [type(e).__name__, str(e)]

# bad arguments
bad = []
for kw in ({"accel_g": 3}, {"gyro_dps": 300}, {"dlpf": 7}, {"rate_hz": 2}, {"addr": 200}, {"retries": -1}):
    fresh()
    try:
        MPU6050(I2C(0), **kw)
        bad.append("no error")
    except ValueError as e:
        bad.append(str(e))
R["bad_args"] = bad

# scaling over every range
FR = ((0.93, -0.61, 0.27, -0.88, 0.45, -0.12), (-0.07, 0.52, -0.99, 0.31, -0.74, 0.66))
scal = []
for ag in (2, 4, 8, 16):
    for gd in (250, 500, 1000, 2000):
        d = fresh()
        d.temp_c = 31.5
        m = MPU6050(I2C(0), accel_g=ag, gyro_dps=gd)
        for f in FR:
            mo = (f[0] * ag, f[1] * ag, f[2] * ag, f[3] * gd, f[4] * gd, f[5] * gd)
            d.motion = mo
            v = m.read()
            scal.append([ag, gd, list(mo), list(v), m.faults])
R["scaling"] = scal

# saturation
d = fresh()
m = MPU6050(I2C(0), accel_g=4, gyro_dps=500)
d.motion = (5.0, 0.0, 1.0, 0.0, -900.0, 0.0)
R["sat"] = [list(m.read()), m.faults]
d.motion = (0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
m.read()
R["sat_clear"] = m.faults

# EIO bursts with a stepped clock
T[0] = 0
d = fresh()
m = MPU6050(I2C(0), retries=2, backoff_ms=50, clock_ms=clk)
d.motion = (0.5, -0.25, 0.98, 10.0, -20.0, 30.0)
good = list(m.read())
d.fail = 2
short = [list(m.read()), m.faults, m.errors, m.fault_count]
d.fail = 3
long1 = [list(m.read()), m.faults, m.fault_count, m.online]
n0 = d.transactions
T[0] = 10
m.read()
inside = [m.faults, d.transactions - n0]
T[0] = 60
d.motion = (-1.5, 1.25, -0.5, -100.5, 200.25, -240.0)
rec = [list(m.read()), m.faults, m.reinit_count, m.online]
R["eio"] = {"good": good, "short": short, "long": long1, "inside": inside, "recovered": rec}

# stuck bus for 10 s of 200 Hz reads, then recovery
T[0] = 0
d = fresh()
m = MPU6050(I2C(0), retries=1, backoff_ms=50, backoff_max_ms=1000, clock_ms=clk)
m.read()
d.stuck = True
n0 = d.transactions
allbad = True
for i in range(2000):
    T[0] = i * 5
    m.read()
    if m.faults != 3:
        allbad = False
stuck_tx = d.transactions - n0
stuck_faults = m.fault_count
d.stuck = False
rec_ms = -1
for i in range(2000, 2400):
    T[0] = i * 5
    m.read()
    if m.faults == 0:
        rec_ms = T[0] - 10000
        break
R["stuck"] = [allbad, stuck_tx, stuck_faults, rec_ms, m.reinit_count]

# brown-out: the chip resets itself, the health check re-initialises it
T[0] = 0
d = fresh()
m = MPU6050(I2C(0), gyro_dps=1000, check_ms=1000, clock_ms=clk)
d.motion = (0.5, -0.25, 0.98, 10.0, -20.0, 30.0)
m.read()
d.write(0x6B, bytes([0x80]))
asleep = d.regs[0x6B] & 0x40
T[0] = 1500
m.read()
T[0] = 1600
v = m.read()
R["brownout"] = [asleep, m.reinit_count, d.regs[0x6B] & 0x40, d.regs[0x1B], list(v), m.faults]

# edge raw patterns decode finite
class Raw:
    def __init__(self, b):
        self.regs = bytearray(256)
        self.regs[0x75] = 0x68
        self.b = b
    def read(self, reg, n):
        return self.b if reg == 0x3B else self.regs[reg:reg + n]
    def write(self, reg, data):
        self.regs[reg] = data[0]
edge = []
for pat in (b"\x80\x00", b"\x7f\xff", b"\x00\x00", b"\xff\xff", b"\x12\x34"):
    I2C.devices[0x68] = Raw(pat * 7)
    m = MPU6050(I2C(0), accel_g=16, gyro_dps=250)
    edge.append([list(m.read()), m.faults])
R["edge"] = edge

print(json.dumps(R))
"""


def _check(R, impl):
    """Assertions on what the scenario script observed (on either interpreter)."""
    # start-up: WHO_AM_I read first, then wake, then configure, then read back
    log = R["startup_log"]
    assert log[0] == ["r", 0x75, 1], impl
    writes = [e[1] for e in log if e[0] == "w"]
    assert writes == [0x6B, 0x6C, 0x19, 0x1A, 0x1B, 0x1C], impl
    assert log[-1] == ["r", 0x19, 4], impl
    assert R["startup_regs"] == [4, 3, 1 << 3, 1 << 3, 0x01, 0x00], impl
    # WHO_AM_I
    w = R["who"]
    assert w["104"] == ["ok", False, 0x68]
    for clone in (0x70, 0x72, 0x98):
        assert w[str(clone)] == ["ok", True, clone], impl
    for refused in (0x12, 0x00, 0x69):
        kind, msg, n_writes = w[str(refused)]
        assert kind == "MPU6050Error" and "0x68" in msg and f"0x{refused:02x}" in msg and n_writes == 0, (impl, msg)
    kind, msg = R["wrong_addr"]
    assert kind == "MPU6050Error" and "0x69" in msg and "answering" in msg, (impl, msg)
    for msg, field in zip(R["bad_args"], ("accel_g", "gyro_dps", "dlpf", "rate_hz", "addr", "retries")):
        assert msg.startswith(field), (impl, msg)
    # scaling within half an LSB, in every range
    assert len(R["scaling"]) == 32
    for ag, gd, mo, v, faults in R["scaling"]:
        a_lsb = 32768 / ag
        g_lsb = {250: 131.0, 500: 65.5, 1000: 32.8, 2000: 16.4}[gd]
        assert faults == 0
        for k in range(3):
            assert abs(v[k] - mo[k]) <= 0.5 / a_lsb + 1e-9, (impl, ag, k, v, mo)
            assert abs(v[3 + k] - mo[3 + k]) <= 0.5 / g_lsb + 1e-9, (impl, gd, k, v, mo)
        assert abs(v[6] - 31.5) <= 0.5 / 340 + 1e-9
    v, faults = R["sat"]
    assert faults == 4 and v[0] == pytest.approx(32767 / 8192) and v[4] == pytest.approx(-32768 / 65.5)
    assert R["sat_clear"] == 0
    # EIO: retried without a fault; a longer burst holds the last good values and
    # sets the bits; the back-off leaves the bus alone; then it recovers
    e = R["eio"]
    assert e["short"][0] == e["good"] and e["short"][1:] == [0, 2, 0], impl
    assert e["long"][0] == e["good"] and e["long"][1:] == [3, 1, False], impl
    assert e["inside"] == [3, 0], impl
    rv, rf, rn, ron = e["recovered"]
    assert rf == 0 and rn == 1 and ron and rv[0] == pytest.approx(-1.5, abs=1e-3), impl
    # stuck: every frame flagged, few transactions, recovery within backoff_max
    allbad, tx, fault_count, rec_ms, reinit = R["stuck"]
    assert allbad and tx < 60 and fault_count == 2000, (impl, tx)
    assert 0 <= rec_ms <= 1000 and reinit == 1, (impl, rec_ms)
    # brown-out
    asleep, reinit, asleep_after, gyro_cfg, v, faults = R["brownout"]
    assert asleep and reinit == 1 and not asleep_after and gyro_cfg == 2 << 3, impl
    assert faults == 0 and v[3] == pytest.approx(10.0, abs=0.02)
    # edge patterns: finite, within range, saturation flagged at the extremes
    for (v, faults), pat in zip(R["edge"], (0x8000, 0x7FFF, 0, 0xFFFF, 0x1234)):
        assert all(math.isfinite(x) for x in v)
        assert all(abs(x) <= 16 for x in v[:3]) and all(abs(x) <= 32768 / 131 for x in v[3:6])
        raw = pat - 65536 if pat & 0x8000 else pat
        assert v[0] == pytest.approx(raw / 2048) and v[6] == pytest.approx(raw / 340 + 36.53)
        assert faults == (4 if pat in (0x8000, 0x7FFF) else 0)


@requires_mpy
def test_twin_on_real_micropython():
    res = run_mpy(SCRIPT, libs=[MPY_LIB], timeout=120)
    assert res.returncode == 0, res.stderr
    R = json.loads(res.stdout.strip().splitlines()[-1])
    assert R["impl"] == "micropython"
    _check(R, "micropython")


def _import_twin():
    cpython_path()
    import machine
    import mpu6050
    return machine, mpu6050


def test_twin_under_cpython():
    _import_twin()
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        exec(compile(SCRIPT, "mpu6050_scenarios", "exec"), {"__name__": "scenarios"})
    R = json.loads(buf.getvalue().strip().splitlines()[-1])
    assert R["impl"] == "cpython"
    _check(R, "cpython")


# ------------------------------------------------------------------ against device.sim
class SimDevice:
    """FakeMPU6050 (an smbus2 stand-in) as a machine.I2C device."""

    def __init__(self, bus):
        self.bus = bus

    def read(self, reg, n):
        return bytes(self.bus.read_i2c_block_data(self.bus.address, reg, n))

    def write(self, reg, data):
        self.bus.write_i2c_block_data(self.bus.address, reg, list(data))


def test_twin_matches_the_pi_driver_reading_by_reading():
    machine, mpu6050 = _import_twin()
    from device.pi.sources.mpu6050 import MPU6050 as PiMPU6050
    from device.sim.fake_mpu6050 import FakeMPU6050

    bus_pi = FakeMPU6050.from_scene("walk", seed=4, clock=None)
    bus_mp = FakeMPU6050.from_scene("walk", seed=4, clock=None)
    machine.I2C.devices.clear()
    machine.I2C.devices[0x68] = SimDevice(bus_mp)
    twin = mpu6050.MPU6050(machine.I2C(0), accel_g=8, gyro_dps=1000)
    pi = PiMPU6050(bus_pi, accel_g=8, gyro_dps=1000)
    assert [bus_mp.register(r) for r in range(0x19, 0x1D)] == [bus_pi.register(r) for r in range(0x19, 0x1D)]
    for i in range(0, bus_pi.n_frames, 7):
        bus_pi.seek(i)
        bus_mp.seek(i)
        v_pi, f_pi = pi.read()
        v_mp = twin.read()
        assert twin.faults == f_pi
        np.testing.assert_allclose(v_mp[:6], v_pi, rtol=1e-6, atol=1e-6)
        assert v_mp[6] == pytest.approx(pi.temp_c)
        np.testing.assert_allclose(v_mp[:6], bus_pi.motion[i], atol=0.5 / 32.8 + 1e-9)


def test_twin_recovers_from_the_sim_fakes_eio_and_stuck():
    machine, mpu6050 = _import_twin()
    from device.sim.fake_mpu6050 import FakeMPU6050

    T = [0]
    bus = FakeMPU6050.from_scene("minimal", clock=None)
    machine.I2C.devices.clear()
    machine.I2C.devices[0x68] = SimDevice(bus)
    m = mpu6050.MPU6050(machine.I2C(0), retries=0, backoff_ms=20, clock_ms=lambda: T[0])
    m.read()
    assert m.faults == 0
    bus.inject("eremoteio")
    m.read()
    assert m.faults == mpu6050.FAULT_STALE | mpu6050.FAULT_OFFLINE
    bus.inject("stuck")
    for t in range(0, 500, 5):
        T[0] = t
        m.read()
        assert m.faults == 3
    bus.unstick()
    T[0] = 2000
    m.read()
    assert m.faults == 0 and m.reinit_count == 1 and not bus.asleep


@settings(max_examples=300, deadline=None)
@given(raw=st.binary(min_size=14, max_size=14), ai=st.integers(0, 3), gi=st.integers(0, 3))
def test_any_14_raw_bytes_decode_finite_in_range_and_equal_to_the_pi_decode(raw, ai, gi):
    machine, mpu6050 = _import_twin()
    from device.pi.sources.mpu6050 import MPU6050 as PiMPU6050

    class RawDev:
        def __init__(self):
            self.regs = bytearray(256)
            self.regs[0x75] = 0x68

        def read(self, reg, n):
            return raw if reg == 0x3B else bytes(self.regs[reg:reg + n])

        def write(self, reg, data):
            self.regs[reg] = data[0]

        # smbus2 face for the Pi driver
        def read_byte_data(self, a, r):
            return self.regs[r]

        def write_byte_data(self, a, r, v):
            self.regs[r] = v

        def read_i2c_block_data(self, a, r, n):
            return list(self.read(r, n))

    ag, gd = (2, 4, 8, 16)[ai], (250, 500, 1000, 2000)[gi]
    machine.I2C.devices.clear()
    machine.I2C.devices[0x68] = RawDev()
    m = mpu6050.MPU6050(machine.I2C(0), accel_g=ag, gyro_dps=gd)
    v = m.read()
    assert all(math.isfinite(x) for x in v)
    assert all(abs(x) <= ag for x in v[:3])
    assert all(abs(x) <= 32768 / m.gyro_lsb_per_dps for x in v[3:6])
    assert -60 < v[6] < 133
    ints = struct.unpack(">7h", raw)
    assert (m.faults == mpu6050.FAULT_SATURATED) == any(x in (-32768, 32767) for x in ints[:3] + ints[4:])
    pi_v, pi_f = PiMPU6050(RawDev(), accel_g=ag, gyro_dps=gd).read()
    np.testing.assert_allclose(v[:6], pi_v, rtol=1e-6)
    assert pi_f == m.faults


def test_bad_arguments_name_the_field():
    machine, mpu6050 = _import_twin()
    from fake_mpu_regs import FakeMPURegs
    machine.I2C.devices.clear()
    machine.I2C.devices[0x68] = FakeMPURegs()
    with pytest.raises(ValueError, match=r"rate_hz.*'fast'"):
        mpu6050.MPU6050(machine.I2C(0), rate_hz="fast")
    with pytest.raises(ValueError, match=r"backoff_ms.*0"):
        mpu6050.MPU6050(machine.I2C(0), backoff_ms=0)


ALLOC_SCRIPT = r"""
import gc, sys
from machine import I2C
from mpu6050 import MPU6050

class Raw:
    def __init__(self):
        self.regs = bytearray(256)
        self.regs[0x75] = 0x68
        self.b = bytes(b"\x12\x34" * 7)
    def read(self, reg, n):
        return self.b if reg == 0x3B else self.regs[reg:reg + n]
    def write(self, reg, data):
        self.regs[reg] = data[0]

I2C.devices.clear()
I2C.devices[0x68] = Raw()
m = MPU6050(I2C(0), clock_ms=lambda: 0)
m.read_raw()
gc.collect()
gc.disable()
a = gc.mem_alloc()
for i in range(1000):
    m.read_raw()
b = gc.mem_alloc()
print(sys.implementation.name, b - a, m.faults, bytes(m.buf) == bytes(b"\x12\x34" * 7))
"""


@requires_mpy
def test_read_raw_allocates_nothing_per_read_on_micropython():
    res = run_mpy(ALLOC_SCRIPT, libs=[MPY_LIB], timeout=120)
    assert res.returncode == 0, res.stderr
    impl, grown, faults, same = res.stdout.split()
    assert impl == "micropython" and faults == "0" and same == "True"
    assert int(grown) < 64          # 1000 reads: nothing allocated per read
