"""The serial side (device/pi/runtime/link.py): the writer keeps the newest SURFACE,
never drops a FAULT, and keeps the byte stream framed whatever the port takes."""
from __future__ import annotations

import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from device.pi import protocol as P
from device.pi.runtime.link import FAULT_QUEUE, LinkError, LinkWriter, open_port
from tests.device.pi.runtime.standins import RecordingPort


def test_a_socket_url_without_a_port_is_named_as_such():
    with pytest.raises(LinkError, match=r"--serial 'socket://notahost': cannot open: "
                                        r"'socket://notahost': a socket:// URL needs a host "
                                        r"and a port 1-65535"):
        open_port("socket://notahost")


def test_writer_keeps_newest_surface_and_never_drops_fault():
    port = RecordingPort()
    port.accept = False
    w = LinkWriter(port, stall_ms=10)
    for i in range(5):
        w.send("surface", P.MSG_SURFACE, P.Surface(pins=i).encode(i, 0))
        w.send("fault", P.MSG_FAULT, P.Fault(faults=1 << (i % 3)).encode(100 + i, 0))
    assert w.packets_dropped == 4 and w.pending == 6
    time.sleep(0.02)
    assert w.stalled
    port.accept = True
    w.pump()
    msgs = [m for _, m in port.frames()]
    assert [type(m).__name__ for m in msgs] == ["Fault"] * 5 + ["Surface"]
    assert msgs[-1].pins == 4 and not w.stalled


@settings(max_examples=60, deadline=None)
@given(ops=st.lists(st.tuples(st.sampled_from(["surface", "fault", "imu", "heartbeat"]),
                              st.integers(0, 40)), min_size=1, max_size=60))
def test_writer_stream_stays_framed_under_any_port_capacity(ops):
    """Whatever the port takes per write, the bytes decode to whole, valid frames;
    every FAULT arrives in order; sent + dropped + pending accounts for every send."""
    port = RecordingPort()
    w = LinkWriter(port)
    sent_faults = []
    for i, (kind, cap) in enumerate(ops):
        mt = {"surface": P.MSG_SURFACE, "fault": P.MSG_FAULT, "imu": P.MSG_IMU_SUMMARY,
              "heartbeat": P.MSG_HEARTBEAT}[kind]
        msg = {"surface": P.Surface(pins=i), "fault": P.Fault(pins_lost=i),
               "imu": P.ImuSummary(samples=i % 255), "heartbeat": P.Heartbeat(uptime_s=i)}[kind]
        w.send(kind, mt, msg.encode(i, 0))
        if kind == "fault":
            sent_faults.append(i)
        port.capacity = cap
        port.accept = cap > 0
        w.pump()
    port.capacity, port.accept = None, True
    w.pump()
    msgs = [m for _, m in port.frames()]                 # asserts no CRC error
    assert [m.pins_lost for m in msgs if isinstance(m, P.Fault)] == sent_faults[:FAULT_QUEUE] \
        or len(sent_faults) > FAULT_QUEUE
    assert w.packets_sent == len(msgs) and w.pending == 0
    assert w.packets_sent + w.packets_dropped == len(ops)

