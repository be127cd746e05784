"""``--foxglove [HOST:]PORT``: the leg's channels served live to Foxglove viewers, with
bounds the SDK's own server lacks: a client limit, a handshake deadline, a per-viewer
queue whose overflow is dropped and counted (docs/viewing.md). The runtime runs it in
the MCAP writer's process (:mod:`device.pi.runtime.mcapproc`), or beside a writer
thread (:mod:`device.pi.runtime.mcaplog`).
"""
from __future__ import annotations

import json
import re
import selectors
import socket
import threading
import time
from device.pi.runtime.mcapfiles import INSTALL_HINT, McapLogError
from device.pi.runtime.mcapmsg import channels as _channels
from device.errors import InputError

#: messages the SDK's server queues per viewer before it drops the oldest (uncounted;
#: :class:`_LiveFront` reads them at once and does the counted dropping)
LIVE_BACKLOG = 256
#: how often the loop asks the live server whether any viewer is subscribed, s
LIVE_CHECK_S = 0.05
#: viewers served at once (``--foxglove-max-clients``); more are refused at once
LIVE_MAX_CLIENTS = 8
#: a connection must send its whole WebSocket upgrade request within this, s
LIVE_HANDSHAKE_S = 5.0
#: ... of at most this many bytes
LIVE_REQUEST_BYTES = 16 * 1024
#: bytes queued for one viewer past which its messages are dropped (counted)
LIVE_CLIENT_BYTES = 512 * 1024


class LiveView:
    """``--foxglove [HOST:]PORT``: the same channels served live over Foxglove's
    WebSocket protocol (``foxglove-sdk``, its own context). A channel no viewer is
    subscribed to costs one check per message (:meth:`wants`); with no viewer at
    all, :meth:`McapLog.frame` builds nothing. A message is handed to the server's
    queue and never waited for.

    The SDK's server has no handshake timeout, no client limit and no count of what
    it drops, so it listens on 127.0.0.1 at a free port and the public port is
    :class:`_LiveFront`'s: at most ``max_clients`` viewers (more are refused at
    once), each given ``handshake_s`` to send its upgrade request, and at most
    ``client_bytes`` queued for each before its messages are dropped (counted)."""

    def __init__(self, host: str, port: int, channels=None, backlog: int | None = None,
                 max_clients: int | None = None, handshake_s: float | None = None,
                 client_bytes: int | None = None):
        max_clients = LIVE_MAX_CLIENTS if max_clients is None else max_clients
        if not (isinstance(max_clients, int) and 1 <= max_clients <= 1000):
            raise InputError(f"--foxglove-max-clients must be 1..1000, got {max_clients!r}")
        try:
            import foxglove
        except ImportError:
            raise McapLogError(INSTALL_HINT.replace("MCAP logging", "--foxglove")) from None
        self._ctx = foxglove.Context()
        try:
            self.server = foxglove.start_server(
                name="tacfoot", host="127.0.0.1", port=0, context=self._ctx,
                message_backlog_size=backlog or LIVE_BACKLOG)
        except Exception as exc:
            raise McapLogError(f"--foxglove {host}:{port}: cannot serve ({exc})") from None
        try:
            self.front = _LiveFront(
                host, int(port), int(self.server.port), max_clients=max_clients,
                handshake_s=LIVE_HANDSHAKE_S if handshake_s is None else handshake_s,
                client_bytes=client_bytes or LIVE_CLIENT_BYTES)
        except OSError as exc:
            self.close()
            raise McapLogError(f"--foxglove {host}:{port}: cannot serve "
                               f"({exc.strerror or exc})") from None
        self.host, self.port = host, self.front.port
        self._ch = {}
        for topic, schema in (channels or _channels()).items():
            sch = foxglove.Schema(name=schema["title"], encoding="jsonschema",
                                  data=json.dumps(schema).encode())
            self._ch[topic] = foxglove.Channel(topic, schema=sch, message_encoding="json",
                                               context=self._ctx)
        self.messages_sent = 0
        self.errors = 0
        self._any, self._any_at = False, float("-inf")

    def wants(self, topic: str) -> bool:
        ch = self._ch.get(topic)
        return ch is not None and ch.has_sinks()

    def any(self) -> bool:
        """Whether any viewer is subscribed to anything; asked of the server at most
        every :data:`LIVE_CHECK_S` (the loop asks this per frame and per packet),
        so a new viewer gets its first messages within that time."""
        now = time.perf_counter()
        if now - self._any_at >= LIVE_CHECK_S:
            self._any = any(ch.has_sinks() for ch in self._ch.values())
            self._any_at = now
        return self._any

    def publish(self, topic: str, t_ns: int, data: bytes) -> None:
        try:
            self._ch[topic].log(data, log_time=int(t_ns))
            self.messages_sent += 1
        except Exception:
            self.errors += 1

    def close(self) -> None:
        front = getattr(self, "front", None)
        if front is not None:
            front.close()
        try:
            self.server.stop()
        except Exception:
            pass

    def status(self) -> dict:
        st = {"foxglove_port": self.port, "foxglove_messages_sent": self.messages_sent,
              "foxglove_errors": self.errors}
        st.update(self.front.status())
        return st


