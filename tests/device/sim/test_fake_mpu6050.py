"""FakeMPU6050: register semantics, scaling, timing, noise, faults, validation."""

from __future__ import annotations

import errno
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from device.sim import fake_mpu6050 as fm
from device.sim.fake_mpu6050 import FakeMPU6050

from tests.realdata import real_data_dir

ADDR = 0x68
MOTION = np.array(
    [
        [0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
        [0.5, -0.25, 0.98, 10.0, -20.0, 30.0],
        [-1.5, 1.25, -0.5, -100.5, 200.25, -240.0],
        [3.0, -3.0, 1.0, 300.0, -300.0, 0.0],      # beyond +-2 g and +-250 deg/s
    ]
)


def burst(bus, addr=ADDR):
    raw = bytes(bus.read_i2c_block_data(addr, fm.ACCEL_XOUT_H, 14))
    assert len(raw) == 14
    return struct.unpack(">hhhhhhh", raw)


def awake(motion=MOTION, fps=100.0, **kw):
    kw.setdefault("clock", None)
    bus = FakeMPU6050(motion, fps, **kw)
    bus.write_byte_data(ADDR, fm.PWR_MGMT_1, 0x00)
    return bus


# ------------------------------------------------------------------ identity / power
def test_who_am_i_genuine():
    bus = FakeMPU6050(MOTION, 100.0, clock=None)
    assert bus.read_byte_data(ADDR, fm.WHO_AM_I) == 0x68


@pytest.mark.parametrize("clone", [0x70, 0x72, 0x98])
def test_who_am_i_clones(clone):
    bus = FakeMPU6050(MOTION, 100.0, clock=None, who_am_i=clone)
    assert bus.read_byte_data(ADDR, fm.WHO_AM_I) == clone


def test_who_am_i_is_read_only():
    bus = FakeMPU6050(MOTION, 100.0, clock=None)
    bus.write_byte_data(ADDR, fm.WHO_AM_I, 0x12)
    assert bus.read_byte_data(ADDR, fm.WHO_AM_I) == 0x68


def test_power_on_state_is_asleep_and_reads_zeros():
    bus = FakeMPU6050(MOTION, 100.0, clock=None)
    bus.seek(1)
    assert bus.read_byte_data(ADDR, fm.PWR_MGMT_1) == 0x40
    for reg in (fm.SMPLRT_DIV, fm.CONFIG, fm.GYRO_CONFIG, fm.ACCEL_CONFIG, fm.PWR_MGMT_2):
        assert bus.read_byte_data(ADDR, reg) == 0
    assert burst(bus) == (0,) * 7
    for reg in range(fm.ACCEL_XOUT_H, fm.GYRO_ZOUT_L + 1):
        assert bus.read_byte_data(ADDR, reg) == 0


def test_wake_then_reads_scaled_motion():
    bus = awake()
    bus.seek(1)
    ax, ay, az, _t, gx, gy, gz = burst(bus)
    assert (ax, ay, az) == (8192, -4096, round(0.98 * 16384))
    assert (gx, gy, gz) == (1310, -2620, 3930)


def test_back_to_sleep_reads_zeros_again():
    bus = awake()
    bus.seek(1)
    assert burst(bus) != (0,) * 7
    bus.write_byte_data(ADDR, fm.PWR_MGMT_1, fm.SLEEP)
    assert burst(bus) == (0,) * 7


def test_device_reset_restores_power_on_registers():
    bus = awake()
    bus.write_i2c_block_data(ADDR, fm.SMPLRT_DIV, [9, 3, 0x18, 0x18])
    assert [bus.read_byte_data(ADDR, r) for r in range(fm.SMPLRT_DIV, fm.ACCEL_CONFIG + 1)] == [9, 3, 0x18, 0x18]
    bus.write_byte_data(ADDR, fm.PWR_MGMT_1, fm.DEVICE_RESET)
    assert bus.read_byte_data(ADDR, fm.PWR_MGMT_1) == 0x40     # DEVICE_RESET self-clears, SLEEP set
    assert [bus.read_byte_data(ADDR, r) for r in range(fm.SMPLRT_DIV, fm.ACCEL_CONFIG + 1)] == [0, 0, 0, 0]
    assert bus.read_byte_data(ADDR, fm.WHO_AM_I) == 0x68
    bus.seek(1)
    assert burst(bus) == (0,) * 7


# ------------------------------------------------------------------ scaling
@pytest.mark.parametrize("fs_sel,lsb", [(0, 131.0), (1, 65.5), (2, 32.8), (3, 16.4)])
def test_gyro_range_rescales(fs_sel, lsb):
    bus = awake()
    bus.write_byte_data(ADDR, fm.GYRO_CONFIG, fs_sel << 3)
    bus.seek(2)
    gx, gy, gz = burst(bus)[4:]
    full_scale = (250, 500, 1000, 2000)[fs_sel]
    for raw, dps in zip((gx, gy, gz), MOTION[2, 3:]):
        if abs(dps) < full_scale:
            assert raw == round(dps * lsb)
            assert abs(raw / lsb - dps) <= 0.5 / lsb + 1e-12
    assert bus.gyro_lsb_per_dps == lsb


@pytest.mark.parametrize("afs_sel,lsb", [(0, 16384), (1, 8192), (2, 4096), (3, 2048)])
def test_accel_range_rescales(afs_sel, lsb):
    bus = awake()
    bus.write_byte_data(ADDR, fm.ACCEL_CONFIG, afs_sel << 3)
    bus.seek(2)
    ax, ay, az = burst(bus)[:3]
    assert (ax, ay, az) == (round(-1.5 * lsb), round(1.25 * lsb), round(-0.5 * lsb))
    assert bus.accel_lsb_per_g == lsb


def test_other_config_bits_do_not_change_the_scale():
    bus = awake()
    bus.seek(1)
    bus.write_byte_data(ADDR, fm.GYRO_CONFIG, 0xE0 | (1 << 3) | 0x07)   # self-test bits + junk
    assert burst(bus)[4] == round(10.0 * 65.5)


def test_saturation_beyond_range():
    bus = awake()
    bus.seek(3)                     # 3 g, -3 g, 300 deg/s, -300 deg/s
    ax, ay, az, _t, gx, gy, gz = burst(bus)
    assert (ax, ay) == (32767, -32768)
    assert (gx, gy) == (32767, -32768)
    bus.write_byte_data(ADDR, fm.ACCEL_CONFIG, 1 << 3)   # +-4 g
    bus.write_byte_data(ADDR, fm.GYRO_CONFIG, 1 << 3)    # +-500 deg/s
    ax, ay, az, _t, gx, gy, gz = burst(bus)
    assert (ax, ay) == (3 * 8192, -3 * 8192)
    assert (gx, gy) == (round(300 * 65.5), round(-300 * 65.5))


def test_exactly_full_scale_saturates_positive_but_not_negative():
    bus = awake(np.array([[2.0, -2.0, 0, 250.0, -250.0, 0]]))
    ax, ay, _az, _t, gx, gy, _gz = burst(bus)
    assert (ax, ay) == (32767, -32768)
    assert gx == 32750 and gy == -32750      # 250 * 131 = 32750 is inside int16


@pytest.mark.parametrize("temp_c", [-40.0, 0.0, 25.0, 36.53, 85.0])
def test_temperature_formula(temp_c):
    bus = awake(temp_c=temp_c)
    raw = burst(bus)[3]
    assert raw == round((temp_c - 36.53) * 340)
    assert abs(raw / 340 + 36.53 - temp_c) <= 0.5 / 340 + 1e-9


def test_temp_dis_and_standby_bits_zero_outputs():
    bus = awake()
    bus.seek(1)
    bus.write_byte_data(ADDR, fm.PWR_MGMT_1, fm.TEMP_DIS)
    assert burst(bus)[3] == 0
    bus.write_byte_data(ADDR, fm.PWR_MGMT_2, fm.STBY_XA | fm.STBY_ZG)
    ax, ay, _az, _t, gx, gy, gz = burst(bus)
    assert ax == 0 and gz == 0 and ay != 0 and gx != 0 and gy != 0


def test_single_byte_reads_match_burst():
    bus = awake()
    bus.seek(2)
    block = bus.read_i2c_block_data(ADDR, fm.ACCEL_XOUT_H, 14)
    singles = [bus.read_byte_data(ADDR, r) for r in range(fm.ACCEL_XOUT_H, fm.GYRO_ZOUT_L + 1)]
    assert singles == block
    hi, lo = bus.read_byte_data(ADDR, fm.GYRO_YOUT_H), bus.read_byte_data(ADDR, fm.GYRO_YOUT_L)
    assert struct.unpack(">h", bytes([hi, lo]))[0] == round(200.25 * 131)


def test_block_read_spanning_data_and_other_registers():
    bus = awake()
    bus.seek(1)
    out = bus.read_i2c_block_data(ADDR, fm.INT_STATUS, 3)       # 0x3A, 0x3B, 0x3C
    assert out[0] == 0
    assert struct.unpack(">h", bytes(out[1:]))[0] == 8192


# ------------------------------------------------------------------ timing
class FakeClock:
    def __init__(self, t=0.0):
        self.t = t

    def __call__(self):
        return self.t


def ramp(n=50):
    m = np.zeros((n, 6))
    m[:, 0] = np.arange(n) / 100.0          # ax encodes the row: row / 100 g
    return m


def row_of(bus):
    return round(burst(bus)[0] / 16384 * 100)


@pytest.mark.parametrize("start, rows", [
    (0.0, {0.0: 0, 0.55: 5, 1.0: 10, 100.0: 49}),     # the clock selects the row; clamps at the end
    (1000.0, {1000.0: 0, 1000.3: 3}),                  # relative to construction
])
def test_clock_selects_row_from_construction_and_clamps(start, rows):
    clk = FakeClock(start)
    bus = awake(ramp(), fps=10.0, clock=clk)
    for t, row in rows.items():
        clk.t = t
        assert row_of(bus) == row


def test_sample_rate_from_dlpf_and_divider():
    bus = awake()
    assert bus.sample_rate_hz == 8000.0                # DLPF_CFG 0
    bus.write_byte_data(ADDR, fm.CONFIG, 3)
    assert bus.sample_rate_hz == 1000.0
    bus.write_byte_data(ADDR, fm.SMPLRT_DIV, 9)
    assert bus.sample_rate_hz == 100.0
    bus.write_byte_data(ADDR, fm.CONFIG, 7)
    assert bus.sample_rate_hz == 800.0


def test_data_registers_only_change_at_sample_instants():
    clk = FakeClock(0.0)
    bus = awake(ramp(), fps=10.0, clock=clk)
    bus.write_byte_data(ADDR, fm.CONFIG, 1)            # 1 kHz
    bus.write_byte_data(ADDR, fm.SMPLRT_DIV, 249)      # 4 Hz: samples at 0, 0.25, 0.5 s
    clk.t = 0.24
    assert row_of(bus) == 0
    clk.t = 0.26
    assert row_of(bus) == 2                            # sample taken at 0.25 s
    clk.t = 0.49
    assert row_of(bus) == 2
    bus.write_byte_data(ADDR, fm.SMPLRT_DIV, 0)        # back to 1 kHz
    assert row_of(bus) == 4


def test_seek_pins_row_and_none_returns_to_clock():
    clk = FakeClock(0.0)
    bus = awake(ramp(), fps=10.0, clock=clk)
    bus.seek(7)
    clk.t = 2.0
    assert row_of(bus) == 7
    bus.seek(None)
    assert row_of(bus) == 20


def test_no_clock_starts_pinned_at_zero():
    bus = awake(ramp(), fps=10.0, clock=None)
    assert row_of(bus) == 0
    bus.seek(12)
    assert row_of(bus) == 12
    with pytest.raises(ValueError, match="clock"):
        bus.seek(None)


@pytest.mark.parametrize("bad", [-1, 50, 1.5, "3", True])
def test_seek_rejects_bad_index(bad):
    bus = awake(ramp(), fps=10.0)
    with pytest.raises(ValueError, match=r"frame_index.*" + repr(bad).replace(".", r"\.")):
        bus.seek(bad)


def test_default_clock_is_monotonic():
    bus = awake(ramp(), fps=10.0, clock=fm.time.monotonic)
    assert row_of(bus) in (0, 1)


# ------------------------------------------------------------------ noise
def test_noise_is_deterministic_for_a_seed_and_stable_per_sample():
    a = awake(noise_g=0.05, noise_dps=1.0, seed=7)
    b = awake(noise_g=0.05, noise_dps=1.0, seed=7)
    c = awake(noise_g=0.05, noise_dps=1.0, seed=8)
    for bus in (a, b, c):
        bus.seek(1)
    ra, rb, rc = burst(a), burst(b), burst(c)
    assert ra == rb
    assert ra != rc
    assert burst(a) == ra                  # re-reading the same sample gives the same value
    a.seek(2)
    assert burst(a) != ra


def test_noise_has_the_requested_spread():
    n = 2000
    bus = awake(np.zeros((n, 6)), fps=100.0, noise_g=0.02, noise_dps=2.0, seed=1)
    acc, gyr = [], []
    for i in range(n):
        bus.seek(i)
        v = burst(bus)
        acc.append(v[0] / 16384)
        gyr.append(v[4] / 131)
    assert abs(np.mean(acc)) < 0.003 and abs(np.std(acc) - 0.02) < 0.002
    assert abs(np.mean(gyr)) < 0.3 and abs(np.std(gyr) - 2.0) < 0.2


def test_zero_noise_is_exact_up_to_quantisation():
    rng = np.random.default_rng(0)
    m = np.column_stack([rng.uniform(-1.9, 1.9, (100, 3)), rng.uniform(-240, 240, (100, 3))])
    bus = awake(m)
    for i in range(100):
        bus.seek(i)
        v = burst(bus)
        assert np.all(np.abs(np.array(v[:3]) / 16384 - m[i, :3]) <= 0.5 / 16384 + 1e-12)
        assert np.all(np.abs(np.array(v[4:]) / 131 - m[i, 3:]) <= 0.5 / 131 + 1e-12)


# ------------------------------------------------------------------ faults
@pytest.mark.parametrize("kind,code", [("eio", 5), ("eremoteio", 121)])
def test_injected_errors_then_recovery(kind, code):
    bus = awake()
    bus.seek(1)
    good = burst(bus)
    bus.inject(kind, count=2)
    for _ in range(2):
        with pytest.raises(OSError) as ei:
            burst(bus)
        assert ei.value.errno == code
    assert burst(bus) == good
    assert bus.errors == 2


def test_failed_write_does_not_take_effect():
    bus = awake()
    bus.inject("eio")
    with pytest.raises(OSError):
        bus.write_byte_data(ADDR, fm.GYRO_CONFIG, 3 << 3)
    assert bus.read_byte_data(ADDR, fm.GYRO_CONFIG) == 0


def test_faults_from_constructor():
    bus = FakeMPU6050(MOTION, 100.0, clock=None, faults={"eremoteio": 1, "eio": 1})
    codes = []
    for _ in range(2):
        with pytest.raises(OSError) as ei:
            bus.read_byte_data(ADDR, fm.WHO_AM_I)
        codes.append(ei.value.errno)
    assert sorted(codes) == [5, 121]
    assert bus.read_byte_data(ADDR, fm.WHO_AM_I) == 0x68


def test_stuck_bus_until_unstick():
    bus = awake()
    bus.inject("stuck")
    for op in (lambda: bus.read_byte_data(ADDR, fm.WHO_AM_I),
               lambda: bus.write_byte_data(ADDR, fm.PWR_MGMT_1, 0),
               lambda: burst(bus)) * 3:
        with pytest.raises(OSError) as ei:
            op()
        assert ei.value.errno == errno.ETIMEDOUT
    bus.unstick()
    assert bus.read_byte_data(ADDR, fm.WHO_AM_I) == 0x68


def test_stuck_from_constructor_and_count_rejected():
    bus = FakeMPU6050(MOTION, 100.0, clock=None, stuck=True)
    with pytest.raises(OSError):
        bus.read_byte_data(ADDR, fm.WHO_AM_I)
    with pytest.raises(ValueError, match="count"):
        bus.inject("stuck", count=3)
    with pytest.raises(ValueError, match="kind.*'brownout'"):
        bus.inject("brownout")


@pytest.mark.parametrize("addr", [0x69, 0x00, 0x77])
def test_wrong_address_is_remote_io_error(addr):
    bus = FakeMPU6050(MOTION, 100.0, clock=None)
    with pytest.raises(OSError) as ei:
        bus.read_byte_data(addr, fm.WHO_AM_I)
    assert ei.value.errno == 121
    with pytest.raises(OSError) as ei:
        bus.write_byte_data(addr, fm.PWR_MGMT_1, 0)
    assert ei.value.errno == 121


def test_ad0_high_address():
    bus = FakeMPU6050(MOTION, 100.0, clock=None, address=0x69)
    assert bus.read_byte_data(0x69, fm.WHO_AM_I) == 0x68
    with pytest.raises(OSError):
        bus.read_byte_data(0x68, fm.WHO_AM_I)


# ------------------------------------------------------------------ bus API
def test_context_manager_closes():
    with FakeMPU6050(MOTION, 100.0, clock=None) as bus:
        assert bus.read_byte_data(ADDR, fm.WHO_AM_I) == 0x68
    assert bus.closed
    with pytest.raises(ValueError, match="closed"):
        bus.read_byte_data(ADDR, fm.WHO_AM_I)


def test_bus_argument_checks_like_smbus2():
    bus = FakeMPU6050(MOTION, 100.0, clock=None)
    with pytest.raises(ValueError, match="length.*33"):
        bus.read_i2c_block_data(ADDR, fm.ACCEL_XOUT_H, 33)
    with pytest.raises(ValueError, match="value.*256"):
        bus.write_byte_data(ADDR, fm.PWR_MGMT_1, 256)
    with pytest.raises(ValueError, match="register.*300"):
        bus.read_byte_data(ADDR, 300)
    with pytest.raises(ValueError, match="data length"):
        bus.write_i2c_block_data(ADDR, fm.SMPLRT_DIV, [0] * 33)


# ------------------------------------------------------------------ validation
@pytest.mark.parametrize(
    "motion,match",
    [
        (np.zeros((10, 5)), r"motion.*\(10, 5\)"),
        (np.zeros(6), r"motion.*\(6,\)"),
        (np.zeros((0, 6)), r"motion.*\(0, 6\)"),
        (np.zeros((3, 6, 1)), r"motion.*\(3, 6, 1\)"),
    ],
)
def test_motion_shape_rejected(motion, match):
    with pytest.raises(ValueError, match=match):
        FakeMPU6050(motion, 100.0)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_motion_rejected(bad):
    m = np.zeros((4, 6))
    m[2, 4] = bad
    with pytest.raises(ValueError, match=r"motion\[2, 4\] = " + repr(float(bad)).replace("nan", "nan")):
        FakeMPU6050(m, 100.0)


@pytest.mark.parametrize("fps", [-1.0, 0, float("nan"), float("inf"), "fast"])
def test_bad_fps_rejected(fps):
    with pytest.raises(ValueError, match="fps.*" + repr(fps).replace("'", ".")):
        FakeMPU6050(MOTION, fps)


@pytest.mark.parametrize("field", ["noise_g", "noise_dps"])
def test_negative_noise_rejected(field):
    with pytest.raises(ValueError, match=f"{field}.*-0.1"):
        FakeMPU6050(MOTION, 100.0, **{field: -0.1})


def test_bad_who_am_i_and_address_rejected():
    with pytest.raises(ValueError, match="who_am_i.*256"):
        FakeMPU6050(MOTION, 100.0, who_am_i=256)
    with pytest.raises(ValueError, match="address.*128"):
        FakeMPU6050(MOTION, 100.0, address=128)


# ------------------------------------------------------------------ properties
finite = st.floats(min_value=-1e12, max_value=1e12, allow_nan=False, allow_infinity=False)


@settings(max_examples=150, deadline=None)
@given(row=st.lists(finite, min_size=6, max_size=6), fs=st.integers(0, 3), afs=st.integers(0, 3),
       temp_c=st.floats(-1e6, 1e6))
def test_any_motion_decodes_to_saturated_values(row, fs, afs, temp_c):
    bus = awake(np.array([row]), temp_c=temp_c)
    bus.write_byte_data(ADDR, fm.GYRO_CONFIG, fs << 3)
    bus.write_byte_data(ADDR, fm.ACCEL_CONFIG, afs << 3)
    raw = bus.read_i2c_block_data(ADDR, fm.ACCEL_XOUT_H, 14)
    assert all(isinstance(b, int) and 0 <= b <= 255 for b in raw)
    vals = struct.unpack(">hhhhhhh", bytes(raw))
    a_lsb, g_lsb = fm.ACCEL_LSB_PER_G[afs], fm.GYRO_LSB_PER_DPS[fs]
    expect = [v * a_lsb for v in row[:3]] + [(temp_c - 36.53) * 340] + [v * g_lsb for v in row[3:]]
    for got, want in zip(vals, expect):
        assert -32768 <= got <= 32767
        if want >= 32767:
            assert got == 32767
        elif want <= -32768:
            assert got == -32768
        else:
            assert abs(got - want) <= 0.5 + 1e-9


@settings(max_examples=50, deadline=None)
@given(t=st.floats(-10, 1e4), fps=st.floats(0.5, 1000), div=st.integers(0, 255), dlpf=st.integers(0, 7))
def test_any_time_gives_a_valid_row(t, fps, div, dlpf):
    clk = FakeClock(0.0)
    bus = awake(ramp(50), fps=fps, clock=clk)
    bus.write_byte_data(ADDR, fm.SMPLRT_DIV, div)
    bus.write_byte_data(ADDR, fm.CONFIG, dlpf)
    clk.t = t
    r = row_of(bus)
    assert 0 <= r <= 49
    if t >= 0:
        assert r <= int(t * fps) + 1


# ------------------------------------------------------------------ real data
@pytest.mark.real
def test_real_concrete_gyro_round_trip():
    path = real_data_dir() / "roboskin" / "concrete_gyro.npy"
    if not path.is_file():
        pytest.skip(f"{path} not present")
    motion = np.load(path)
    bus = FakeMPU6050.from_npy(path, fps=120.0, clock=None)
    bus.write_byte_data(ADDR, fm.PWR_MGMT_1, 0x01)                  # wake, PLL with X gyro
    # the recording peaks at 250.14 deg/s: it saturates +-250 but fits +-500
    bus.seek(int(np.argmax(motion[:, 4])))
    assert burst(bus)[5] == 32767
    bus.write_byte_data(ADDR, fm.GYRO_CONFIG, 1 << 3)
    for i in range(0, len(motion), 7):
        bus.seek(i)
        v = burst(bus)
        np.testing.assert_allclose(np.array(v[:3]) / 16384, motion[i, :3], atol=0.5 / 16384 + 1e-12)
        np.testing.assert_allclose(np.array(v[4:]) / 65.5, motion[i, 3:], atol=0.5 / 65.5 + 1e-12)


def test_from_scene_reads_the_walks_steps_and_slip_jerks():
    """Driven by the simulator: touchdowns and slip jerks show in the burst reads."""
    import struct

    from device.sim import Simulator, load_scene
    from device.sim.fake_mpu6050 import FakeMPU6050

    truth = Simulator(load_scene("slip-onset"), seed=0).truth
    imu = FakeMPU6050.from_scene("slip-onset", seed=0, clock=None)
    imu.write_byte_data(0x68, 0x6B, 0x00)               # wake
    imu.write_byte_data(0x68, 0x1C, 0x08)               # +-4 g
    az, gz = [], []
    for i in range(imu.n_frames):
        imu.seek(i)
        raw = struct.unpack(">hhhhhhh", bytes(imu.read_i2c_block_data(0x68, 0x3B, 14)))
        az.append(raw[2] / 8192.0)
        gz.append(raw[6] / 131.0)
    az, gz = np.array(az), np.array(gz)
    touch = np.flatnonzero(truth["touch"][1:] & ~truth["touch"][:-1]) + 1
    onset = np.flatnonzero(truth["slip"][1:] & ~truth["slip"][:-1]) + 1
    assert len(touch) == 2 and len(onset) >= 2
    assert np.all(az[touch] > 1.05)                      # touchdown impact above 1 g
    assert np.median(az[~truth["contact"]]) == pytest.approx(1.0, abs=0.01)
    assert np.all(np.abs(gz[onset]) > 10)                # slip jerk
    assert np.abs(gz[~truth["slip"]]).max() < 1.0
