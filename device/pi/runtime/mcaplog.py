"""The leg's MCAP log: ``python -m device.pi run --mcap FILE`` (docs/viewing.md).

What the leg senses, in the format Foxglove and ROS 2 read, one channel per kind
(all JSON-encoded; the two images ones use Foxglove's well-known schemas, so the
Image panel draws the pins and vectors over the frame):

===========================  =========================  ==============================
topic                        schema                     when
===========================  =========================  ==============================
``/tacfoot/image``           ``foxglove.CompressedImage``  every ``image_every``-th frame
``/tacfoot/pins``            ``foxglove.ImageAnnotations`` with each image
``/tacfoot/grid``            ``tacfoot.ContactGrid``    every frame
``/tacfoot/decision``        ``tacfoot.Decision``       every frame (the --json-log line)
``/tacfoot/imu``             ``tacfoot.Imu``            every frame
``/tacfoot/latency``         ``tacfoot.Latency``        every frame
``/tacfoot/packets/out``     ``tacfoot.Packet``         every packet sent
``/tacfoot/packets/in``      ``tacfoot.Packet``         every packet received
``/tacfoot/faults``          ``tacfoot.Faults``         every FAULT packet sent
===========================  =========================  ==============================

Times: a frame's messages are logged at the frame's own time (``t_s`` of the JSON
log, in ns). Packets and faults, which happen between frames, are logged on the
same time line: the runtime's clock, shifted by the last frame's offset between
the two (clamped at 0); those before the first frame at 0.

Files roll over by size: ``run.mcap``, then ``run-0001.mcap``, ``run-0002.mcap``
... once a file reaches ``max_mb``. Each is a complete MCAP file with its own
schemas and channels. The file is written unbuffered, one chunk per write (chunk
size ``[mcap] chunk_kb``), so a crash loses at most the chunk being filled and what
the writer thread had not yet taken (below; normally nothing, as it keeps up):
:func:`read_log` reads the complete chunks of a file that has no footer, and
:func:`recover` rewrites them as a well-formed file.

The loop does not wait on the log (``background=True``, the runtime's): per frame it
copies the values the messages need and queues them; a writer thread encodes them
(the small messages from templates, :mod:`device.pi.runtime.mcapmsg`; the JPEG only
on an image frame), compresses the chunks and writes them. When the writer falls
:data:`QUEUE_ITEMS` frames and packets behind, the oldest is dropped and counted
(``mcap_dropped``, and its messages in ``mcap_messages_lost``): the newest wins.

The log is not the job: :class:`McapLog` never raises into the loop. A failed
write (a full disk, a vanished mount, a bad frame) is counted in ``messages_lost``
(the status file's ``mcap_messages_lost``) and warned about once; the broken file
is dropped and the next one is tried after :data:`RETRY_S`.

``--foxglove [HOST:]PORT`` serves the same channels live (:class:`LiveView`, over
``foxglove-sdk``'s WebSocket server behind :class:`_LiveFront`, which bounds the
viewers, their handshake time and what each may queue): the runtime's one hook,
``LegRuntime.mcap``, is an :class:`McapLog` with a file, a live view, or both.

The ``mcap`` and ``foxglove-sdk`` packages are the ``viz`` extra (``pip install
.[viz]``): this module imports them only when a log or a view is opened, so the
base install runs without them.
"""
from __future__ import annotations

import json
import selectors
import socket
import sys
import threading
import time
from collections import deque
from pathlib import Path

import numpy as np

from device.pi import protocol as P
from device.pi.runtime import mcapmsg as M
from device.pi.runtime.mcapmsg import (  # noqa: F401  (the names this module had)
    CHANNELS, COMPRESSED_IMAGE, FRAME_ID, IMAGE_ANNOTATIONS, LINE_LIST, POINTS, annotations)

#: after a failed write, the next file is tried this much later (runtime clock, s)
RETRY_S = 1.0
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
#: frames and packets the writer thread holds before the oldest is dropped
QUEUE_ITEMS = 128
#: the writer thread looks for queued frames this often (s): it takes them in batches,
#: its code warm in the cache, instead of waking once per frame
WRITER_POLL_S = 0.02
#: close() waits this long for the writer thread to write what is queued, s
CLOSE_WAIT_S = 10.0
INSTALL_HINT = "MCAP logging needs the viz extra: pip install .[viz]"


class McapLogError(OSError):
    """The MCAP log cannot be opened (no ``mcap`` package, a bad path)."""


