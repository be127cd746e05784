"""device/pi/sources/mpu6050.py and imu.py: the MPU6050 driver on smbus2 (against FakeMPU6050) and open_imu."""

from __future__ import annotations

import errno
import struct
import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from device.pi.sources import imu as im
from device.pi.sources import mpu6050 as drv
from device.pi.sources.imu import open_imu
from device.pi.sources.mpu6050 import FAULT_ENDED, FAULT_OFFLINE, FAULT_SATURATED, FAULT_STALE, IMUError, MPU6050
from device.sim import fake_mpu6050 as fm
from device.sim.fake_mpu6050 import FakeMPU6050

ADDR = 0x68
MOTION = np.array([
    [0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
    [0.5, -0.25, 0.98, 10.0, -20.0, 30.0],
    [-1.5, 1.25, -0.5, -100.5, 200.25, -240.0],
])


class Clock:
    def __init__(self, t=0.0):
        self.t = t

    def __call__(self):
        return self.t


class Recorder:
    """Wraps a bus and logs every transaction in order."""

    def __init__(self, bus):
        self.bus = bus
        self.log = []

    def read_byte_data(self, a, r):
        self.log.append(("rb", r))
        return self.bus.read_byte_data(a, r)

    def write_byte_data(self, a, r, v):
        self.log.append(("wb", r, v))
        return self.bus.write_byte_data(a, r, v)

    def read_i2c_block_data(self, a, r, n):
        self.log.append(("rblk", r, n))
        return self.bus.read_i2c_block_data(a, r, n)


def fake(motion=MOTION, **kw):
    kw.setdefault("clock", None)
    return FakeMPU6050(motion, 100.0, **kw)


def tol(lsb, v):
    """Half an LSB plus float32 rounding of the value."""
    return 0.5 / lsb + abs(float(v)) * 2.0 ** -23 + 1e-12


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


def test_wrong_address_through_open_imu_names_address_and_source():
    with pytest.raises(IMUError, match=r"0x69.*i2c://1/0x69"):
        open_imu("i2c://1/0x69", bus=fake())


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
    bus.who_am_i = 0x12
    bus._regs[fm.WHO_AM_I] = 0x12
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


# ------------------------------------------------------------------ sources
def test_i2c_source_parses_address_and_options():
    bus = fake(address=0x69)
    src = open_imu("i2c://1/0x69?rate_hz=100&accel_g=8&gyro_dps=1000&dlpf=2", bus=bus)
    assert src.driver.address == 0x69
    assert bus.sample_rate_hz == 100.0 and bus.accel_lsb_per_g == 4096 and bus.gyro_lsb_per_dps == 32.8
    assert bus.register(fm.CONFIG) == 2 and src.rate_hz == 100.0
    bus.seek(2)
    v, f = src.read()
    assert f == 0 and abs(v[2] + 0.5) <= tol(4096, 0.5)
    src.close()
    assert bus.closed


def test_i2c_source_keywords_override_query():
    bus = fake()
    src = open_imu("i2c://1/0x68?accel_g=8", bus=bus, accel_g=16)
    assert bus.accel_lsb_per_g == 2048 and src.driver.accel_g == 16


def test_i2c_source_without_the_bus_device_names_it():
    with pytest.raises(IMUError, match=r"I2C bus 97 \(/dev/i2c-97\).*i2c://97/0x68"):
        open_imu("i2c://97/0x68")


@pytest.mark.parametrize("source,match", [
    ("", "non-empty"),
    ("imu0", "'imu0'"),
    ("ftp://x", "scheme 'ftp'.*'ftp://x'"),
    ("i2c://x/0x68", "'i2c://x/0x68'"),
    ("i2c://1/0xZZ", "'i2c://1/0xZZ'"),
    ("i2c://1/0x03", "0x03.*0x08..0x77"),
    ("i2c://1/0x68?bogus=1", "'bogus'.*'i2c://1/0x68\\?bogus=1'"),
    ("i2c://1/0x68?accel_g=3", "accel_g.*'3'.*i2c://1/0x68\\?accel_g=3"),
    ("i2c://1/0x68?rate_hz=fast", "rate_hz.*'fast'"),
    ("sim://", "sim:// needs a scene"),
    ("sim://no-such-scene", "no-such-scene"),
    ("sim://walk?loop=1", "'loop'.*sim://walk"),
    ("file://", "file:// needs a path"),
    ("file://x.npy?rate=3", "'rate'"),
    ("none?x=1", "unknown IMU source"),
])
def test_bad_source_strings_are_named(source, match):
    with pytest.raises(ValueError, match=match):
        open_imu(source, bus=fake()) if source.startswith("i2c") else open_imu(source)


def test_none_source_gives_zeros_without_faults():
    with open_imu("none") as src:
        for _ in range(3):
            v, f = src.read()
            assert f == 0 and v.shape == (6,) and not v.any()
        assert src.temp_c == 0.0 and src.fault_count == 0
    with pytest.raises(ValueError, match="none.*options"):
        open_imu("none", rate_hz=100)


def write_npy(tmp_path, arr, name="imu.npy"):
    p = tmp_path / name
    np.save(p, arr)
    return p


def test_file_source_rows_in_order_and_loops(tmp_path):
    m = np.arange(18, dtype=np.float64).reshape(3, 6)
    p = write_npy(tmp_path, m)
    src = open_imu(f"file://{p}")
    rows = [src.read()[0].copy() for _ in range(5)]
    assert [r[0] for r in rows] == [0, 6, 12, 0, 6]
    assert rows[1].dtype == np.float32 and np.array_equal(rows[2], m[2].astype(np.float32))


def test_file_source_without_loop_holds_last_row_with_fault(tmp_path):
    m = np.arange(12, dtype=np.float64).reshape(2, 6)
    p = write_npy(tmp_path, m)
    src = open_imu(f"file://{p}?loop=0")
    assert src.read()[1] == 0 and src.read()[1] == 0
    v, f = src.read()
    assert f == FAULT_ENDED and np.array_equal(v, m[1].astype(np.float32))
    assert drv.fault_names(f | FAULT_STALE) == ["imu_stale", "imu_ended"]


@pytest.mark.parametrize("arr,match", [
    (np.zeros((4, 5)), r"\(F, 6\).*\(4, 5\)"),
    (np.zeros((0, 6)), r"\(0, 6\)"),
    (np.array([[0, 0, 1, 0, np.nan, 0]]), r"non-finite.*\[0, 4\]"),
])
def test_file_source_refuses_bad_recordings_naming_the_file(tmp_path, arr, match):
    p = write_npy(tmp_path, arr, "bad.npy")
    with pytest.raises(IMUError, match="bad.npy"):
        open_imu(f"file://{p}")
    with pytest.raises(IMUError, match=match):
        open_imu(f"file://{p}")


def test_file_source_missing_file_names_it(tmp_path):
    with pytest.raises(IMUError, match="nothere.npy"):
        open_imu(f"file://{tmp_path}/nothere.npy")


def test_file_source_reads_the_roboskin_recording():
    from tests.realdata import real_data_dir
    p = real_data_dir("roboskin/concrete_gyro.npy") / "roboskin" / "concrete_gyro.npy"
    ref = np.load(p)
    src = open_imu(f"file://{p}")
    for i in range(len(ref)):
        v, f = src.read()
        assert f == 0
        np.testing.assert_allclose(v, ref[i], rtol=1e-6, atol=1e-6)


def test_sim_source_runs_the_real_driver_over_the_scene_motion():
    src = open_imu("sim://walk?seed=2")
    assert isinstance(src.driver, MPU6050) and isinstance(src.bus, FakeMPU6050)
    ref = FakeMPU6050.from_scene("walk", seed=2, clock=None).motion
    a_lsb, g_lsb = src.driver.accel_lsb_per_g, src.driver.gyro_lsb_per_dps
    for i in range(40):
        v, f = src.read()
        full = np.concatenate([np.full(3, 32767 / a_lsb), np.full(3, 32767 / g_lsb)])
        inside = np.abs(ref[i]) < full
        assert (f == 0) == bool(inside.all())
        for k in np.flatnonzero(inside):
            lsb = a_lsb if k < 3 else g_lsb
            assert abs(v[k] - ref[i, k]) <= tol(lsb, ref[i, k])


def test_sim_source_wraps_and_options_reach_the_driver():
    src = open_imu("sim://minimal?accel_g=16&gyro_dps=2000&seed=1")
    assert src.bus.accel_lsb_per_g == 2048
    n = src.bus.n_frames
    first = src.read()[0].copy()
    for _ in range(n - 1):
        src.read()
    assert np.array_equal(src.read()[0], first)


def test_sim_source_recovers_from_injected_eio_burst():
    src = open_imu("sim://walk?retries=0&backoff_s=0.001")
    assert src.read()[1] == 0
    src.bus.inject("eio", count=3)
    assert src.read()[1] == FAULT_STALE | FAULT_OFFLINE
    import time
    for _ in range(200):
        time.sleep(0.002)
        if src.read()[1] == 0:
            break
    assert src.faults == 0 and src.reinit_count == 1 and src.fault_count >= 1


def test_sim_source_clone_option_warns():
    with pytest.warns(RuntimeWarning, match="0x70"):
        src = open_imu("sim://minimal?who_am_i=0x70")
    assert src.driver.who_am_i == 0x70


def test_closed_source_read_does_not_raise():
    src = open_imu("sim://minimal")
    src.close()
    v, f = src.read()
    assert f & FAULT_STALE and np.all(np.isfinite(v))


class BurstFails(Recorder):
    """A bus whose data burst fails (or comes back short) while everything else works."""

    def __init__(self, bus, mode="eio"):
        super().__init__(bus)
        self.mode = mode

    def read_i2c_block_data(self, a, r, n):
        if r == fm.ACCEL_XOUT_H and self.mode == "eio":
            raise OSError(errno.EIO, "burst fails")
        if r == fm.ACCEL_XOUT_H and self.mode == "short":
            return self.bus.read_i2c_block_data(a, r, n)[:9]
        return super().read_i2c_block_data(a, r, n)


@pytest.mark.parametrize("mode", ["eio", "short"])
def test_burst_that_keeps_failing_after_good_reinits_still_backs_off(mode):
    clk = Clock()
    bus = BurstFails(fake(), mode)
    d = MPU6050(bus, clock=clk, backoff_s=0.05, backoff_max_s=2.0)
    for i in range(2000):                           # 10 s at 200 Hz
        clk.t = i / 200.0
        v, f = d.read()
        assert f == FAULT_STALE | FAULT_OFFLINE and np.all(np.isfinite(v))
    assert 3 <= d.reinit_count <= 12                # 0.05, 0.1, 0.2, ... 2 s apart
    assert ("burst fails" if mode == "eio" else "short read") in d.last_error
    bus.mode = "ok"
    clk.t = 20.0
    assert d.read()[1] == 0 and d.last_error        # recovered; last_error kept for status


@settings(max_examples=200, deadline=None)
@given(st.one_of(
    st.text(max_size=30),
    st.builds(lambda a, b: f"i2c://{a}/{b}", st.text("0123456789x", max_size=25), st.text("0123456789abxX", max_size=6)),
    st.builds(lambda q: f"i2c://1/0x68?{q}", st.text("=&abcdefghijklmnopqrstuvwxyz_0123456789.-", max_size=30)),
    st.builds(lambda s: f"sim://{s}", st.text(max_size=12)),
    st.builds(lambda s: f"file://{s}", st.text(max_size=12)),
))
def test_any_source_string_opens_or_fails_with_a_clear_error(source):
    try:
        src = open_imu(source, bus=fake()) if source.lower().startswith("i2c") else open_imu(source)
    except (ValueError, IMUError) as e:
        assert str(e)
        return
    v, f = src.read()
    assert v.shape == (6,) and np.all(np.isfinite(v))
    src.close()


def test_sim_source_realtime_follows_the_clock():
    import time
    src = open_imu("sim://walk?realtime=1&rate_hz=1000&dlpf=1")
    ref = src.bus.motion
    time.sleep(0.1)
    v, f = src.read()
    lsb = np.array([src.driver.accel_lsb_per_g] * 3 + [src.driver.gyro_lsb_per_dps] * 3)
    rows = [i for i in range(len(ref)) if np.all(np.abs(ref[i] - v) <= 0.5 / lsb + 1e-4)]
    assert rows and min(rows) >= 6           # 0.1 s at 120 fps is row 12; not stuck at row 0


# ------------------------------------------------------- absent at start-up
def test_nothing_answering_is_unavailable_but_a_wrong_chip_is_refused():
    with pytest.raises(drv.IMUUnavailable, match=r"0x68"):
        MPU6050(fake(stuck=True))
    with pytest.raises(drv.IMUUnavailable, match=r"/dev/i2c-97"):
        open_imu("i2c://97/0x68")
    with pytest.raises(IMUError) as ei:
        open_imu("i2c://1/0x68", bus=fake(who_am_i=0x12))
    assert not isinstance(ei.value, drv.IMUUnavailable)


def test_an_imu_absent_at_start_faults_then_recovers_by_itself():
    """RetryingImuSource: zeros with stale|offline while the opener fails, retried
    with a doubling back-off, and the real readings once the IMU answers."""
    t = [0.0]
    tries = []
    good = fake()

    def opener():
        tries.append(t[0])
        if len(tries) < 3:
            raise drv.IMUUnavailable("no MPU6050 answering at address 0x68")
        return im.MPU6050Source(MPU6050(good), "i2c://1/0x68")

    src = im.RetryingImuSource("i2c://1/0x68", OSError("first"), backoff_s=0.5,
                               backoff_max_s=5.0, clock=lambda: t[0], opener=opener)
    seen = []
    for _ in range(60):                 # 6 s at 10 reads per second
        v, bits = src.read()
        seen.append(bits)
        assert np.isfinite(v).all()
        t[0] += 0.1
    assert tries[:2] == pytest.approx([0.5, 1.5]) and len(tries) == 3   # 0.5, +1, +2 s
    assert seen[0] & FAULT_STALE and seen[0] & FAULT_OFFLINE
    assert seen[-1] == 0 and src.reinit_count == 1
    v, bits = src.read()
    good_v, _ = im.MPU6050Source(MPU6050(fake()), "x").read()
    np.testing.assert_allclose(v, good_v, atol=1e-3)


def test_the_runtime_starts_without_its_imu_and_reports_the_fault(tmp_path):
    import json
    import subprocess
    import sys
    status = tmp_path / "status.json"
    res = subprocess.run([sys.executable, "-m", "device.pi", "run", "--camera",
                          "sim://press-hard", "--imu", "i2c://97/0x68", "--serial", "loop://",
                          "--frames", "20", "--status", str(status)],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert "retrying" in res.stderr
    doc = json.loads(status.read_text())
    assert "imu" in doc["fault_names"] and doc["frames"] == 20
