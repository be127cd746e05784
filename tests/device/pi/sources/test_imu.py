"""device/pi/sources/imu.py: the IMU sources open_imu opens (i2c://, file://, sim://, none)."""

from __future__ import annotations

import errno

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from device.pi.sources import imu as im
from device.pi.sources import mpu6050 as drv
from device.pi.sources.imu import open_imu
from device.pi.sources.mpu6050 import FAULT_ENDED, FAULT_OFFLINE, FAULT_STALE, IMUError, MPU6050
from device.sim import fake_mpu6050 as fm
from device.sim.fake_mpu6050 import FakeMPU6050
from tests.mpu_bus import Clock, Recorder, fake, tol


# ------------------------------------------------------------------ sources
def test_wrong_address_through_open_imu_names_address_and_source():
    with pytest.raises(IMUError, match=r"0x69.*i2c://1/0x69"):
        open_imu("i2c://1/0x69", bus=fake())




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


@pytest.mark.parametrize("content,match", [(b"", "empty or cut short"),
                                           (np.lib.format.MAGIC_PREFIX, "")])
def test_an_empty_or_cut_short_recording_is_one_error_naming_the_file(tmp_path, content, match):
    """Issue 21, item 6: a zero-length .npy was an EOFError traceback."""
    p = tmp_path / "empty.npy"
    p.write_bytes(content)
    with pytest.raises(IMUError, match=r"cannot read IMU recording '.*empty\.npy'.*" + match):
        open_imu(f"file://{p}")


def test_a_value_beyond_the_sensors_range_reads_at_full_scale_with_the_saturated_fault(tmp_path):
    """Issue 21, item 10: 1e308 is finite as float64 and inf as float32."""
    m = np.zeros((3, 6))
    m[1, 0], m[1, 5], m[2, 2] = 1e308, -1e308, 15.0
    src = open_imu(f"file://{write_npy(tmp_path, m)}")
    v0, f0 = src.read(out=np.empty(6, np.float32))
    with np.errstate(over="raise"):
        v1, f1 = src.read(out=np.empty(6, np.float32))
    v2, f2 = src.read(out=np.empty(6, np.float32))
    assert (f0, f1, f2) == (0, drv.FAULT_SATURATED, 0)
    assert np.isfinite(v1).all() and (v1[0], v1[5]) == (16.0, -2000.0)
    assert v2[2] == 15.0                  # within range: as recorded


def test_a_recording_shorter_than_the_run_says_once_that_it_loops(tmp_path, caplog):
    """Issue 21, item 13: 10 rows against 383 frames looped silently."""
    src = open_imu(f"file://{write_npy(tmp_path, np.zeros((10, 6)), 'short.npy')}")
    for _ in range(10):
        src.read()
    assert caplog.records == []
    for _ in range(373):
        src.read()
    assert len(caplog.records) == 1 and caplog.records[0].levelname == "WARNING"
    err = caplog.records[0].getMessage()
    assert "short.npy" in err and "10 rows" in err and "loop" in err


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
