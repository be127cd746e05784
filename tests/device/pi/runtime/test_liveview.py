"""The live view's limits (``--foxglove``): connections that never finish their
handshake, more connections than ``LIVE_MAX_CLIENTS``, and viewers that never read.

Each test waits on a condition with a generous deadline, never on a duration."""
from __future__ import annotations

import contextlib
import json
import os
import socket
import threading
import time

import pytest

from device.pi.runtime import liveview
from device.pi.runtime.liveview import LiveView

pytest.importorskip("foxglove")
websockets_sync = pytest.importorskip("websockets.sync.client")

SUBPROTOCOL = "foxglove.sdk.v1"


def _until(cond, what: str, deadline_s: float = 10.0):
    end = time.monotonic() + deadline_s
    while not cond():
        assert time.monotonic() < end, f"never happened: {what}"
        time.sleep(0.01)


def _fds() -> int:
    return len(os.listdir("/proc/self/fd"))


def _silent(port: int) -> socket.socket:
    s = socket.create_connection(("127.0.0.1", port), timeout=10)
    return s


def _read_to_eof(s: socket.socket) -> bytes:
    """Everything the leg sends before it closes (a timeout fails the test)."""
    got = b""
    while True:
        d = s.recv(4096)
        if not d:
            return got
        got += d


def _closed(s: socket.socket) -> bool:
    """Closed by the leg: the end of the stream, or a reset (it left bytes unread)."""
    try:
        return _read_to_eof(s) == b""
    except ConnectionResetError:
        return True


def _viewer_gets_server_info(port: int) -> str:
    with websockets_sync.connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL],
                                 open_timeout=10) as ws:
        return json.loads(ws.recv(timeout=10))["op"]


@pytest.fixture
def live(monkeypatch):
    views = []

    def make(**kw):
        v = LiveView("127.0.0.1", 0, **kw)
        views.append(v)
        return v
    yield make
    for v in views:
        _closes(v)


def _closes(view) -> bool:
    """view.close() returns (in a thread, so that a close that hangs fails the test
    rather than hanging it)."""
    th = threading.Thread(target=view.close, daemon=True)
    th.start()
    th.join(10)
    return not th.is_alive()


def test_connections_past_the_limit_are_refused_at_once_and_counted(live, monkeypatch):
    """LIVE_MAX_CLIENTS connections are served (silent ones too, within their
    handshake time); each one more gets a 503 and is closed at once, counted in
    foxglove_refused. The leg never holds more than the limit's file descriptors,
    and once the silent ones leave a real viewer connects."""
    monkeypatch.setattr(liveview, "LIVE_MAX_CLIENTS", 3, raising=False)
    monkeypatch.setattr(liveview, "LIVE_HANDSHAKE_S", 60.0, raising=False)
    view = live()
    before = _fds()
    held = [_silent(view.port) for _ in range(3)]
    _until(lambda: view.status()["foxglove_clients"] == 3, "3 clients accepted")
    extra = [_silent(view.port) for _ in range(40)]
    for s in extra:                               # a 503 and the close, at once
        assert _read_to_eof(s).startswith(b"HTTP/1.1 503 ")
    st = view.status()
    assert st["foxglove_refused"] == 40 and st["foxglove_clients"] == 3
    # the leg's side: 3 accepted sockets (and their relays, none yet: no handshake)
    assert _fds() - before - len(held) - len(extra) <= 3
    for s in held + extra:
        s.close()
    _until(lambda: view.status()["foxglove_clients"] == 0, "the silent ones gone")
    assert _viewer_gets_server_info(view.port) == "serverInfo"
    assert view.status()["foxglove_refused"] == 40


def test_a_connection_that_does_not_finish_its_handshake_in_time_is_closed(live, monkeypatch):
    """A silent connection, one that sends half a request and one that sends an
    endless request are closed after LIVE_HANDSHAKE_S (shortened here), counted in
    foxglove_handshake_closed; a viewer that handshakes is served meanwhile."""
    monkeypatch.setattr(liveview, "LIVE_HANDSHAKE_S", 0.3, raising=False)
    view = live()
    silent = _silent(view.port)
    half = _silent(view.port)
    half.sendall(b"GET / HTTP/1.1\r\nHost: leg\r\n")
    endless = _silent(view.port)
    endless.sendall(b"GET / HTTP/1.1\r\n" + b"X-Pad: aaaaaaaa\r\n" * 1100)
    t0 = time.monotonic()
    assert _viewer_gets_server_info(view.port) == "serverInfo"
    assert _read_to_eof(silent) == b"" and _read_to_eof(half) == b""
    assert _closed(endless)
    assert time.monotonic() - t0 >= 0.3
    st = view.status()
    assert st["foxglove_handshake_closed"] == 3 and st["foxglove_refused"] == 0
    _until(lambda: view.status()["foxglove_clients"] == 0, "all connections gone")
    for s in (silent, half, endless):
        s.close()


