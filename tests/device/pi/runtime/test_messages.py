"""The runtime's packets (device/pi/runtime/messages.py): real units in, wire
messages out that survive encoding; COMMAND opcodes by their protocol names."""
from __future__ import annotations

import numpy as np
import pytest

from device.pi.faults import FAULT_CAMERA, FAULT_LINK
from device.pi import protocol as P
from device.pi.runtime.messages import (TEMP_UNKNOWN_C, command_op, cpu_temp_c, fault_message,
                                        heartbeat_message, imu_message, surface_message)


def _roundtrip(msg):
    return P.decode_message(P.FrameDecoder().feed(msg.encode(1, 2))[0])


def test_surface_message_carries_the_decision():
    msg = surface_message(2, [0.1, 0.2, 0.6, 0.1], True, False, 0.25, 90.0, 1.5, None, 120,
                          FAULT_CAMERA)
    back = _roundtrip(msg)
    assert back.class_id == 2 and back.contact and not back.slip
    assert back.load_n == 0.0 and back.pins == 120 and back.faults == FAULT_CAMERA
    assert back.texture_id == P.TEXTURE_NONE
    assert surface_message(1, [0, 1, 0, 0], True, True, 0.9, 0, 0, 12.5, 1, 0, 3).texture_id == 3


def test_fault_message_keeps_sixteen_bits():
    back = _roundtrip(fault_message(0x1_0000 | FAULT_LINK, FAULT_LINK, 7))
    assert (back.faults, back.raised, back.pins_lost) == (FAULT_LINK, FAULT_LINK, 7)


def test_heartbeat_and_imu_clamp_counts():
    hb = heartbeat_message(12.7, 120.0, 10 ** 6, FAULT_CAMERA)
    assert hb.uptime_s == 12 and hb.frames_dropped == 0xFFFF and hb.faults == FAULT_CAMERA
    assert P.Heartbeat.unpack(hb.pack()) == hb
    imu = imu_message(np.array([0.0, 0.0, 1.0, 1.0, 2.0, 3.0]), 1.5, 1000, 0)
    assert imu.acc_mg == pytest.approx((0.0, 0.0, 1000.0)) and imu.samples == 255
    assert imu.gyro_dps == pytest.approx((1.0, 2.0, 3.0)) and imu.acc_peak_mg == 1500.0


def test_command_opcodes():
    assert command_op(P.Command(P.CMD_REZERO)) == "rezero"
    assert command_op(P.Command(P.CMD_SET_RATE, 60)) == "rate"
    assert command_op(P.Command(P.CMD_REQUEST_STATUS)) == "status"
    assert command_op(P.Command(200)) == "unknown"


@pytest.mark.parametrize("text, want", [("45678\n", 46), ("-5200", -5), ("0", 0),
                                        ("warm", TEMP_UNKNOWN_C), ("", TEMP_UNKNOWN_C)])
def test_cpu_temperature_is_the_thermal_zone_in_degrees_or_unknown(tmp_path, monkeypatch,
                                                                   text, want):
    from device.pi.runtime import messages
    zone = tmp_path / "temp"
    zone.write_text(text)
    monkeypatch.setattr(messages, "THERMAL_ZONE", str(zone))
    assert cpu_temp_c() == want
    monkeypatch.setattr(messages, "THERMAL_ZONE", str(tmp_path / "missing"))
    assert cpu_temp_c() == TEMP_UNKNOWN_C
