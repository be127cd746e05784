"""device/pi/sources/mpu6050.py: the MPU6050 driver on smbus2, against FakeMPU6050."""

from __future__ import annotations

import struct
import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from device.pi.sources.mpu6050 import FAULT_OFFLINE, FAULT_SATURATED, FAULT_STALE, IMUError, MPU6050
from device.sim import fake_mpu6050 as fm
from tests.mpu_bus import ADDR, Clock, Recorder, fake, tol


# ------------------------------------------------------------------ start-up
@pytest.mark.parametrize("rate_hz,dlpf,accel_g,gyro_dps,div", [
    (200, 3, 4, 500, 4), (1000, 1, 2, 250, 0), (100, 0, 16, 2000, 79), (50, 6, 8, 1000, 19)])
def test_startup_sequence_wakes_then_configures(rate_hz, dlpf, accel_g, gyro_dps, div):
    bus = fake()
    rec = Recorder(bus)
    assert bus.asleep
    d = MPU6050(rec, rate_hz=rate_hz, dlpf=dlpf, accel_g=accel_g, gyro_dps=gyro_dps)
    assert rec.log[0] == ("rb", fm.WHO_AM_I)                  # identity before any write
    writes = [e[1] for e in rec.log if e[0] == "wb"]
    assert writes == [fm.PWR_MGMT_1, fm.PWR_MGMT_2, fm.SMPLRT_DIV, fm.CONFIG, fm.GYRO_CONFIG, fm.ACCEL_CONFIG]
    assert not bus.asleep
    assert bus.register(fm.SMPLRT_DIV) == div
    assert bus.register(fm.CONFIG) & 7 == dlpf
    assert bus.gyro_lsb_per_dps == fm.GYRO_LSB_PER_DPS[fm.GYRO_RANGE_DPS.index(gyro_dps)]
    assert bus.accel_lsb_per_g == fm.ACCEL_LSB_PER_G[fm.ACCEL_RANGE_G.index(accel_g)]
    assert bus.sample_rate_hz == pytest.approx(rate_hz)
    assert d.rate_hz == pytest.approx(rate_hz)


@pytest.mark.parametrize("kw,match", [
    ({"accel_g": 3}, r"accel_g.*\[2, 4, 8, 16\].*3"),
    ({"gyro_dps": 300}, r"gyro_dps.*300"),
    ({"dlpf": 7}, r"dlpf.*7"),
    ({"rate_hz": 2, "dlpf": 3}, r"rate_hz.*2"),
    ({"rate_hz": -5}, r"rate_hz.*-5"),
    ({"address": 200}, r"address.*200"),
])
def test_bad_driver_options_name_the_field(kw, match):
    with pytest.raises(ValueError, match=match):
        MPU6050(fake(), **kw)


def test_genuine_who_am_i_gives_no_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        d = MPU6050(fake())
    assert d.who_am_i == 0x68


@pytest.mark.parametrize("clone", [0x70, 0x72, 0x98])
def test_clone_who_am_i_accepted_with_warning(clone):
    bus = fake(who_am_i=clone)
    with pytest.warns(RuntimeWarning, match=f"0x{clone:02x}.*clone"):
        d = MPU6050(bus)
    bus.seek(1)
    v, f = d.read()
    assert f == 0 and abs(v[0] - 0.5) <= tol(8192, 0.5)


@pytest.mark.parametrize("who", [0x00, 0x12, 0x69, 0xFF])
def test_unknown_who_am_i_refused_naming_address_and_nothing_written(who):
    bus = fake(who_am_i=who, address=0x69)
    rec = Recorder(bus)
    with pytest.raises(IMUError, match=f"address 0x69.*WHO_AM_I reads 0x{who:02x}"):
        MPU6050(rec, address=0x69)
    assert [e for e in rec.log if e[0] == "wb"] == []
    assert bus.asleep


@pytest.mark.parametrize("addr", [0x69, 0x50])
def test_wrong_address_error_names_it(addr):
    with pytest.raises(IMUError, match=f"0x{addr:02x}"):
        MPU6050(fake(), address=addr)


def test_stuck_bus_at_startup_is_a_clear_error():
    with pytest.raises(IMUError, match=r"0x68.*timed out"):
        MPU6050(fake(stuck=True))