def test_many_silent_connections_leave_the_file_descriptors_as_they_were(live, monkeypatch):
    """300 connections that never handshake: the leg holds at most LIVE_MAX_CLIENTS
    of them, and its file descriptors come back to where they were."""
    monkeypatch.setattr(liveview, "LIVE_HANDSHAKE_S", 0.5, raising=False)
    view = live()
    before = _fds()
    socks = []
    for _ in range(300):
        socks.append(_silent(view.port))
    _until(lambda: view.status()["foxglove_refused"] + view.status()["foxglove_clients"]
           + view.status()["foxglove_handshake_closed"] == 300, "300 connections seen")
    assert _fds() - before - len(socks) <= liveview.LIVE_MAX_CLIENTS
    for s in socks:
        s.close()
    _until(lambda: view.status()["foxglove_clients"] == 0, "all connections gone")
    assert _fds() == before
    assert _viewer_gets_server_info(view.port) == "serverInfo"


def test_close_returns_with_a_silent_connection_and_a_viewer_open(monkeypatch):
    """SIGTERM closes the live view: a connection that never handshakes (the SDK's
    server alone waited on it for ever) and a viewer that is connected do not hold
    it, and they are closed."""
    monkeypatch.setattr(liveview, "LIVE_HANDSHAKE_S", 60.0, raising=False)
    view = LiveView("127.0.0.1", 0)
    silent = _silent(view.port)
    with websockets_sync.connect(f"ws://127.0.0.1:{view.port}", subprotocols=[SUBPROTOCOL],
                                 open_timeout=10, close_timeout=1) as ws:
        assert json.loads(ws.recv(timeout=10))["op"] == "serverInfo"
        assert _closes(view)
    assert _closed(silent)
    silent.close()


def _subscribed_viewer(stack, port: int, topic: str, rcvbuf: int = 16 * 1024):
    """A websockets client that subscribes to ``topic`` and returns once it has its
    first message (so the server has its subscription); the caller may then stop
    reading. A small receive buffer keeps the kernel's share small."""
    s = socket.socket()
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    s.connect(("127.0.0.1", port))
    ws = stack.enter_context(websockets_sync.connect(
        f"ws://127.0.0.1:{port}", sock=s, max_queue=1, subprotocols=[SUBPROTOCOL],
        open_timeout=10))
    stack.callback(ws.close_socket)      # at the end: no closing handshake to wait for
    while True:
        msg = ws.recv(timeout=10)
        if isinstance(msg, str) and json.loads(msg)["op"] == "advertise":
            ids = [c["id"] for c in json.loads(msg)["channels"] if c["topic"] == topic]
            if ids:
                ws.send(json.dumps({"op": "subscribe",
                                    "subscriptions": [{"id": 1, "channelId": ids[0]}]}))
                break
    return ws


def _payload(k: int, size: int) -> bytes:
    return json.dumps({"k": k, "pad": "x" * size}).encode()


def test_viewers_that_never_read_queue_a_bounded_amount_and_their_drops_are_counted(
        live, monkeypatch):
    with contextlib.ExitStack() as stack:
        _four_viewers(stack, live, monkeypatch)


def _four_viewers(stack, live, monkeypatch):
    """Three viewers subscribe and stop reading, a fourth reads. 300 messages of
    32 kB (9.6 MB each): what waits for each silent viewer stays under
    LIVE_CLIENT_BYTES plus one message, the rest is dropped and counted in
    foxglove_dropped, nobody is disconnected, and once the reader has caught up it
    gets new messages again."""
    monkeypatch.setattr(liveview, "LIVE_CLIENT_BYTES", 64 * 1024, raising=False)
    view = live(backlog=4096)           # the SDK's own queue never drops here
    topic = "/tacfoot/decision"
    ping = [0]

    def first_message(ws):
        box = []
        th = threading.Thread(target=lambda: box.append(ws.recv(timeout=10)), daemon=True)
        th.start()
        while th.is_alive():
            view.publish(topic, ping[0], _payload(-1, 10))
            ping[0] += 1
            th.join(0.02)
        assert box and box[0][0] == 1               # a messageData
    silent = []
    for _ in range(3):
        ws = _subscribed_viewer(stack, view.port, topic)
        first_message(ws)
        silent.append(ws)
    reader = _subscribed_viewer(stack, view.port, topic)
    first_message(reader)
    got = []

    def read():         # the k of each message, in order
        try:
            while True:
                m = reader.recv(timeout=10)
                if not isinstance(m, str) and m[0] == 1:
                    got.append(json.loads(bytes(m[13:]))["k"])
        except Exception:
            pass
    th = threading.Thread(target=read, daemon=True)
    th.start()
    size, n = 32 * 1024, 300
    for k in range(n):
        view.publish(topic, 10_000 + k, _payload(k, size))
    front = view.front
    # the silent viewers: at most ~10 messages each fit in the queues and buffers
    _until(lambda: front.dropped >= 3 * (n - 20), "the silent viewers' drops counted")
    for conn in {c.c: c for c in list(front._conns.values())}.values():
        assert len(conn.to_client) <= liveview.LIVE_CLIENT_BYTES + size + 100
    st = view.status()
    assert st["foxglove_dropped"] == front.dropped and st["foxglove_slow_closed"] == 0
    assert st["foxglove_clients"] == 4
    # the reader, once it has caught up, gets what comes next (the marker is sent
    # again until it arrives: the flood's tail may still fill the reader's queue)
    end = time.monotonic() + 10
    while n not in got:
        assert time.monotonic() < end, "the reader never got a new message"
        view.publish(topic, 20_000, _payload(n, 10))
        time.sleep(0.05)
    assert got == sorted(got) and th.is_alive()


