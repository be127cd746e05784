"""device/pi/runtime/mcaplog.py: ``python -m device.pi run --mcap FILE`` writes an
MCAP log that mcap's own reader reads back: the channels with Foxglove's schemas,
one message per frame where there should be one, timestamps and decisions that
match the JSON log; files roll over by size; a killed run leaves a readable prefix;
a failed write is a count and one warning, never an exception into the loop."""
from __future__ import annotations

import json
import re
import signal
import subprocess
import threading
import time
from collections import deque
from types import SimpleNamespace

import numpy as np
import pytest

mcap = pytest.importorskip("mcap")

from mcap.reader import make_reader  # noqa: E402

from device.pi import protocol as P  # noqa: E402
from device.pi.runtime import liveview, mcaplog  # noqa: E402
from device.pi.runtime.config import McapConfig  # noqa: E402
from device.pi.runtime.mcaplog import CHANNELS, McapLog, read_log, recover, roll_name  # noqa
from device.pi.runtime.mcapmsg import grid_cells  # noqa: E402
from tests.mcapread import frame_args, kill_when_logged, sim_run_command  # noqa: E402

FRAMES = 60


def _run(tmp_path, *extra, frames=FRAMES, config=None):
    return sim_run_command(tmp_path, *extra, frames=frames, config=config)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    d = tmp_path_factory.mktemp("mcap")
    f, j = d / "run.mcap", d / "run.jsonl"
    r = subprocess.run(_run(d, "--mcap", f, "--json-log", j), capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    lines = [json.loads(x) for x in j.read_text().splitlines()]
    return SimpleNamespace(file=f, status=json.loads(r.stdout), decisions=lines)


def _by_topic(path):
    out = {}
    with open(path, "rb") as fh:
        for schema, channel, msg in make_reader(fh).iter_messages(log_time_order=False):
            out.setdefault(channel.topic, []).append(
                (schema.name, schema.encoding, channel.message_encoding, msg.log_time,
                 json.loads(msg.data)))
    return out


def test_the_channels_exist_with_their_schemas(run):
    with open(run.file, "rb") as fh:
        summary = make_reader(fh).get_summary()       # a complete file: footer + summary
    schemas = {s.id: s for s in summary.schemas.values()}
    got = {c.topic: schemas[c.schema_id].name for c in summary.channels.values()}
    assert got == {t: s["title"] for t, s in CHANNELS.items()}
    assert got["/tacfoot/image"] == "foxglove.CompressedImage"
    assert got["/tacfoot/pins"] == "foxglove.ImageAnnotations"
    assert {s.encoding for s in schemas.values()} == {"jsonschema"}
    assert {c.message_encoding for c in summary.channels.values()} == {"json"}
    for s in schemas.values():                        # each schema is JSON naming itself
        assert json.loads(s.data)["title"] == s.name


def test_one_message_per_frame_and_an_image_every_nth(run):
    m = _by_topic(run.file)
    for topic in ("/tacfoot/decision", "/tacfoot/grid", "/tacfoot/imu", "/tacfoot/latency"):
        assert len(m[topic]) == FRAMES, topic
        if topic != "/tacfoot/grid":             # foxglove.Grid has no frame number
            assert [x[4]["frame"] for x in m[topic]] == list(range(FRAMES))
    # the grid at its frame's time, stamped with it
    assert [x[3] for x in m["/tacfoot/grid"]] == [x[3] for x in m["/tacfoot/decision"]]
    assert all(divmod(x[3], 10**9) == (x[4]["timestamp"]["sec"], x[4]["timestamp"]["nsec"])
               for x in m["/tacfoot/grid"])
    every = McapConfig().image_every
    n_img = -(-FRAMES // every)
    assert len(m["/tacfoot/image"]) == len(m["/tacfoot/pins"]) == n_img
    # the images are the frames 0, N, 2N ...: same times as those decisions
    dec_t = [x[3] for x in m["/tacfoot/decision"]]
    assert [x[3] for x in m["/tacfoot/image"]] == dec_t[::every]
    assert [x[3] for x in m["/tacfoot/pins"]] == dec_t[::every]
    # every packet the runtime sent (loop:// drops none), the SURFACEs one per frame
    out = [x[4] for x in m["/tacfoot/packets/out"]]
    assert len(out) == run.status["packets_sent"] and run.status["packets_dropped"] == 0
    assert sum(p["type"] == "surface" for p in out) == FRAMES
    assert [p["seq"] for p in out] == list(range(len(out)))      # in the order sent
    t_out = [x[3] for x in m["/tacfoot/packets/out"]]
    assert dec_t[0] - 10**9 <= t_out[0] <= t_out[-1] <= dec_t[-1] + 10**9   # the frames' line
    assert len(m["/tacfoot/packets/in"]) > 0                  # loop:// echoes them back
    faults_out = [p for p in out if p["type"] == "fault"]
    assert len(m["/tacfoot/faults"]) == len(faults_out) >= 1
    # each FAULT also a foxglove.Log line, WARNING when it raised a bit
    flines = [x[4] for x in m["/tacfoot/log"] if x[4]["name"] == "tacfoot.faults"]
    assert len(flines) == len(faults_out)
    assert [ln["level"] for ln in flines] == [3 if p["raised"] else 2 for p in faults_out]
    assert run.status["mcap_messages_lost"] == 0
    assert run.status["mcap_messages_written"] == sum(len(v) for v in m.values())


def test_decisions_and_timestamps_match_the_json_log(run):
    m = _by_topic(run.file)
    decs = m["/tacfoot/decision"]
    assert len(decs) == len(run.decisions) == FRAMES
    t0_ns, t0_s = decs[0][3], run.decisions[0]["t_s"]
    for (_, _, _, t_ns, d), line in zip(decs, run.decisions):
        # the frame's own time, ns, on a time line anchored to the epoch (time_ns)
        assert abs((t_ns - t0_ns) - (line["t_s"] - t0_s) * 1e9) <= 1e3
        extra = {k: d.pop(k) for k in ("surface_conf", "texture_conf")}
        assert d == line                                       # the same decision line
        assert extra["surface_conf"] == round(max(line["probs"]), 4)
        assert (extra["texture_conf"] is None) == (line["texture"] is None)
    assert [x[3] for x in decs] == sorted(x[3] for x in decs)
    lat = [x[4]["latency_ms"] for x in m["/tacfoot/latency"]]
    assert lat == [line["latency_ms"] for line in run.decisions]
    assert all(x[4]["pipeline_ms"] > 0 for x in m["/tacfoot/latency"])
    imu = m["/tacfoot/imu"][0][4]
    assert len(imu["acc_g"]) == 3 and len(imu["gyro_dps"]) == 3
    assert 0.5 < float(np.linalg.norm(imu["acc_g"])) < 1.5        # gravity, in g


def test_images_are_jpegs_of_the_configured_width_and_pins_one_point_each(run):
    import base64

    import cv2
    m = _by_topic(run.file)
    decs = {x[3]: x[4] for x in m["/tacfoot/decision"]}
    for (_, _, _, t, img), (_, _, _, t2, ann) in zip(m["/tacfoot/image"], m["/tacfoot/pins"]):
        assert t == t2 and img["format"] == "jpeg" and img["frame_id"] == mcaplog.FRAME_ID
        assert img["timestamp"] == {"sec": t // 10**9, "nsec": t % 10**9}
        pic = cv2.imdecode(np.frombuffer(base64.b64decode(img["data"]), np.uint8),
                           cv2.IMREAD_UNCHANGED)
        assert pic is not None and pic.shape[1] == McapConfig().image_width
        pts, segs = ann["points"]
        assert pts["type"] == mcaplog.POINTS and segs["type"] == mcaplog.LINE_LIST
        assert len(pts["points"]) == decs[t]["pins"]         # one point per tracked pin
        assert len(segs["points"]) % 2 == 0
        h, w = pic.shape[:2]
        for p in pts["points"] + segs["points"][::2]:
            assert -1 <= p["x"] <= w + 1 and -1 <= p["y"] <= h + 1
    assert any(len(a[4]["points"][1]["points"]) for a in m["/tacfoot/pins"])   # vectors


def test_files_roll_over_by_size_and_each_reads_back(tmp_path):
    f = tmp_path / "roll.mcap"
    r = subprocess.run(_run(tmp_path, "--mcap", f, "--mcap-max-mb", "1", frames=30,
                            config="[mcap]\nchunk_kb = 8\nimage_every = 1\n"
                                   "image_width = 640\njpeg_quality = 100\n"),
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    files = json.loads(r.stdout)["mcap_files"]
    assert len(files) >= 3 and files[0] == str(f) and files[1] == str(roll_name(f, 1))
    assert str(roll_name(f, 1)).endswith("roll-0001.mcap")
    frames = []
    for p in files:
        msgs, complete = read_log(p)
        assert complete, p
        with open(p, "rb") as fh:                 # and mcap's own seeking reader
            summary = make_reader(fh).get_summary()
        assert len(summary.channels) == len(CHANNELS)
        frames += [x["data"]["frame"] for x in msgs if x["topic"] == "/tacfoot/decision"]
    assert frames == list(range(30))              # nothing lost, nothing twice


def test_a_killed_run_leaves_a_readable_prefix(tmp_path):
    # the thread writer dies with the runtime (the process writer ends the file:
    # tests/device/pi/runtime/test_mcapproc.py)
    f = tmp_path / "killed.mcap"
    kill_when_logged(tmp_path, f, 80_000, writer="thread")
    msgs, complete = read_log(f)
    assert not complete                           # no footer: cut short
    frames = [x["data"]["frame"] for x in msgs if x["topic"] == "/tacfoot/decision"]
    assert len(frames) >= 3 and frames == list(range(len(frames)))   # a whole prefix
    # recover(): the prefix as a well-formed file mcap's seeking reader opens
    fixed = tmp_path / "fixed.mcap"
    assert recover(f, fixed) == len(msgs)
    with open(fixed, "rb") as fh:
        n = sum(1 for _ in make_reader(fh).iter_messages())
    assert n == len(msgs)


def _frame_args(k=0, t_s=0.01):
    return frame_args(k, t_s, np.array([[10.0, 20.0], [30.0, 40.0]]))


def test_a_failed_write_is_a_count_and_one_warning_then_the_next_file(tmp_path, caplog,
                                                                      monkeypatch):
    now, full = [0.0], [False]
    real = mcaplog._CountingFile.write

    def write(self, data):
        if full[0]:
            raise OSError(28, "No space left on device")
        return real(self, data)
    monkeypatch.setattr(mcaplog._CountingFile, "write", write)
    log = McapLog(tmp_path / "w.mcap", McapConfig(image_every=1, image_width=32, chunk_kb=1),
                  clock=lambda: now[0])
    log.frame(*_frame_args(0))
    assert log.messages_written == 6 and log.messages_lost == 0   # image, pins + 4
    full[0] = True                                # the disk fills
    for k in range(1, 6):                         # a chunk is written within a few frames
        log.frame(*_frame_args(k))                # never an exception into the loop
        log.packet("out", P.Fault(faults=1, raised=1, pins_lost=0), now[0], k, 10)
    assert log.messages_lost > 0
    err = "".join(r.getMessage() for r in caplog.records if r.levelname == "WARNING")
    assert err.count("--mcap") == 1 and "No space left" in err and "mcap_messages_lost" in err
    lost = log.messages_lost
    log.frame(*_frame_args(6))                    # before RETRY_S: dropped and counted
    assert log.messages_lost == lost + 6 and len(log.files) == 1
    full[0] = False
    now[0] = 10.0                                 # later: the next file is opened
    log.frame(*_frame_args(7))
    log.close()
    assert log.files == [str(tmp_path / "w.mcap"), str(tmp_path / "w-0001.mcap")]
    msgs, complete = read_log(log.files[-1])
    assert complete and len(msgs) == 6
    assert {m["data"].get("frame", 7) for m in msgs} == {7}
    assert log.status()["mcap_messages_lost"] == log.messages_lost


def test_annotations_skip_lost_pins_and_scale_with_the_image():
    dec, _, _, ef, *_rest, ref = _frame_args()
    a = mcaplog.annotations({"sec": 0, "nsec": 0}, ef.features, ref, 0.5, 3.0)
    pts, segs = a["points"]
    assert pts["points"] == [{"x": 5.0, "y": 10.0}, {"x": 15.0, "y": 20.0}]
    # pin 1 is lost: one segment, from pin 0's place along 3x its vector, halved
    assert segs["points"] == [{"x": 5.0, "y": 10.0}, {"x": 6.5, "y": 10.0}]


def test_a_bad_path_is_an_error_naming_it(tmp_path):
    with pytest.raises(mcaplog.McapLogError, match="does not exist"):
        McapLog(tmp_path / "nope" / "x.mcap", McapConfig())
    with pytest.raises(mcaplog.McapLogError, match="is a folder"):
        McapLog(tmp_path, McapConfig())
    with pytest.raises(mcaplog.McapLogError, match="got neither"):
        McapLog(None, McapConfig())               # else frame() would raise in the loop


def test_the_foxglove_layout_names_only_logged_topics_and_fields():
    import re

    from tests import REPO_ROOT
    text = (REPO_ROOT / "docs" / "foxglove-layout.json").read_text()
    json.loads(text)
    refs = re.findall(r'"(/tacfoot/[a-z/]+)(?:\.(\w+))?', text)
    assert {"/tacfoot/image", "/tacfoot/pins", "/tacfoot/imu"} <= {t for t, _ in refs}
    for topic, fld in refs:
        assert topic in CHANNELS, topic
        if fld:
            assert fld in CHANNELS[topic]["properties"], f"{topic}.{fld}"


class _FakeLive:
    host, port = "127.0.0.1", 0

    def __init__(self, topics=()):
        self.topics, self.got = set(topics), []

    def wants(self, topic):
        return topic in self.topics

    def any(self):
        return bool(self.topics)

    def publish(self, topic, t_ns, data):
        self.got.append((topic, t_ns, json.loads(data)))

    def close(self):
        pass

    def status(self):
        return {}


def test_the_live_view_alone_builds_only_what_a_viewer_subscribed_to(monkeypatch):
    built = []
    monkeypatch.setattr(McapLog, "_image", lambda self, *a: built.append(a))
    idle = _FakeLive()
    log = McapLog(None, McapConfig(image_every=1), live=idle, clock=lambda: 0.0)
    log.frame(*_frame_args(0))
    log.packet("out", P.Fault(faults=1, raised=1, pins_lost=0), 0.5, 1, 2)
    assert idle.got == [] and built == [] and log.files == []     # no viewer: nothing
    one = _FakeLive({"/tacfoot/decision", "/tacfoot/faults"})
    log = McapLog(None, McapConfig(image_every=1), live=one, clock=lambda: 0.0)
    log.frame(*_frame_args(3, t_s=0.25))
    log.packet("out", P.Fault(faults=1, raised=1, pins_lost=0), 0.5, 1, 2)
    assert [g[0] for g in one.got] == ["/tacfoot/decision", "/tacfoot/faults"]
    assert abs(one.got[0][1] - time.time_ns()) < 60 * 10**9 and one.got[0][2]["frame"] == 3
    assert built == []                                 # the image is not built either
    assert log.messages_lost == 0


@pytest.mark.parametrize("text,want", [("8765", ("127.0.0.1", 8765)),
                                       ("0.0.0.0:9000", ("0.0.0.0", 9000)),
                                       (":0", ("127.0.0.1", 0))])
def test_parse_hostport(text, want):
    assert liveview.parse_hostport(text) == want


@pytest.mark.parametrize("text", ["x", "host:", "1:70000", "-1"])
def test_parse_hostport_refuses_a_bad_port_naming_it(text):
    with pytest.raises(ValueError, match=re.escape(repr(text))):
        liveview.parse_hostport(text)


def test_a_websocket_client_receives_the_live_channels(tmp_path):
    """--foxglove: a Foxglove WebSocket client connects to the running leg, sees the
    channels advertised with their schemas, subscribes and receives messages."""
    pytest.importorskip("foxglove")
    websockets = pytest.importorskip("websockets")
    import asyncio
    cmd = _run(tmp_path, "--foxglove", "127.0.0.1:0", frames=None)
    cmd[cmd.index("sim://walk")] = "sim://walk?realtime=1"
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stderr.readline()
        m = re.search(r"ws://([\d.]+):(\d+)", line)
        assert m, line

        async def client():
            async with websockets.connect(f"ws://{m[1]}:{m[2]}",
                                          subprotocols=["foxglove.sdk.v1"]) as ws:
                chans, got = {}, []
                while len(got) < 10:
                    msg = await asyncio.wait_for(ws.recv(), 10)
                    if isinstance(msg, str):
                        d = json.loads(msg)
                        if d["op"] == "advertise":
                            chans.update({c["id"]: c for c in d["channels"]})
                            subs = [{"id": i, "channelId": cid} for i, cid in enumerate(
                                c["id"] for c in d["channels"]
                                if c["topic"] in ("/tacfoot/decision", "/tacfoot/image"))]
                            await ws.send(json.dumps({"op": "subscribe",
                                                      "subscriptions": subs}))
                    elif msg[0] == 1:                 # messageData
                        got.append(msg)
                return chans, got
        chans, got = asyncio.run(client())
        topics = {c["topic"]: c["schemaName"] for c in chans.values()}
        assert topics == {t: s["title"] for t, s in CHANNELS.items()}
        payloads = [json.loads(bytes(g[1 + 4 + 8:])) for g in got]   # op, sub id, time
        assert any("class" in p and "surface_conf" in p for p in payloads)
    finally:
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=10)
    assert proc.returncode == 0, err
    st = json.loads(out)
    assert st["foxglove_messages_sent"] >= 10 and st["mcap_files"] == []


def test_in_the_background_the_loop_never_waits_and_the_newest_wins(tmp_path, monkeypatch):
    """background=True (the runtime's): with the writer stuck on the disk, frame()
    still returns at once; past QUEUE_ITEMS queued, the oldest frames are dropped and
    counted, and once the disk is back the newest frames are written."""
    import threading
    stuck = threading.Event()
    real = McapLog._write

    def slow(self, *a):
        stuck.wait(30)
        return real(self, *a)
    monkeypatch.setattr(McapLog, "_write", slow)
    log = McapLog(tmp_path / "bg.mcap", McapConfig(image_every=1000, image_width=32),
                  clock=lambda: 0.0, background=True)
    n = mcaplog.QUEUE_ITEMS + 50
    t0 = time.perf_counter()
    for k in range(n):
        log.frame(*_frame_args(k, t_s=0.01 * (k + 1)))
    assert time.perf_counter() - t0 < 5.0          # nothing waited on the stuck writer
    assert log.messages_written == 0
    assert 49 <= log.dropped <= 51                # the writer may hold one frame
    assert log.messages_lost >= 4 * 49            # four messages a frame without an image
    stuck.set()
    log.close()
    msgs, complete = read_log(tmp_path / "bg.mcap")
    frames = [m["data"]["frame"] for m in msgs if m["topic"] == "/tacfoot/decision"]
    assert complete and frames[-1] == n - 1       # the newest got through
    assert len(frames) == n - log.dropped and frames == sorted(frames)
    assert log.status()["mcap_dropped"] == log.dropped
    assert log.status()["mcap_writer_cpu_s"] >= 0 and log.loop_cpu_s > 0


def test_in_the_background_close_writes_everything_queued(tmp_path):
    log = McapLog(tmp_path / "all.mcap", McapConfig(image_every=2, image_width=32),
                  clock=lambda: 0.0, background=True)
    for k in range(40):
        log.frame(*_frame_args(k, t_s=0.01 * (k + 1)))
        log.packet("out", P.Fault(faults=1, raised=1, pins_lost=0), 0.01 * k, k, 10)
    log.close()
    m = _by_topic(tmp_path / "all.mcap")
    assert [x[4]["frame"] for x in m["/tacfoot/decision"]] == list(range(40))
    assert len(m["/tacfoot/image"]) == len(m["/tacfoot/pins"]) == 20
    assert len(m["/tacfoot/packets/out"]) == len(m["/tacfoot/faults"]) == 40
    assert log.dropped == 0 and log.messages_lost == 0
    assert len(m["/tacfoot/log"]) == 40                # each FAULT also a log line
    assert log.messages_written == sum(len(v) for v in m.values()) == 40 * 7 + 20 * 2


class _LateQueue(deque):
    """A queue whose first empty take lets the loop queue ``frames`` and call close()
    before the writer looks at ``_closing``: the race a busy machine can hit."""

    def __init__(self, late):
        super().__init__()
        self.late = late

    def popleft(self):
        if not self and self.late is not None:
            late, self.late = self.late, None
            late()                  # after the writer found it empty
            raise IndexError("empty")
        return super().popleft()


def test_close_right_after_the_last_frame_still_writes_it(tmp_path):
    """Items queued while the writer found the queue empty are written, not left
    behind because close() had set ``_closing`` meanwhile."""
    log = McapLog(tmp_path / "late.mcap", McapConfig(image_every=2, image_width=32),
                  clock=lambda: 0.0)
    log._q = None

    def late():                                   # the loop's frames, then close()'s flag
        for k in range(3):
            log._put((log._frame, *_late_args(log, k)), 4)
        log._closing = True
    log._q = _LateQueue(late)
    log._wake, log._closing = threading.Event(), False
    log._drain()                                  # the writer's loop, here
    log._q = None
    log.close()
    m = _by_topic(tmp_path / "late.mcap")
    assert [x[4]["frame"] for x in m["/tacfoot/decision"]] == [0, 1, 2]


def _late_args(log, k):
    """What McapLog.frame queues for frame ``k`` (no image)."""
    dec = {"frame": k, "t_s": 0.01 * k, "probs": [0.5, 0.5], "texture": None, "pins": 2,
           "latency_ms": 1.0}
    return (dec, None, 10_000 + k, None, np.zeros((3, 3)), False, np.zeros(6), 0, 1.0)


def test_the_frame_values_are_copied_before_the_loop_reuses_its_buffers(tmp_path):
    """The writer encodes later: a frame's grid and image are copied at frame() so a
    buffer the loop overwrites afterwards does not change what was logged."""
    log = McapLog(tmp_path / "cp.mcap", McapConfig(image_every=1, image_width=32),
                  clock=lambda: 0.0, background=True)
    args = list(_frame_args(0))
    args[3].features.grid = np.full((3, 3), 0.5)
    log.frame(*args)
    args[3].features.grid[:] = 9.0                # the loop reuses the buffer
    args[3].features.pins[:] = -50.0
    log.close()
    m = _by_topic(tmp_path / "cp.mcap")
    assert grid_cells(m["/tacfoot/grid"][0][4]).ravel().tolist() == [0.5] * 9
    assert m["/tacfoot/pins"][0][4]["points"][0]["points"][0] == {"x": 5.0, "y": 10.0}


def test_the_live_view_asks_the_server_about_viewers_at_most_every_live_check_s(monkeypatch):
    """With no viewer the loop's only cost is LiveView.any(); it asks the server (one
    call per channel) at most every LIVE_CHECK_S, not per frame and packet."""
    live = object.__new__(liveview.LiveView)
    calls = []

    class Ch:
        def has_sinks(self):
            calls.append(1)
            return False
    live._ch = {t: Ch() for t in CHANNELS}
    live._any, live._any_at = False, float("-inf")
    now = [100.0]
    monkeypatch.setattr(liveview.time, "perf_counter", lambda: now[0])
    assert live.any() is False and len(calls) == len(CHANNELS)
    for _ in range(50):                            # within LIVE_CHECK_S: no more asks
        assert live.any() is False
    assert len(calls) == len(CHANNELS)
    now[0] += 1.01 * liveview.LIVE_CHECK_S
    live.any()
    assert len(calls) == 2 * len(CHANNELS)


def test_the_runtimes_log_lines_go_on_the_log_topic_until_close(tmp_path):
    """records=LOGGER: that logger's records (INFO and up) as foxglove.Log lines on
    /tacfoot/log; none after close (the handler is removed)."""
    import logging
    lg = logging.getLogger("tacfoot_test_records")
    lg.setLevel(logging.DEBUG)
    log = McapLog(tmp_path / "rec.mcap", McapConfig(), clock=lambda: 1.5, records=lg.name)
    lg.debug("not this one")
    lg.warning("camera %s reopened", "v4l2")
    log.close()
    lg.warning("after close")
    m = _by_topic(tmp_path / "rec.mcap")
    (line,) = [x[4] for x in m["/tacfoot/log"]]
    assert line["message"] == "camera v4l2 reopened" and line["level"] == 3
    assert line["name"] == lg.name and line["line"] > 0
    assert not lg.handlers