# ------------------------------------------------------------------ scaling
@pytest.mark.parametrize("accel_g", [2, 4, 8, 16])
@pytest.mark.parametrize("gyro_dps", [250, 500, 1000, 2000])
def test_scaling_matches_the_motion_within_half_an_lsb(accel_g, gyro_dps):
    rng = np.random.default_rng(accel_g * 7 + gyro_dps)
    m = np.column_stack([rng.uniform(-0.95, 0.95, (20, 3)) * accel_g,
                         rng.uniform(-0.95, 0.95, (20, 3)) * gyro_dps])
    bus = fake(m, temp_c=31.5)
    d = MPU6050(bus, accel_g=accel_g, gyro_dps=gyro_dps)
    a_lsb, g_lsb = d.accel_lsb_per_g, d.gyro_lsb_per_dps
    assert a_lsb == 32768 / accel_g
    for i in range(len(m)):
        bus.seek(i)
        v, f = d.read()
        assert f == 0 and v.dtype == np.float32 and v.shape == (6,)
        for k in range(3):
            assert abs(v[k] - m[i, k]) <= tol(a_lsb, m[i, k])
            assert abs(v[3 + k] - m[i, 3 + k]) <= tol(g_lsb, m[i, 3 + k])
    assert abs(d.temp_c - 31.5) <= 0.5 / 340 + 1e-9


def test_saturation_sets_fault_bit_with_finite_full_scale_values():
    m = np.array([[0.0, 0.0, 1.0, 0.0, 0.0, 0.0], [5.0, 0.0, 1.0, 0.0, -900.0, 0.0]])
    bus = fake(m)
    d = MPU6050(bus, accel_g=4, gyro_dps=500)
    assert d.read()[1] == 0
    bus.seek(1)
    v, f = d.read()
    assert f == FAULT_SATURATED
    assert np.all(np.isfinite(v))
    assert v[0] == pytest.approx(32767 / 8192) and v[4] == pytest.approx(-32768 / 65.5)


def test_read_reuses_its_buffer_and_out_gets_a_copy():
    bus = fake()
    d = MPU6050(bus)
    v1, _ = d.read()
    bus.seek(1)
    v2, _ = d.read()
    assert v1 is v2 is d.values
    out = np.full(6, -7.0, dtype=np.float32)
    bus.seek(2)
    r, _ = d.read(out=out)
    assert r is out and out[3] == pytest.approx(-100.5, abs=0.01)
    bus.seek(0)
    d.read()
    assert out[3] == pytest.approx(-100.5, abs=0.01)      # untouched by later reads


# ------------------------------------------------------------------ faults
def make(clock=None, **kw):
    bus = fake(**{k: kw.pop(k) for k in list(kw) if k in ("stuck", "faults", "who_am_i")})
    d = MPU6050(bus, clock=clock or Clock(), **kw)
    bus.seek(1)
    return bus, d


def test_short_eio_burst_is_retried_without_a_fault():
    bus, d = make(retries=2)
    good = d.read()[0].copy()
    bus.inject("eio", count=2)
    v, f = d.read()
    assert f == 0 and np.array_equal(v, good)
    assert d.errors == 2 and d.fault_count == 0 and d.reinit_count == 0


@pytest.mark.parametrize("kind", ["eio", "eremoteio"])
def test_eio_burst_raises_fault_bit_then_reinits_and_recovers(kind):
    clk = Clock()
    bus, d = make(clk, retries=2, backoff_s=0.05)
    good = d.read()[0].copy()
    bus.inject(kind, count=3)                     # more than 1 + retries
    v, f = d.read()
    assert f == FAULT_STALE | FAULT_OFFLINE
    assert np.array_equal(v, good)                # last good values held
    assert d.fault_count == 1 and not d.online
    n = bus.transactions
    clk.t = 0.01                                  # inside the back-off: bus left alone
    v, f = d.read()
    assert f & FAULT_STALE and bus.transactions == n
    clk.t = 0.06                                  # back-off over: re-init and read
    bus.seek(2)
    v, f = d.read()
    assert f == 0 and d.online and d.reinit_count == 1
    assert v[0] == pytest.approx(-1.5, abs=1e-3)
    assert not bus.asleep


def test_stuck_bus_backs_off_then_recovers_by_itself():
    clk = Clock()
    bus, d = make(clk, retries=1, backoff_s=0.05, backoff_max_s=1.0)
    d.read()
    bus.inject("stuck")
    t0 = bus.transactions
    for i in range(2000):                         # 10 s of 200 Hz frames
        clk.t = i / 200.0
        v, f = d.read()
        assert f == FAULT_STALE | FAULT_OFFLINE
        assert np.all(np.isfinite(v))
    assert bus.transactions - t0 < 60             # not re-initialising on every frame
    assert d.fault_count == 2000
    bus.unstick()
    recovered_at = None
    for i in range(2000, 2000 + 400):
        clk.t = i / 200.0
        if d.read()[1] == 0:
            recovered_at = clk.t
            break
    assert recovered_at is not None and recovered_at - 10.0 <= 1.0 + 1e-9   # within backoff_max_s
    assert d.reinit_count == 1


