"""A gait MCU that floods the link with COMMAND request-status (issue 29, item 2): the
leg keeps its SURFACE rate, the status file is rewritten at most once a pass, and the
reader hands the loop a bounded number of messages per pass.

The loop runs on a virtual clock, so the test counts per frame, never per second: a
camera paced at 120 frames per virtual second (the newest frame wins, as a live
camera), a frame's work and a status-file write each cost a fixed virtual time, and
the MCU's requests arrive at 6,000 per virtual second. What the loop does with them
decides how many of the camera's frames get a SURFACE packet.
"""
from __future__ import annotations

import pytest

from device.pi import protocol as P
from device.pi.runtime import loop as L
from device.pi.runtime.link import MAX_MESSAGES, LinkReader
from device.pi.sources.camera import Frame, open_camera
from tests.device.pi.runtime.standins import FPS, RecordingPort, make_runtime, run_for

#: camera frames offered per run (2 virtual seconds)
FRAMES = 240
#: what a frame's work costs the loop, virtual s (a Pi 4 at 120 frames/s: ~4 ms)
FRAME_COST_S = 0.004
#: what one status-file write costs (a temporary file and a rename: 0.3 ms on this
#: machine's disk, more on an SD card)
WRITE_COST_S = 0.0005
#: REQUEST_STATUS a second in the flood (about what a 921600-baud UART carries)
FLOOD_HZ = 6000.0
REQUEST = P.Command(P.CMD_REQUEST_STATUS, 0).encode(0, 0)


class PacedFeed:
    """A camera feed on the virtual clock ``vt``: frame k is available from k / FPS;
    ``get`` hands over the newest one (older ones not taken are dropped), or waits
    (moves the clock) until the next one or the timeout; "eof" after ``n`` frames."""

    lossless = False
    opens, errors, skipped = 1, 0, 0
    opened_at = 0.0

    def __init__(self, vt, images, n):
        self.vt, self.images, self.n = vt, images, n
        self.last = -1
        self.dropped = 0

    def start(self):
        return self

    def stop(self):
        pass

    def reopen(self):
        pass

    def _hand(self, k):
        self.dropped += k - self.last - 1
        self.last = k
        return Frame(k, k / FPS, self.images[k % len(self.images)]), k / FPS

    def get(self, timeout):
        now = self.vt[0]
        k = min(int(now * FPS + 1e-9), self.n - 1)
        if k > self.last:
            return self._hand(k)
        if self.last >= self.n - 1:
            return "eof"
        t_next = (self.last + 1) / FPS
        if t_next <= now + timeout:
            self.vt[0] = t_next
            return self._hand(self.last + 1)
        self.vt[0] = now + max(timeout, 0.0)
        return None


@pytest.fixture(scope="module")
def images():
    cam = open_camera("sim://press-hard")
    out = [cam.read().image for _ in range(24)]
    cam.close()
    return out


def _run(tmp_path, monkeypatch, images, flood_hz):
    """(SURFACE packets sent, status-file writes per pass, the runtime) for FRAMES
    camera frames, with ``flood_hz`` REQUEST_STATUS a virtual second."""
    vt = [0.0]
    writes = [0]

    def write_status_file(path, doc):      # costs the loop its time; nothing on disk
        writes[0] += 1
        vt[0] += WRITE_COST_S
        return True

    monkeypatch.setattr(L, "write_status_file", write_status_file)
    tmp_path.mkdir()
    port = RecordingPort()
    rt, _, _ = make_runtime(tmp_path, port=port, clock=lambda: vt[0],
                            status_path=str(tmp_path / "status.json"))
    rt.feed = PacedFeed(vt, images, FRAMES)
    frame = rt._frame

    def costly_frame(*a):
        frame(*a)
        vt[0] += FRAME_COST_S

    rt._frame = costly_frame
    poll = rt.reader.poll_timed
    fed = [0.0, 0]                          # virtual time fed up to, requests sent

    def flooded_poll():
        due = int(flood_hz * vt[0]) - fed[1]    # the MCU sent these since the last pass
        if due > 0:
            port.inbox += REQUEST * due
            fed[1] += due
        return poll()

    rt.reader.poll_timed = flooded_poll
    per_pass = []
    rt.start()
    try:
        while not rt.stopped:
            before = writes[0]
            rt.step()
            per_pass.append(writes[0] - before)
    finally:
        rt.close()
    surfaces = sum(isinstance(m, P.Surface) for _, m in port.frames())
    return surfaces, per_pass, rt, fed[1]


