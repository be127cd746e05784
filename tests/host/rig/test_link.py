"""The rig link's host side (host/rig/link.py): message numbers shared with the
firmware, and the client through ``--rig sim://`` (the firmware behind a pty):
refusals, moves, reads and the clock offset."""
from __future__ import annotations

import pytest

from host.rig import link as rig_link
from tests.mpyrun import cpython_path


def test_host_and_firmware_agree_on_message_numbers():
    cpython_path()                                  # device/micropython on the path
    from rig import firmware as fw
    for name in ("HOME", "MOVE_TO", "PRESS", "DRAG", "LIFT", "READ", "STREAM", "STOP", "PING",
                 "ACK", "NAK", "DONE", "PONG", "SAMPLE"):
        assert getattr(rig_link, name) == getattr(fw, name), name
        assert 0x20 <= getattr(fw, name) <= 0x3F       # the rig link's range
    assert rig_link.REASONS[fw.R_OUT_OF_RANGE] == "out of range"
    assert rig_link.REASONS[fw.R_NOT_HOMED] == "not homed"
    assert rig_link.REASONS[fw.R_BUSY] == "busy"
    assert rig_link.RESULTS[fw.LINK_LOST] == "link lost"


def test_client_refusals_and_clock_offset_through_the_sim_pty():
    import serial
    from host.rig.sim import SimRig

    sim = SimRig("sim://?start_mm=5")
    c = rig_link.RigClient(serial.Serial(sim.port, 115200, timeout=0.02))
    try:
        with pytest.raises(rig_link.RigRefused, match="not homed"):
            c.move_to(5.0)
        c.home()
        # the firmware's zero is where it saw the switch; a slow poll under load lets the
        # carriage pass the switch by a few steps before it stops, so the carriage is
        # measured from where homing left it
        z0 = sim.carriage.z_mm
        with pytest.raises(rig_link.RigRefused, match="out of range"):
            c.move_to(45.0)                            # beyond the 40 mm travel
        d = c.move_to(3.0, 20.0)
        assert d.ok and abs(d.z_mm - 3.0) < 0.011
        assert abs(sim.carriage.z_mm - z0 - 3.0) < 0.011   # the carriage went there
        sync = c.sync_clock(n=10)
        fw = sim.firmware
        with sim.carriage.lock:                        # the rig clock in whole ms at the last poll
            true_off = fw.t_ms - sim.last_poll_s * 1000.0
        # the true offset lies in [true_off, true_off + 1 ms): the estimate within 3 ms of it
        assert -3.0 < sync["offset_ms"] - true_off < 4.0, (sync, true_off)
        assert 0 <= sync["rtt_ms"] < 50
        s = c.read()
        assert s.flags & 1 and abs(s.z_mm - 3.0) < 0.011 and s.load_n == 0.0
        assert abs(s.imu[2] - 1.0) < 0.1                # gravity on z
    finally:
        c.close()
        sim.close()