def roll_name(path: Path, n: int) -> Path:
    """The n-th file of a log: ``run.mcap``, ``run-0001.mcap``, ..."""
    return path if n == 0 else path.with_name(f"{path.stem}-{n:04d}{path.suffix}")


def _mcap():
    try:
        from mcap import writer
    except ImportError:
        raise McapLogError(INSTALL_HINT) from None
    return writer


def _copy(a):
    return None if a is None else np.array(a, copy=True)


class _CountingFile:
    """An unbuffered file that counts the bytes written (the roll-over size)."""

    def __init__(self, path: Path):
        self.fh = open(path, "wb", buffering=0)
        self.size = 0

    def write(self, data) -> int:
        n = len(data)
        mv = memoryview(data)
        done = 0
        while done < n:                       # a raw write may take less than asked
            k = self.fh.write(mv[done:])
            if not k:
                raise OSError("the file took no bytes")
            done += k
        self.size += n
        return n

    def tell(self) -> int:
        return self.size

    def flush(self) -> None:
        pass

    def close(self) -> None:
        self.fh.close()


class McapLog:
    """The runtime's MCAP writer. ``cfg`` is the leg config's ``[mcap]`` section;
    ``clock`` the runtime's. The runtime calls :meth:`frame` once per frame,
    :meth:`packet` for every packet and :meth:`close` at the end.

    ``background=True`` (the runtime's): :meth:`frame` and :meth:`packet` only copy
    the frame's values and queue them; a writer thread encodes them, compresses the
    chunks and writes the file, so the loop never waits on encoding or the disk. The
    queue holds :data:`QUEUE_ITEMS` frames and packets; when the writer falls that
    far behind, the oldest is dropped (the newest wins) and counted in ``dropped``
    and, by its messages, in ``messages_lost``. ``background=False`` (the host's
    offline commands, which must not drop): the caller's thread does the work."""

    def __init__(self, path, cfg, *, max_mb: float = 256.0, clock=None, channels=None,
                 live=None, background: bool = False):
        #: topic -> JSON schema: :data:`CHANNELS` and any more (``host export mcap``)
        self.channels = {**CHANNELS, **(channels or {})}
        self.live = live             # a LiveView (--foxglove), or None
        self.cfg = cfg
        self.clock = clock
        self.files: list[str] = []
        self.messages_written = 0
        self._lost = 0               # the writer's failures (its thread)
        self._dropped_msgs = 0       # messages of the items dropped from the queue
        self.dropped = 0             # queue items (frames, packets) dropped
        self.warned = False
        self._w = None
        self._retry_at = None
        self._offset_s = None        # frame time - runtime clock, at the last frame
        self._frames = 0
        self._q: deque | None = None
        self._thread = None
        self.loop_cpu_s = 0.0        # CPU the loop's thread spent in frame() and packet()
        self.writer_cpu_s = 0.0      # CPU of the writer thread (background=True)
        self.path = None if path is None else Path(path)
        self._file_on = path is not None
        if path is None and live is None:
            raise McapLogError("McapLog needs a file (--mcap), a live view (--foxglove) "
                               "or both; got neither")
        if path is not None:
            self._open_first(path, max_mb)
        if background:
            self._q = deque()
            self._wake = threading.Event()
            self._closing = False
            self._thread = threading.Thread(target=self._drain, name="mcap-writer",
                                            daemon=True)
            self._thread.start()

    def _open_first(self, path, max_mb) -> None:
        self._writer_mod = _mcap()
        folder = self.path.resolve().parent
        if self.path.is_dir():
            raise McapLogError(f"--mcap {str(path)!r} is a folder; give a file, e.g. "
                               f"{self.path / 'run.mcap'}")
        if not folder.is_dir():
            raise McapLogError(f"--mcap {str(path)!r}: the folder {folder} does not exist")
        if not max_mb > 0:
            raise McapLogError(f"--mcap-max-mb must be > 0, got {max_mb}")
        self.max_bytes = int(max_mb * 1024 * 1024)
        self._n = 0                  # the next file's number
        self._fh = None
        self._ids: dict[str, int] = {}
        try:
            self._open()
        except OSError as exc:
            raise McapLogError(f"--mcap {str(path)!r}: {exc.strerror or exc}") from None

    @property
    def messages_lost(self) -> int:
        """Messages not written: failed writes and the messages of dropped items."""
        return self._lost + self._dropped_msgs

    # -- files -----------------------------------------------------------------
    def _open(self) -> None:
        W = self._writer_mod
        p = roll_name(self.path, self._n)
        self._n += 1
        self._fh = _CountingFile(p)
        self.files.append(str(p))
        w = W.Writer(self._fh, chunk_size=self.cfg.chunk_kb * 1024,
                     compression=W.CompressionType.ZSTD)
        w.start(profile="", library="tacfoot")
        schemas: dict[str, int] = {}
        self._ids = {}
        for topic, schema in self.channels.items():
            name = schema["title"]
            if name not in schemas:
                schemas[name] = w.register_schema(name, "jsonschema",
                                                  json.dumps(schema).encode())
            self._ids[topic] = w.register_channel(topic, "json", schemas[name])
        self._w = w

    def _drop_file(self) -> None:
        try:
            self._fh.close()
        except Exception:
            pass
        self._w = None

    def _finish(self) -> None:
        w, self._w = self._w, None
        try:
            w.finish()
        finally:
            self._fh.close()

    # -- the queue (background=True) ---------------------------------------------
    def _put(self, item: tuple, n_msgs: int) -> None:
        """Queue ``(handler, args...)``; when full, the oldest item goes (counted)."""
        q = self._q
        if len(q) >= QUEUE_ITEMS:
            try:
                old = q.popleft()
                self.dropped += 1
                self._dropped_msgs += old[-1]
            except IndexError:       # the writer took it meanwhile
                pass
        q.append(item + (n_msgs,))

    def _drain(self) -> None:
        """The writer thread: handle the queued items in order until closed."""
        q, wake = self._q, self._wake
        c0 = time.thread_time()
        while True:
            self.writer_cpu_s = time.thread_time() - c0
            try:
                fn, *args, _n = q.popleft()
            except IndexError:
                if self._closing:
                    return
                wake.wait(WRITER_POLL_S)     # woken early only by close()
                continue
            try:
                fn(*args)
            except Exception as exc:
                self._fail(exc)
            time.sleep(0)            # the GIL to the loop, if it waits, between items

    def _do(self, fn, args: tuple, n_msgs: int) -> None:
        if self._q is None:
            try:
                fn(*args)
            except Exception as exc:
                self._fail(exc)
        else:
            self._put((fn,) + args, n_msgs)

    # -- writing ---------------------------------------------------------------
    def write(self, topic: str, t_ns: int, doc: dict) -> None:
        """One message on ``topic`` at ``t_ns``; a failure is counted, never raised."""
        self._do(self._write_doc, (topic, int(t_ns), doc), 1)

    def image(self, t_ns: int, image, ff, reference=None) -> None:
        """The frame on ``/tacfoot/image`` and its pins on ``/tacfoot/pins``."""
        self._do(self._image, (int(t_ns), _copy(image), _copy(ff.pins), _copy(ff.vectors),
                               _copy(ff.lost), _copy(reference)), 2)

    def _write_doc(self, topic: str, t_ns: int, doc: dict) -> None:
        if self._on(topic):
            self._write(topic, t_ns, json.dumps(doc, separators=(",", ":")).encode())

    def _on(self, topic: str) -> bool:
        """Whether a message on ``topic`` goes anywhere (the file, or a live viewer
        subscribed to it): nothing is built for a topic no one takes."""
        return self._file_on or (self.live is not None and self.live.wants(topic))

    def _write(self, topic: str, t_ns: int, data: bytes) -> None:
        if self.live is not None and self.live.wants(topic):
            self.live.publish(topic, t_ns, data)
        if not self._file_on:
            return
        if self._w is None:
            now = self._now()
            if self._retry_at is None or now < self._retry_at:
                self._lost += 1
                return
            try:
                self._retry_at = None
                self._open()
            except Exception as exc:
                return self._fail(exc)
        try:
            self._w.add_message(self._ids[topic], log_time=t_ns, publish_time=t_ns, data=data)
            self.messages_written += 1
            if self._fh.size >= self.max_bytes:
                self._finish()
                self._open()
        except Exception as exc:
            self._fail(exc)

    def _fail(self, exc: Exception) -> None:
        self._lost += 1
        if self._w is not None:
            self._drop_file()
        self._retry_at = self._now() + RETRY_S
        if not self.warned:
            self.warned = True
            err = getattr(exc, "strerror", None) or str(exc) or type(exc).__name__
            print(f"device.pi run: warning: --mcap {self.path}: cannot write ({err}); "
                  f"running on, counting the lost messages in the status "
                  f"(mcap_messages_lost)", file=sys.stderr)

    def _now(self) -> float:
        return 0.0 if self.clock is None else float(self.clock())

    def _t_ns(self, clock_s: float) -> int:
        if self._offset_s is None:           # before the first frame: at 0
            return 0
        return max(0, int(round((clock_s + self._offset_s) * 1e9)))

    # -- what the runtime logs -----------------------------------------------------
    def frame(self, dec: dict, decision, frame, ef, imu, faults: int, t_avail: float,
              t_done: float, reference=None) -> None:
        """One frame: its decision line (``dec``, as --json-log writes it) and the
        :class:`~device.pi.runtime.decisions.Decision`, the camera frame and its
        encoding ``ef``, the IMU vector (acc g, gyro dps), the fault bits, when the
        frame came and when its packet went (runtime clock, s) and the reference pins.
        On the loop's thread this copies what the messages need (the image only on
        an image frame) and, in the background, queues it."""
        c0 = time.thread_time()
        t_s = float(frame.t_s)
        self._offset_s = t_s - t_avail
        n = self._frames
        self._frames += 1
        if not self._file_on and not self.live.any():     # no file, no viewer: nothing
            return
        try:
            tex = getattr(decision, "texture", None)
            t = max(0, int(round(t_s * 1e9)))
            ff = ef.features
            img = None
            if n % self.cfg.image_every == 0:
                # a camera hands a new array each frame (device.pi.sources.camera): the
                # image is kept, not copied; the features' arrays are copied
                img = (frame.image, _copy(ff.pins), _copy(ff.vectors), _copy(ff.lost),
                       _copy(reference))
            args = (dec, None if not tex else round(float(tex[1]), 4), t, img,
                    _copy(ff.grid), bool(ff.contact), _copy(imu), int(faults),
                    (t_done - t_avail) * 1e3)
        except Exception as exc:            # never into the loop
            return self._fail(exc)
        self._do(self._frame, args, 6 if img is not None else 4)
        self.loop_cpu_s += time.thread_time() - c0

    def _frame(self, dec, tex_conf, t, img, grid, contact, imu, faults, pipeline_ms) -> None:
        k = int(dec["frame"])
        if img is not None and (self._on("/tacfoot/image") or self._on("/tacfoot/pins")):
            self._image(t, *img)
        if self._on("/tacfoot/grid"):
            self._write("/tacfoot/grid", t, M.grid_bytes(k, grid, contact))
        if self._on("/tacfoot/decision"):
            self._write("/tacfoot/decision", t, M.decision_bytes(dec, tex_conf))
        if self._on("/tacfoot/imu"):
            self._write("/tacfoot/imu", t, M.imu_bytes(k, imu, faults))
        if self._on("/tacfoot/latency"):
            self._write("/tacfoot/latency", t,
                        M.latency_bytes(k, dec.get("latency_ms"), pipeline_ms))

    def _image(self, t: int, image, pins, vectors, lost, reference) -> None:
        jpg, s = M.jpeg(image, self.cfg.image_width, self.cfg.jpeg_quality)
        self._write("/tacfoot/image", t, M.image_bytes(t, jpg))
        self._write("/tacfoot/pins", t, M.annotations_bytes(t, pins, vectors, lost, reference,
                                                            s, self.cfg.vector_scale))

    def packet(self, direction: str, msg, clock_s: float, seq=None, t_ms=None) -> None:
        """A packet sent (``direction`` "out") or received ("in"), decoded; a FAULT
        sent is also logged on ``/tacfoot/faults``."""
        if not self._file_on and not self.live.any():
            return
        c0 = time.thread_time()
        fault = direction == "out" and isinstance(msg, P.Fault)
        self._do(self._packet, (f"/tacfoot/packets/{direction}", msg, self._t_ns(clock_s),
                                seq, t_ms, fault), 2 if fault else 1)
        self.loop_cpu_s += time.thread_time() - c0

    def _packet(self, topic, msg, t, seq, t_ms, fault) -> None:
        if self._on(topic):
            self._write(topic, t, M.packet_bytes(msg, seq, t_ms))
        if fault and self._on("/tacfoot/faults"):
            self._write("/tacfoot/faults", t, M.faults_bytes(msg))

    def close(self) -> None:
        """Write what is queued (waiting at most :data:`CLOSE_WAIT_S`), end the
        file with its summary and stop the live view."""
        if self._thread is not None:
            self._closing = True
            self._wake.set()
            self._thread.join(CLOSE_WAIT_S)
            if self._thread.is_alive():          # the disk hangs: leave it, count it
                self._dropped_msgs += sum(x[-1] for x in list(self._q))
                self._thread = None
                if self.live is not None:
                    self.live.close()
                return
            self._thread = None
        if self.live is not None:
            self.live.close()
        if self._w is None:
            return
        try:
            self._finish()
        except Exception as exc:
            self._fail(exc)

    def status(self) -> dict:
        st = {"mcap_messages_written": self.messages_written,
              "mcap_messages_lost": self.messages_lost, "mcap_dropped": self.dropped,
              "mcap_files": list(self.files), "mcap_loop_cpu_s": round(self.loop_cpu_s, 4),
              "mcap_writer_cpu_s": round(self.writer_cpu_s, 4)}
        if self.live is not None:
            st.update(self.live.status())
        return st


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
            raise ValueError(f"--foxglove-max-clients must be 1..1000, got {max_clients!r}")
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
        for topic, schema in (channels or CHANNELS).items():
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
                 "left", "dropping", "drop_msg", "masks")

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
        conn.to_up += conn.req
        conn.req = bytearray()

    def _from_server(self, conn: _Conn, data: bytes) -> None:
        if conn.ws is None:                        # the HTTP answer to the upgrade
            conn.head += data
            end = conn.head.find(b"\r\n\r\n")
            if end < 0:
                return
            conn.to_client += conn.head[:end + 4]
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