class _Conn:
    """One viewer's connection through :class:`_LiveFront`."""
    __slots__ = ("c", "u", "deadline", "req", "to_client", "to_up", "head", "ws", "inbuf",
                 "left", "dropping", "drop_msg", "masks", "alias")

    def __init__(self, c: socket.socket, deadline: float):
        self.c, self.u, self.deadline = c, None, deadline
        self.req = bytearray()            # the upgrade request, until it is whole
        self.to_client = bytearray()      # bytes the viewer has not taken yet
        self.to_up = bytearray()          # bytes from the viewer for the server
        self.head = bytearray()           # the server's HTTP answer, until it is whole
        self.ws = None                    # None: in the HTTP answer; True: frames; False: raw
        self.inbuf = bytearray()          # a frame header split between two reads
        self.left = 0                     # payload bytes left in the current frame
        self.dropping = False             # the current frame is being dropped
        self.drop_msg = False             # the current fragmented message is dropped
        self.masks = {}                   # socket -> registered selector events
        self.alias = False                # asked for foxglove.websocket.v1 (see _subprotocol)


class _LiveFront:
    """The live view's public port: a TCP front in one thread (``selectors``,
    non-blocking sockets) before the SDK's server on 127.0.0.1.

    - At most ``max_clients`` connections at once, the ones still in their handshake
      included; one more is answered ``503`` and closed at once (``foxglove_refused``).
    - A connection must send its whole HTTP upgrade request (at most
      :data:`LIVE_REQUEST_BYTES`) within ``handshake_s`` of its accept, else it is
      closed (``foxglove_handshake_closed``). Only then is the server connected.
    - After that the bytes are relayed both ways. The server's frames to the viewer
      are read as WebSocket frames; once ``client_bytes`` wait for a viewer, its
      next data messages (``messageData``) are dropped whole and counted
      (``foxglove_dropped``); the control messages (advertise, status ...) are always
      passed, and a viewer with four times that waiting, plus 1 MiB, is closed
      (``foxglove_slow_closed``). The viewer's socket send buffer is set to
      ``min(client_bytes, 256 KiB)``, so the kernel's share is bounded too.
    - An ``accept`` that fails (no file descriptors left) pauses the listener for
      :data:`ACCEPT_PAUSE_S`; it is never given up."""

    ACCEPT_PAUSE_S = 0.1
    REFUSAL = (b"HTTP/1.1 503 Service Unavailable\r\nContent-Length: 0\r\n"
               b"Connection: close\r\n\r\n")

    def __init__(self, host: str, port: int, upstream_port: int, *, max_clients: int,
                 handshake_s: float, client_bytes: int):
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self._lsock = socket.create_server((host, port), family=family, backlog=128)
        self._lsock.setblocking(False)
        self.port = self._lsock.getsockname()[1]
        self.upstream = ("127.0.0.1", upstream_port)
        self.max_clients, self.handshake_s = max_clients, float(handshake_s)
        self.client_bytes = int(client_bytes)
        self.slow_bytes = 4 * self.client_bytes + (1 << 20)
        self.sndbuf = min(self.client_bytes, 256 * 1024)
        self.refused = self.handshake_closed = self.dropped = self.slow_closed = 0
        self.accept_errors = self.clients = self.errors = 0
        self.cpu_s = 0.0                           # the front thread's CPU time, s
        self._conns: dict[socket.socket, _Conn] = {}
        self._sel = selectors.DefaultSelector()
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._sel.register(self._wake_r, selectors.EVENT_READ)
        self._sel.register(self._lsock, selectors.EVENT_READ)
        self._paused_until = None
        self._stop = False
        self._thread = threading.Thread(target=self._serve, name="tacfoot-live-front",
                                        daemon=True)
        self._thread.start()

    def status(self) -> dict:
        return {"foxglove_clients": self.clients,
                "foxglove_refused": self.refused,
                "foxglove_handshake_closed": self.handshake_closed,
                "foxglove_dropped": self.dropped, "foxglove_slow_closed": self.slow_closed,
                "foxglove_front_errors": self.errors, "foxglove_accept_errors": self.accept_errors,
                "foxglove_front_cpu_s": round(self.cpu_s, 4)}

    def close(self) -> None:
        self._stop = True
        try:
            self._wake_w.send(b"x")
        except OSError:
            pass
        self._thread.join(2.0)
        if self._thread.is_alive():
            return                                 # stuck: the daemon thread goes with us
        for conn in list(self._conns.values()):
            self._drop(conn)
        for s in (self._lsock, self._wake_r, self._wake_w):
            s.close()
        self._sel.close()

    # -- the thread ---------------------------------------------------------------
    def _serve(self) -> None:
        while not self._stop:
            self.cpu_s = time.thread_time()
            now = time.monotonic()
            waits = [c.deadline - now for c in self._conns.values() if c.u is None]
            if self._paused_until is not None:
                waits.append(self._paused_until - now)
            timeout = max(0.0, min(waits)) if waits else None
            for key, events in self._sel.select(timeout):
                sock = key.fileobj
                if sock is self._lsock:
                    self._accept()
                elif sock is self._wake_r:
                    try:
                        self._wake_r.recv(64)
                    except OSError:
                        pass
                else:
                    conn = self._conns.get(sock)
                    if conn is not None:
                        try:
                            self._event(conn, sock, events)
                        except Exception:          # a bug must cost one viewer, not the port
                            self.errors += 1
                            self._drop(conn)
            self._expire(time.monotonic())

    def _accept(self) -> None:
        for _ in range(64):                        # a burst, not for ever
            try:
                c, _addr = self._lsock.accept()
            except BlockingIOError:
                return
            except OSError:                        # EMFILE, ENFILE, ENOBUFS ...
                self.accept_errors += 1
                self._sel.unregister(self._lsock)
                self._paused_until = time.monotonic() + self.ACCEPT_PAUSE_S
                return
            c.setblocking(False)
            if self.clients >= self.max_clients:
                self.refused += 1
                try:
                    c.send(self.REFUSAL)
                except OSError:
                    pass
                c.close()
                continue
            try:                                   # the kernel's share, bounded too
                c.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self.sndbuf)
            except OSError:
                pass
            conn = _Conn(c, time.monotonic() + self.handshake_s)
            self._conns[c] = conn
            self.clients += 1
            self._watch(conn, c, selectors.EVENT_READ)

    def _expire(self, now: float) -> None:
        if self._paused_until is not None and now >= self._paused_until:
            self._paused_until = None
            self._sel.register(self._lsock, selectors.EVENT_READ)
        for conn in [c for c in self._conns.values() if c.u is None and now >= c.deadline]:
            self.handshake_closed += 1
            self._drop(conn)

    def _watch(self, conn: _Conn, sock: socket.socket, events: int) -> None:
        had = conn.masks.get(sock, 0)
        if events == had:
            return
        if not events:
            self._sel.unregister(sock)
        elif not had:
            self._sel.register(sock, events)
        else:
            self._sel.modify(sock, events)
        conn.masks[sock] = events

    def _drop(self, conn: _Conn) -> None:
        if self._conns.get(conn.c) is conn:
            self.clients -= 1
        for sock in (conn.c, conn.u):
            if sock is None:
                continue
            if conn.masks.get(sock):
                try:
                    self._sel.unregister(sock)
                except (KeyError, ValueError):
                    pass
            self._conns.pop(sock, None)
            sock.close()
        conn.masks.clear()

    def _event(self, conn: _Conn, sock: socket.socket, events: int) -> None:
        try:
            if events & selectors.EVENT_READ:
                data = sock.recv(1 << 16)
                if not data:
                    self._drop(conn)
                    return
                if sock is conn.u:
                    self._from_server(conn, data)
                elif conn.u is None:
                    self._handshake(conn, data)
                else:
                    conn.to_up += data
            if events & selectors.EVENT_WRITE:
                buf = conn.to_client if sock is conn.c else conn.to_up
                if buf:
                    del buf[:sock.send(buf)]
        except (BlockingIOError, InterruptedError):
            pass
        except OSError:                            # a reset, a broken pipe
            self._drop(conn)
            return
        if conn.c.fileno() < 0:
            return
        if len(conn.to_client) > self.slow_bytes:
            self.slow_closed += 1
            self._drop(conn)
            return
        self._arm(conn)

    def _arm(self, conn: _Conn) -> None:
        """The events each side waits for: the viewer's bytes while the server is
        not behind with them, and a write wherever bytes wait."""
        if conn.u is None:
            return
        read_c = selectors.EVENT_READ if len(conn.to_up) < (1 << 20) else 0
        self._watch(conn, conn.c, read_c | (selectors.EVENT_WRITE if conn.to_client else 0))
        self._watch(conn, conn.u,
                    selectors.EVENT_READ | (selectors.EVENT_WRITE if conn.to_up else 0))

    def _handshake(self, conn: _Conn, data: bytes) -> None:
        conn.req += data
        if b"\r\n\r\n" not in conn.req:
            if len(conn.req) > LIVE_REQUEST_BYTES:
                self.handshake_closed += 1
                self._drop(conn)
            return
        u = socket.create_connection(self.upstream, timeout=1.0)
        u.setblocking(False)
        conn.u = u
        self._conns[u] = conn
        conn.to_up += _subprotocol(conn, bytes(conn.req))
        conn.req = bytearray()

    def _from_server(self, conn: _Conn, data: bytes) -> None:
        if conn.ws is None:                        # the HTTP answer to the upgrade
            conn.head += data
            end = conn.head.find(b"\r\n\r\n")
            if end < 0:
                return
            head = bytes(conn.head[:end + 4])
            if conn.alias:                         # answer in the name the viewer asked
                head = _PROTO_ANSWER.sub(lambda m: m.group(1) + OLD_SUBPROTOCOL.encode(), head)
            conn.to_client += head
            conn.ws = bytes(conn.head[:13]) == b"HTTP/1.1 101 "
            data = bytes(conn.head[end + 4:])
            conn.head = bytearray()
        if not conn.ws:
            conn.to_client += data
            return
        buf = conn.inbuf
        buf += data
        out, n, pos = conn.to_client, len(buf), 0
        mv = memoryview(buf)
        while pos < n:
            if conn.left:                          # inside a frame's payload
                k = min(conn.left, n - pos)
                if not conn.dropping:
                    out += mv[pos:pos + k]
                pos += k
                conn.left -= k
                continue
            if n - pos < 2:
                break
            b0, b1 = buf[pos], buf[pos + 1]
            size, h = b1 & 0x7F, 2
            if size >= 126:
                h = 4 if size == 126 else 10
                if n - pos < h:
                    break
                size = int.from_bytes(buf[pos + 2:pos + h], "big")
            if b1 & 0x80:                          # masked (not from a server, but legal)
                h += 4
            if n - pos < h + (1 if size else 0):   # the header and the op byte
                break
            opcode = b0 & 0x0F
            if opcode & 0x8:                       # close, ping, pong
                drop = False
            elif opcode == 0:                      # a continuation: as its message
                drop = conn.drop_msg
            else:
                drop = (opcode == 2 and size > 0 and buf[pos + h] == 1
                        and len(out) >= self.client_bytes and not b1 & 0x80)
                conn.drop_msg = drop
                self.dropped += drop
            if not drop:
                out += mv[pos:pos + h]
            conn.dropping, conn.left = drop, size
            pos += h
        mv.release()
        del buf[:pos]