def _frame(opcode: int, payload: bytes, fin: bool = True) -> bytes:
    n = len(payload)
    head = bytes([(0x80 if fin else 0) | opcode])
    if n < 126:
        head += bytes([n])
    elif n < 65536:
        head += bytes([126]) + n.to_bytes(2, "big")
    else:
        head += bytes([127]) + n.to_bytes(8, "big")
    return head + payload


@pytest.mark.parametrize("chunk", [1, 3, 7, 1000, 10 ** 6])
def test_the_relay_keeps_whole_frames_and_drops_only_data_messages(chunk):
    """The relay's frame reader, fed in chunks of any size: the HTTP answer and every
    frame pass whole while the viewer's queue is under LIVE_CLIENT_BYTES; past it,
    messageData frames (and the continuation frames of one) are dropped whole and
    counted, while text (advertise ...) and control frames (ping, close) still pass."""
    front = object.__new__(liveview._LiveFront)
    front.client_bytes, front.dropped = 1000, 0
    conn = liveview._Conn(None, 0.0)
    http = b"HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\n\r\n"
    big = _frame(2, b"\x01" + b"b" * 1200)                 # passes: the queue is empty
    data = _frame(2, b"\x01" + b"d" * 200)                  # dropped from here on
    mid = _frame(2, b"\x01" + b"m" * 70_000)                # 8-byte length form
    text = _frame(1, b'{"op":"advertise"}')
    ping = _frame(9, b"")
    frag = _frame(2, b"\x01" + b"f" * 10, fin=False) + ping + _frame(0, b"g" * 10)
    other = _frame(2, b"\x02" + b"o" * 10)                  # not messageData: passes
    stream = http + big + data + mid + text + frag + other + ping
    for i in range(0, len(stream), chunk):
        front._from_server(conn, stream[i:i + chunk])
    assert bytes(conn.to_client) == http + big + text + ping + other + ping
    assert front.dropped == 3 and not conn.inbuf and conn.left == 0


def test_the_client_limit_is_an_option_checked_at_start(live, capsys):
    """--foxglove-max-clients N: outside 1..1000 the runtime refuses to start with one
    line naming the option and the value (exit 2); LiveView(max_clients=1) serves one
    connection and refuses the next."""
    from device.pi.__main__ import main
    rc = main(["run", "--camera", "sim://press-hard", "--imu", "none", "--serial", "loop://",
               "--frames", "2", "--foxglove", "127.0.0.1:0", "--foxglove-max-clients", "0"])
    line, = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and "--foxglove-max-clients" in line and "got 0" in line
    with pytest.raises(ValueError, match="--foxglove-max-clients.*got 0"):
        LiveView("127.0.0.1", 0, max_clients=0)
    view = live(max_clients=1)
    first = _silent(view.port)
    _until(lambda: view.status()["foxglove_clients"] == 1, "one client accepted")
    second = _silent(view.port)
    assert _read_to_eof(second).startswith(b"HTTP/1.1 503 ")
    assert view.status()["foxglove_refused"] == 1
    first.close()
    second.close()


@pytest.mark.parametrize("offered", [["foxglove.websocket.v1"],
                                     ["foxglove.websocket.v1", "foxglove.sdk.v1"]])
def test_viewers_that_speak_foxglove_websocket_v1_connect(live, offered):
    """The SDK's server accepts only foxglove.sdk.v1 (the same protocol under a new
    name): a viewer offering only foxglove.websocket.v1 is served under the name it
    asked for; one offering both gets the SDK's."""
    view = live()
    with websockets_sync.connect(f"ws://127.0.0.1:{view.port}", subprotocols=offered,
                                 open_timeout=5) as ws:
        assert ws.subprotocol == ("foxglove.sdk.v1" if len(offered) == 2 else offered[0])
        assert json.loads(ws.recv(timeout=5))["op"] == "serverInfo"