def test_brownout_reset_is_detected_and_reinitialised():
    clk = Clock()
    bus, d = make(clk, check_s=1.0, gyro_dps=1000)
    assert d.read()[1] == 0
    bus.write_byte_data(ADDR, fm.PWR_MGMT_1, fm.DEVICE_RESET)   # chip resets: asleep, ranges lost
    assert bus.asleep
    clk.t = 1.5
    d.read()                                      # health check finds SLEEP set
    assert d.reinit_count == 1 and not bus.asleep
    assert bus.gyro_lsb_per_dps == 32.8
    clk.t = 1.6
    v, f = d.read()
    assert f == 0 and v[3] == pytest.approx(10.0, abs=0.02)


def test_chip_swapped_for_wrong_device_while_running_stays_a_fault():
    clk = Clock()
    bus, d = make(clk, retries=0)
    d.read()
    bus.inject("eio")
    assert d.read()[1] & FAULT_OFFLINE
    bus.who_am_i = 0x12                            # another chip on the bus, fresh from reset
    bus.write_byte_data(bus.address, fm.PWR_MGMT_1, fm.DEVICE_RESET)
    assert bus.register(fm.WHO_AM_I) == 0x12
    for i in range(1, 50):
        clk.t = i * 0.1
        v, f = d.read()                            # never raises
        assert f == FAULT_STALE | FAULT_OFFLINE
    assert d.reinit_count == 0


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.sampled_from(["read", "eio", "eremoteio", "stuck", "unstick", "tick", "seek"]),
                          st.integers(0, 5)), max_size=60))
def test_loop_never_crashes_under_any_fault_sequence(ops):
    clk = Clock()
    bus, d = make(clk, retries=1, backoff_s=0.02, backoff_max_s=0.2)
    for op, n in ops:
        if op == "eio" or op == "eremoteio":
            bus.inject(op, count=n)
        elif op == "stuck":
            bus.inject("stuck")
        elif op == "unstick":
            bus.unstick()
        elif op == "tick":
            clk.t += n * 0.05
        elif op == "seek":
            bus.seek(n % bus.n_frames)
        v, f = d.read()
        assert v.shape == (6,) and np.all(np.isfinite(v)) and isinstance(f, int)
        assert (f & FAULT_STALE) == (0 if d.online else FAULT_STALE)
    # once the bus is healthy again it recovers by itself
    bus.clear_faults()
    clk.t += 1.0
    assert d.read()[1] == 0 and d.online


# ------------------------------------------------------------------ property
@settings(max_examples=300, deadline=None)
@given(raw=st.binary(min_size=14, max_size=14), a=st.sampled_from([2, 4, 8, 16]),
       g=st.sampled_from([250, 500, 1000, 2000]))
def test_any_14_raw_bytes_decode_finite_and_within_range(raw, a, g):
    class Bus:                                    # a bus that answers with these bytes
        def __init__(self):
            self.regs = bytearray(256)
            self.regs[fm.WHO_AM_I] = 0x68

        def read_byte_data(self, addr, r):
            return self.regs[r]

        def write_byte_data(self, addr, r, v):
            self.regs[r] = v

        def read_i2c_block_data(self, addr, r, n):
            return list(raw) if r == fm.ACCEL_XOUT_H else list(self.regs[r:r + n])

    d = MPU6050(Bus(), accel_g=a, gyro_dps=g)
    v, f = d.read()
    ints = struct.unpack(">7h", raw)
    assert np.all(np.isfinite(v)) and np.isfinite(d.temp_c)
    assert np.all(np.abs(v[:3]) <= 32768 / d.accel_lsb_per_g) and np.all(np.abs(v[:3]) <= a)
    assert np.all(np.abs(v[3:]) <= 32768 / d.gyro_lsb_per_dps + 1e-3)
    assert -60.0 < d.temp_c < 133.0
    sat = any(x in (-32768, 32767) for x in ints[:3] + ints[4:])
    assert bool(f & FAULT_SATURATED) == sat
    dec, t = d.decode(raw)
    assert np.array_equal(dec, v) and t == d.temp_c
    assert v[0] == pytest.approx(ints[0] / d.accel_lsb_per_g, rel=1e-6)