def parse_hostport(text: str, default_host: str = "127.0.0.1") -> tuple[str, int]:
    """``[HOST:]PORT`` -> (host, port); ValueError naming the text."""
    host, _, port = str(text).rpartition(":")
    try:
        p = int(port)
    except ValueError:
        p = -1
    if not 0 <= p <= 65535:
        raise ValueError(f"--foxglove {text!r}: give [HOST:]PORT, a port 0..65535 "
                         f"(e.g. 8765 or 0.0.0.0:8765)")
    return (host or default_host), p


# ---------------------------------------------------------------------------
# Reading back (tests, recovery after a crash)
# ---------------------------------------------------------------------------

def read_log(path) -> tuple[list[dict], bool]:
    """The messages of one MCAP file in file order, as dicts (``topic``, ``schema``,
    ``log_time``, ``data``: the decoded JSON), and whether the file was complete.
    A file cut short (a crash) gives the messages of its complete chunks."""
    try:
        from mcap.exceptions import McapError
        from mcap.records import Channel, Chunk, Message, Schema
        from mcap.stream_reader import StreamReader, breakup_chunk
    except ImportError:
        raise McapLogError(INSTALL_HINT) from None
    schemas, channels, out = {}, {}, []
    complete = False

    def take(rec):
        if isinstance(rec, Schema):
            schemas[rec.id] = rec.name
        elif isinstance(rec, Channel):
            channels[rec.id] = (rec.topic, rec.schema_id)
        elif isinstance(rec, Message):
            topic, sid = channels[rec.channel_id]
            out.append({"topic": topic, "schema": schemas.get(sid), "log_time": rec.log_time,
                        "data": json.loads(rec.data)})

    with open(path, "rb") as fh:
        try:
            for rec in StreamReader(fh, skip_magic=False, emit_chunks=True).records:
                if isinstance(rec, Chunk):
                    for r in breakup_chunk(rec, validate_crc=True):
                        take(r)
                else:
                    take(rec)
            complete = True
        except (McapError, EOFError, ValueError, KeyError, OSError):
            pass                          # cut short: what came before stands
    return out, complete


def recover(src, dst) -> int:
    """Rewrite the readable prefix of ``src`` (a log cut short by a crash) as a
    well-formed MCAP file ``dst``; the number of messages kept."""
    W = _mcap()
    msgs, _ = read_log(src)
    topics = {**CHANNELS, **{m["topic"]: {"title": m["schema"]} for m in msgs
                             if m["topic"] not in CHANNELS}}
    with open(dst, "wb") as fh:
        w = W.Writer(fh, compression=W.CompressionType.ZSTD)
        w.start(profile="", library="tacfoot")
        sids, cids = {}, {}
        for topic, schema in topics.items():
            name = schema["title"]
            if name not in sids:
                sids[name] = w.register_schema(name, "jsonschema", json.dumps(schema).encode())
            cids[topic] = w.register_channel(topic, "json", sids[name])
        for m in msgs:
            w.add_message(cids[m["topic"]], log_time=m["log_time"],
                          publish_time=m["log_time"], data=json.dumps(m["data"]).encode())
        w.finish()
    return len(msgs)
