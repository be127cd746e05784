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


# ---------------------------------------------------------------------------
# What the runtime takes from the MCU's packets (was test_mcu_packets.py)
# Packets between the leg runtime and the gait MCU (issue 29).
#
# Item 12: what the runtime takes from GAIT packets: a phase other than stance (0) or
# swing (1), or a packet flagged non-finite, is refused and counted; a packet flagged
# clamped is used with its clamped values and counted.
#
# Item 13: the SURFACE `clamped` bit means a value beyond its field, not the pressure
# model's error around no load.

import struct

from device.pi import protocol as P
from device.pi.runtime.config import LegConfig
from device.pi.runtime.load import load_models
from device.pi.runtime.loop import LegRuntime
from tests.device.pi.runtime.standins import (FPS, NullImu, RecordingPort, SimCamera,
                                              make_runtime, run_for)

_GAIT = struct.Struct("<BHhhhB")


def raw_gait(phase, load_x10, vel, flags, seq):
    """A GAIT frame with any phase and flags byte (Gait.pack clamps the phase)."""
    return P.encode_frame(P.MsgType.GAIT, _GAIT.pack(phase, load_x10, *vel, flags), seq, 0)


#: (frame it is sent at, wire bytes, taken?): a good swing, then a phase of 2 and of
#: 255, a stance flagged non-finite (its load was NaN, sent as 0), a stance flagged
#: clamped (its load beyond the field, sent as 6553.5 N), a plain stance
PLAN = [
    (4, raw_gait(P.PHASE_SWING, 30, (0, 0, 0), 0, 1), True),
    (8, raw_gait(2, 990, (5, 0, 0), 0, 2), False),
    (12, raw_gait(255, 990, (5, 0, 0), 0, 3), False),
    (16, raw_gait(P.PHASE_STANCE, 0, (5, 0, 0), P.GAIT_FLAG_NONFINITE, 4), False),
    (20, raw_gait(P.PHASE_STANCE, 0xFFFF, (0, 0, 0), P.GAIT_FLAG_CLAMPED, 5), True),
    (24, raw_gait(P.PHASE_STANCE, 50, (0, 0, 0), P.GAIT_FLAG_CLAMPED | P.GAIT_FLAG_NONFINITE,
                  6), False),
    (28, raw_gait(P.PHASE_STANCE, 70, (0, 0, 0), 0, 7), True),
]


def test_a_gait_phase_out_of_range_or_flagged_non_finite_is_refused_and_counted(tmp_path):
    """Before: phase 2..255 was taken as swing and both flags were ignored (24,259 such
    packets accepted in a probe)."""
    rt, _, port = make_runtime(tmp_path)
    seen = {}

    def hook(rt):
        for at, wire, _ in PLAN:
            if rt.frames == at and at not in seen:
                port.inbox += wire
                seen[at] = None
            if rt.frames == at + 2 and seen.get(at) is None and at in seen:
                g = rt.gait
                seen[at] = None if g is None else (g.stance, round(g.load_n, 1))
    run_for(rt, frames=34, hook=hook)
    assert [seen[at] for at, _, _ in PLAN] == [
        (False, 3.0), (False, 3.0), (False, 3.0), (False, 3.0),      # refused: swing stays
        (True, 6553.5), (True, 6553.5),                               # clamped: used
        (True, 7.0)]
    st = rt.status()
    assert st["gait_packets"] == len(PLAN)
    assert st["gait_refused"] == sum(not ok for _, _, ok in PLAN) == 4
    assert st["gait_clamped"] == 1


def test_surface_from_the_real_models_in_a_walk_never_says_clamped():
    """The leg's own models on sim://walk: the pressure regressor's estimate in the air
    is a few hundredths of a newton below 0 (its error is 0.024 N), which the SURFACE
    field (0..655.35 N) clamped and flagged on 138 of the walk's 720 frames, from
    frame 7 on. A normal load cannot pull: below 0 it is no load, sent as 0 with no
    fault."""
    cfg = LegConfig()
    models = load_models(None, "int8", None, cfg)
    assert models.pressure is not None
    port = RecordingPort()
    cam = SimCamera("walk")
    rt = LegRuntime(cfg, cam.factory, NullImu(), port, models, lossless=True, fps=FPS,
                    notify=lambda s: None)
    run_for(rt, frames=100)
    surf = [m for _, m in port.frames() if isinstance(m, P.Surface)]
    assert len(surf) >= 99
    assert [i for i, m in enumerate(surf) if m.faults & P.FAULT_CLAMPED] == []
    assert sum(m.load_n == 0.0 for m in surf[10:]) > 5       # the swing frames: no load