def test_a_request_status_flood_keeps_the_surface_rate_and_one_write_per_pass(
        tmp_path, monkeypatch, images):
    """6,000 REQUEST_STATUS a second: SURFACE keeps >= 80 % of the frames it gets with
    no flood, the status file is written at most once a pass and at most every
    STATUS_ANSWER_GAP_S, every request is counted and answered within its pass (before:
    each request rewrote the file on the loop thread, and SURFACE fell to a few %)."""
    quiet, quiet_writes, _, _ = _run(tmp_path / "quiet", monkeypatch, images, 0.0)
    assert quiet >= 0.95 * FRAMES                   # the unflooded loop keeps up
    loud, per_pass, rt, sent = _run(tmp_path / "loud", monkeypatch, images, FLOOD_HZ)
    assert loud >= 0.8 * quiet, f"SURFACE {loud} of {quiet} frames under the flood"
    assert max(per_pass) <= 1, "the status file was written more than once in a pass"
    # at most once per gap (and once at close); the run lasts FRAMES / FPS virtual s
    assert sum(per_pass) <= FRAMES / FPS / L.STATUS_ANSWER_GAP_S + 2
    assert sum(per_pass) > sum(quiet_writes) + 20    # requests do bring the file forward
    st = rt.status()
    assert st["status_requests"] == sent > 0.9 * FLOOD_HZ * FRAMES / FPS
    assert st["link_messages_dropped"] == 0          # 50 a pass: under the reader's bound
    answers = sum(isinstance(m, P.Heartbeat) for _, m in rt.port.frames())
    assert 0 < st["status_requests"] - st["status_requests_coalesced"] <= answers
    # the answers replaced in the writer's slot are not counted as dropped packets
    assert st["packets_dropped"] < 0.1 * sent


def _wire(*msgs):
    return b"".join(m.encode(i, 0) for i, m in enumerate(msgs))


def test_the_reader_hands_the_loop_a_bounded_number_of_messages_the_newest():
    """A backlog of 1,000 COMMANDs and a GAIT read at once: MAX_MESSAGES messages come
    out, the newest (the GAIT last), and the rest are counted as dropped."""
    port = RecordingPort()
    port.inbox += _wire(*[P.Command(P.CMD_REQUEST_STATUS, 0)] * 1000,
                        P.Gait(P.PHASE_SWING, 12.5, (1, 2, 3)))
    reader = LinkReader(port, clock=lambda: 1.0)
    got = reader.poll_timed()
    assert len(got) == MAX_MESSAGES
    assert isinstance(got[-1][0], P.Gait) and got[-1][0].load_n == 12.5
    assert reader.messages_dropped == 1001 - MAX_MESSAGES
    assert reader.poll_timed() == [] and reader.messages_dropped == 1001 - MAX_MESSAGES
    port.inbox += _wire(P.Gait(P.PHASE_STANCE, 1.0, (0, 0, 0)))
    assert len(reader.poll_timed()) == 1                   # a pass under the bound: all


def test_requests_of_one_pass_share_one_answer(tmp_path):
    """Five requests in one pass: one HEARTBEAT answer, four counted as coalesced; a
    request in a later pass gets its own answer."""
    rt, _, port = make_runtime(tmp_path, status_path=str(tmp_path / "status.json"))
    sent = []

    def hook(rt):
        if rt.frames == 5 and not sent:
            port.inbox += _wire(*[P.Command(P.CMD_REQUEST_STATUS, 0)] * 5)
            sent.append(1)
        elif rt.frames == 20 and len(sent) == 1:
            port.inbox += _wire(P.Command(P.CMD_REQUEST_STATUS, 0))
            sent.append(2)
    run_for(rt, frames=30, hook=hook)
    st = rt.status()
    assert (st["status_requests"], st["status_requests_coalesced"]) == (6, 4)
    assert rt.commands == 6
    assert rt.writer.sent_by_type.get(P.MSG_HEARTBEAT, 0) >= 2