#: the subprotocol older viewers ask for; the SDK's server accepts only SDK_SUBPROTOCOL,
#: the same protocol on the wire under a new name (Foxglove's stance, quoted in
#: lichtblick-suite/lichtblick pull request 819): the front renames it both ways
OLD_SUBPROTOCOL, SDK_SUBPROTOCOL = "foxglove.websocket.v1", "foxglove.sdk.v1"
_PROTO_ASK = re.compile(rb"(?im)^(sec-websocket-protocol:[ \t]*)([^\r\n]*)")
_PROTO_ANSWER = re.compile(rb"(?im)^(sec-websocket-protocol:[ \t]*)foxglove\.sdk\.v1")


def _subprotocol(conn: _Conn, req: bytes) -> bytes:
    """The upgrade request, its ``foxglove.websocket.v1`` asked as ``foxglove.sdk.v1``
    when the viewer does not offer the latter (``conn.alias`` then set)."""
    m = _PROTO_ASK.search(req)
    if m is None:
        return req
    offered = [p.strip() for p in m.group(2).decode("latin-1").split(",")]
    if OLD_SUBPROTOCOL not in offered or SDK_SUBPROTOCOL in offered:
        return req
    conn.alias = True
    return req[:m.start(2)] + SDK_SUBPROTOCOL.encode() + req[m.end(2):]


def parse_hostport(text: str, default_host: str = "127.0.0.1") -> tuple[str, int]:
    """``[HOST:]PORT`` -> (host, port); ValueError naming the text."""
    host, _, port = str(text).rpartition(":")
    try:
        p = int(port)
    except ValueError:
        p = -1
    if not 0 <= p <= 65535:
        raise InputError(f"--foxglove {text!r}: give [HOST:]PORT, a port 0..65535 "
                         f"(e.g. 8765 or 0.0.0.0:8765)")
    return (host or default_host), p
