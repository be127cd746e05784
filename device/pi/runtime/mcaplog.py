"""The leg's MCAP log: ``python -m device.pi run --mcap FILE`` (docs/viewing.md).

What the leg senses, in the format Foxglove and ROS 2 read, one channel per kind
(all JSON-encoded; Foxglove's well-known schemas where one fits, so the Image panel
draws the pins and vectors over the frame, the 3D panel the grid, the Log panel the
lines):

===========================  =========================  ==============================
topic                        schema                     when
===========================  =========================  ==============================
``/tacfoot/image``           ``foxglove.CompressedImage``  every ``image_every``-th frame
``/tacfoot/pins``            ``foxglove.ImageAnnotations`` with each image
``/tacfoot/grid``            ``foxglove.Grid``          every frame (float32 ``contact``)
``/tacfoot/decision``        ``tacfoot.Decision``       every frame (the --json-log line)
``/tacfoot/imu``             ``tacfoot.Imu``            every frame
``/tacfoot/latency``         ``tacfoot.Latency``        every frame
``/tacfoot/packets/out``     ``tacfoot.Packet``         every packet sent
``/tacfoot/packets/in``      ``tacfoot.Packet``         every packet received
``/tacfoot/faults``          ``tacfoot.Faults``         every FAULT packet sent
``/tacfoot/log``             ``foxglove.Log``           each FAULT sent, and the runtime's
                                                        log records (``records``)
===========================  =========================  ==============================

Times are Unix-epoch ns (so a log lines up with the robot's other logs): the
runtime's clock is anchored to ``time.time_ns()`` once, when the log is made. A
frame's messages are logged at the frame's own time (``t_s`` of the JSON log), its
time line anchored at the first frame to the clock's epoch time of its arrival.
Packets and faults, which happen between frames, are logged on the same time line:
the runtime's clock, shifted by the last frame's offset between the two (those
before the first frame at the clock's epoch time). Within a topic a log time never
steps back: one that would (the offset moved between two packets) is logged 1 ns
after its topic's last, counted in ``mcap_time_clamped``. Each file starts with a
``tacfoot`` Metadata record (:func:`run_metadata`: version, profile, model hashes,
config).

Files roll over by size (``run.mcap``, ``run-0001.mcap`` ... once a file reaches
``max_mb``), each a complete MCAP file; the runtime's log never truncates one
(``keep_existing``, one line names the file it takes instead): names and reading
back are :mod:`device.pi.runtime.mcapfiles`. A chunk is at most a quarter of
``max_mb``: a file ends at most that far past it, plus the message that filled the
chunk and the summary (about 5 kB). A file is written unbuffered, one chunk per
write (``[mcap] chunk_kb``), so a crash loses at most the chunk being filled and
what the writer thread had not yet taken (below; normally nothing). A file whose
first chunk cannot be written (a full disk) is removed and its name tried again.

The loop does not wait on the log (``background=True``): per frame it copies the
values the messages need and queues them; a writer thread encodes them (templates,
:mod:`device.pi.runtime.mcapmsg`; the JPEG only on an image frame), compresses the
chunks and writes them. The runtime's default moves that writer to a child process
(:mod:`device.pi.runtime.mcapproc`), off the loop's GIL. When the writer falls
:data:`QUEUE_ITEMS` frames and packets behind, the oldest is dropped and counted
(``mcap_dropped``, its messages in ``mcap_messages_lost``): the newest wins.

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

import logging
import json
import os
import threading
import time
from collections import deque
from pathlib import Path

import numpy as np

from device.pi import protocol as P
from device.pi.runtime import mcapmsg as M
from device.pi.runtime.mcapfiles import (  # noqa: F401  (the names this module had)
    INSTALL_HINT, MAGIC, MAX_MB_MAX, MAX_MB_MIN, McapLogError, free_name, read_log, recover,
    roll_name, run_metadata)
from device.pi.runtime.mcapfiles import CountingFile as _CountingFile
from device.pi.runtime.mcapfiles import writer_module as _mcap
from device.pi.runtime.mcapmsg import (  # noqa: F401  (the names this module had)
    CHANNELS, FRAME_ID, LINE_LIST, POINTS, annotations)

_log = logging.getLogger(__name__)

#: after a failed write, the next file is tried this much later (runtime clock, s)
RETRY_S = 1.0
#: frames and packets the writer thread holds before the oldest is dropped
QUEUE_ITEMS = 128
#: the writer thread looks for queued frames this often (s): it takes them in batches,
#: its code warm in the cache, instead of waking once per frame
WRITER_POLL_S = 0.02
#: close() waits this long for the writer thread to write what is queued, s
CLOSE_WAIT_S = 10.0
#: ... and leaves one that handled nothing this long (a stalled disk), counted lost, s
CLOSE_STALL_S = 0.5


def _copy(a):
    return None if a is None else np.array(a, copy=True)


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
    offline commands, which must not drop): the caller's thread does the work.

    ``keep_existing=True`` (the runtime's): an existing log is never truncated; the
    run takes the next free name (:func:`free_name`) and says so in one line.
    ``prog`` names the command in its warnings."""

    def __init__(self, path, cfg, *, max_mb: float = 256.0, clock=None, channels=None,
                 live=None, background: bool = False, keep_existing: bool = False,
                 prog: str = "device.pi run", metadata: dict | None = None,
                 records: str | None = None):
        self._setup(cfg, clock, prog, keep_existing, metadata, channels)
        self.live = live             # a LiveView (--foxglove), or None
        self.host, self.port = (None, None) if live is None else (live.host, live.port)
        self.path = None if path is None else Path(path)
        self._file_on = path is not None
        if path is None and live is None:
            raise McapLogError("McapLog needs a file (--mcap), a live view (--foxglove) "
                               "or both; got neither")
        if path is not None:
            self._open_first(path, max_mb)
        self._start(records, background)

    def _setup(self, cfg, clock, prog, keep_existing, metadata, channels) -> None:
        """The counters and the time line's anchor (the front, which the loop drives)."""
        #: topic -> JSON schema: :data:`CHANNELS` and any more (``host export mcap``)
        self.channels = {**M.channels(), **(channels or {})}
        #: the "tacfoot" Metadata record of every file (name -> string, :func:`run_metadata`)
        self.metadata = {k: str(v) for k, v in (metadata or {}).items()}
        #: Unix-epoch ns at runtime clock 0: the one offset that makes log times epoch ns
        self._epoch_ns = time.time_ns() - (0 if clock is None else int(round(clock() * 1e9)))
        self._frame_ns = None        # epoch ns minus the frame time line's ns (first frame)
        self._last_t: dict[str, int] = {}    # topic -> its last log time (writer thread)
        #: messages whose log time stepped back within their topic, logged 1 ns later
        self.time_clamped = 0
        self.cfg = cfg
        self.clock = clock
        self.files: list[str] = []
        self.prog = prog
        self.keep_existing = keep_existing
        #: close() waits no later than this (time.monotonic()); set at a stop signal
        self.close_by: float | None = None
        self._done = 0               # items the writer thread has handled
        self._busy = None            # (messages, written + lost) of the item in hand
        self._abandoned = False
        self._head = self._file_msgs = self._file_kept = self.messages_written = 0
        self._lost = 0               # the writer's failures (its thread)
        self._dropped_msgs = 0       # messages of the items dropped from the queue
        self.dropped = 0             # queue items (frames, packets) dropped
        self.warned, self._w, self._retry_at = False, None, None
        self._offset_s = None        # frame time - runtime clock, at the last frame
        self._frames = 0
        self._q: deque | None = None
        self._thread = None
        self.loop_cpu_s = 0.0        # CPU the loop's thread spent in frame() and packet()
        self.writer_cpu_s = 0.0      # CPU of the writer thread (background=True)

    def _start(self, records, background: bool) -> None:
        """The runtime's log records on /tacfoot/log, and the writer thread."""
        self._records = None
        if records is not None:
            self._records = (logging.getLogger(records), _Records(self))
            self._records[0].addHandler(self._records[1])
        if background:
            self._q = deque()
            self._wake = threading.Event()
            self._closing = False
            self._thread = threading.Thread(target=self._drain, name="mcap-writer",
                                            daemon=True)
            self._thread.start()

    def _anyone(self) -> bool:      # the file, or a live viewer
        return self._file_on or self.live.any()

    def _open_first(self, path, max_mb) -> None:
        self._writer_mod = _mcap()
        folder = self.path.resolve().parent
        if self.path.is_dir():
            raise McapLogError(f"--mcap {str(path)!r} is a folder; give a file, e.g. "
                               f"{self.path / 'run.mcap'}")
        if not folder.is_dir():
            raise McapLogError(f"--mcap {str(path)!r}: the folder {folder} does not exist")
        if not (max_mb > 0 and np.isfinite(max_mb)):
            raise McapLogError(f"--mcap-max-mb must be a finite number > 0, got {max_mb}")
        self.max_bytes = int(max_mb * 1024 * 1024)
        self._n = 0                  # the next file's number
        self._fh = None
        self._ids: dict[str, int] = {}
        self._base = free_name(self.path) if self.keep_existing else self.path
        try:
            self._open()
        except OSError as exc:
            raise McapLogError(f"--mcap {str(path)!r}: {exc.strerror or exc}") from None
        if self._base != self.path:
            _log.info("%s: --mcap %s already holds an earlier log, kept; this run writes %s",
                      self.prog, self.path, self.files[0])

    @property
    def messages_lost(self) -> int:
        """Messages not written: failed writes and the messages of dropped items."""
        return self._lost + self._dropped_msgs

    # -- files -----------------------------------------------------------------
    def _open(self) -> None:
        """The next file, created (never an existing one with ``keep_existing``) with
        its header, schemas and channels; a file whose start cannot be written is
        removed and its number used again at the next try."""
        W = self._writer_mod
        while True:
            p = roll_name(self._base, self._n)
            try:
                fh = _CountingFile(p, exclusive=self.keep_existing)
                break
            except FileExistsError:          # appeared since: never truncated, skipped
                self._n += 1
        try:
            chunk = max(1024, min(self.cfg.chunk_kb * 1024, self.max_bytes // 4))
            w = W.Writer(fh, chunk_size=chunk, compression=W.CompressionType.ZSTD)
            w.start(profile="", library="tacfoot")
            if self.metadata:
                w.add_metadata("tacfoot", self.metadata)
            schemas: dict[str, int] = {}
            ids = {}
            for topic, schema in self.channels.items():
                name = schema["title"]
                if name not in schemas:
                    schemas[name] = w.register_schema(name, "jsonschema",
                                                      json.dumps(schema).encode())
                ids[topic] = w.register_channel(topic, "json", schemas[name])
        except BaseException:
            self._remove(fh, p)
            raise
        self._n += 1
        self._fh, self._ids, self._w = fh, ids, w
        self.files.append(str(p))
        self._head = fh.writes               # writes of a file that holds no message yet
        self._file_msgs = self._file_kept = 0

    @staticmethod
    def _remove(fh: _CountingFile, p) -> None:
        for step in (fh.close, lambda: os.unlink(p)):
            try:
                step()
            except Exception:
                pass

    def _unflushed_lost(self) -> None:
        """The messages of the file's chunk that never reached it: lost, not written."""
        if self._abandoned:                  # counted by _abandon
            return
        n = self._file_msgs - self._file_kept
        self._file_msgs = self._file_kept
        self.messages_written -= n
        self._lost += n

    def _drop_file(self) -> None:
        """After a failed write: the file is closed; one that holds no message (the
        first chunk failed) is removed and its name is used again."""
        self._w = None
        self._unflushed_lost()
        if self._fh.writes <= self._head and self.files:
            self._remove(self._fh, self.files.pop())
            self._n -= 1
            return
        try:
            self._fh.close()
        except Exception:
            pass

    def _finish(self) -> None:
        w, self._w = self._w, None
        try:
            w.finish()
            self._file_kept = self._file_msgs
        finally:
            self._unflushed_lost()
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
        while not self._abandoned:
            self.writer_cpu_s = time.thread_time() - c0
            closing = self._closing      # read first: what close() queued is then taken
            try:
                fn, *args, n = q.popleft()
            except IndexError:
                if closing:
                    return
                wake.wait(WRITER_POLL_S)     # woken early only by close()
                continue
            self._busy = (n, self.messages_written + self._lost)
            try:
                fn(*args)
            except Exception as exc:
                self._fail(exc)
            self._busy = None
            self._done += 1
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
        if self._abandoned:                  # left by close(): counted there
            return
        last = self._last_t.get(topic)
        if last is not None and t_ns < last:     # never back within a topic: counted
            t_ns = last + 1
            self.time_clamped += 1
        self._last_t[topic] = t_ns
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
            writes = self._fh.writes
            self._w.add_message(self._ids[topic], log_time=t_ns, publish_time=t_ns, data=data)
            if self._abandoned:
                return
            self.messages_written += 1
            self._file_msgs += 1
            if self._fh.writes != writes:    # a chunk went out, this message last in it
                self._file_kept = self._file_msgs
            if self._fh.size >= self.max_bytes:
                self._finish()
                self._open()
        except Exception as exc:
            self._fail(exc)

    def _fail(self, exc: Exception) -> None:
        if self._abandoned:
            return
        self._lost += 1
        if self._w is not None:
            self._drop_file()
        self._retry_at = self._now() + RETRY_S
        if not self.warned:
            self.warned = True
            err = getattr(exc, "strerror", None) or str(exc) or type(exc).__name__
            where = (" in the status (mcap_messages_lost)" if self.prog == "device.pi run"
                     else "")
            _log.warning("%s: warning: --mcap %s: cannot write (%s); running on, counting "
                         "the lost messages%s", self.prog, self.path, err, where)

    def _now(self) -> float:
        return 0.0 if self.clock is None else float(self.clock())

    def _t_ns(self, clock_s: float) -> int:
        """Epoch ns of a runtime clock reading: on the frames' time line after the
        first frame (shifted by the last frame's offset), the clock's before it."""
        if self._offset_s is None:
            return self._epoch_ns + int(round(clock_s * 1e9))
        return self._frame_ns + int(round((clock_s + self._offset_s) * 1e9))

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
        if self._frame_ns is None:           # the frame time line, anchored once
            self._frame_ns = self._epoch_ns + int(round((t_avail - t_s) * 1e9))
        n = self._frames
        self._frames += 1
        if not self._anyone():     # no file, no viewer: nothing
            return
        try:
            tex = getattr(decision, "texture", None)
            t = self._frame_ns + int(round(t_s * 1e9))
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
            self._write("/tacfoot/grid", t, M.grid_bytes(t, grid))
        if self._on("/tacfoot/decision"):
            self._write("/tacfoot/decision", t, M.decision_bytes(dec, tex_conf))
        if self._on("/tacfoot/imu"):
            self._write("/tacfoot/imu", t, M.imu_bytes(k, imu, faults))
        if self._on("/tacfoot/latency"):
            self._write("/tacfoot/latency", t,
                        M.latency_bytes(k, dec.get("latency_ms"), pipeline_ms))

    def _image(self, t: int, image, pins, vectors, lost, reference) -> None:
        jpg, s = (image if isinstance(image, tuple)      # (JPEG, scale) made by the sender
                  else M.jpeg(image, self.cfg.image_width, self.cfg.jpeg_quality))
        self._write("/tacfoot/image", t, M.image_bytes(t, jpg))
        self._write("/tacfoot/pins", t, M.annotations_bytes(t, pins, vectors, lost, reference,
                                                            s, self.cfg.vector_scale))

    def packet(self, direction: str, msg, clock_s: float, seq=None, t_ms=None) -> None:
        """A packet sent (``direction`` "out") or received ("in"), decoded; a FAULT
        sent is also logged on ``/tacfoot/faults``."""
        if not self._anyone():
            return
        c0 = time.thread_time()
        fault = direction == "out" and isinstance(msg, P.Fault)
        self._do(self._packet, (f"/tacfoot/packets/{direction}", msg, self._t_ns(clock_s),
                                seq, t_ms, fault), 3 if fault else 1)
        self.loop_cpu_s += time.thread_time() - c0

    def _packet(self, topic, msg, t, seq, t_ms, fault) -> None:
        if self._on(topic):
            self._write(topic, t, M.packet_bytes(msg, seq, t_ms))
        if fault and self._on("/tacfoot/faults"):
            self._write("/tacfoot/faults", t, M.faults_bytes(msg))
        if fault and self._on("/tacfoot/log"):
            level, text = M.fault_line(msg)
            self._write("/tacfoot/log", t, M.log_bytes(t, level, text, "tacfoot.faults"))

    def _record(self, t, level, text, name, file, line) -> None:
        if self._on("/tacfoot/log"):
            self._write("/tacfoot/log", t, M.log_bytes(t, level, text, name, file, line))

    def close(self) -> None:
        """Write what is queued, end the file with its summary and stop the live
        view. The writer thread gets at most :data:`CLOSE_WAIT_S` (or until
        ``close_by``), and is left when it handles nothing for :data:`CLOSE_STALL_S`
        (a stalled disk): what it had not written is counted lost."""
        if self._records is not None:
            self._records[0].removeHandler(self._records[1])
            self._records = None
        if self._thread is not None:
            self._q.append((lambda: self._w is not None and self._finish(), 0))  # + summary
            self._closing = True
            self._wake.set()
            if not self._wait_writer():          # the disk hangs: leave it, count it
                self._abandon()
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

    def _wait_writer(self) -> bool:
        """Whether the writer thread ended within the bounds of :meth:`close`."""
        now = time.monotonic()
        end = now + CLOSE_WAIT_S
        if self.close_by is not None:
            end = min(end, max(self.close_by, now + 0.05))
        seen, since = self._done, now
        while self._thread.is_alive():
            now = time.monotonic()
            if self._done != seen:
                seen, since = self._done, now
            if now >= end or now - since >= CLOSE_STALL_S:
                return False
            self._thread.join(0.01)
        return True

    def _abandon(self) -> None:
        """The writer is stuck (on its disk): what is queued, the rest of its item and
        its unwritten chunk are lost. Left, it writes nothing more if it ever wakes."""
        self._abandoned = True
        queued = list(self._q)
        self._q.clear()
        self._dropped_msgs += sum(x[-1] for x in queued)
        busy = self._busy
        if busy is not None:
            n, before = busy
            self._lost += max(0, n - (self.messages_written + self._lost - before))
        self._w = None
        n = self._file_msgs - self._file_kept    # the chunk that never reached the disk
        self._file_msgs = self._file_kept
        self.messages_written -= n
        self._lost += n

    def status(self) -> dict:
        st = {"mcap_messages_written": self.messages_written,
              "mcap_messages_lost": self.messages_lost, "mcap_dropped": self.dropped,
              "mcap_files": list(self.files),
              "mcap_file": self.files[-1] if self.files else None,
              "mcap_loop_cpu_s": round(self.loop_cpu_s, 4),
              "mcap_time_clamped": self.time_clamped,
              "mcap_writer_cpu_s": round(self.writer_cpu_s, 4)}
        if self.live is not None:
            st.update(self.live.status())
        return st


class _Records(logging.Handler):
    """The runtime's log records (INFO and up) as foxglove.Log lines on
    ``/tacfoot/log``, at the runtime clock's log time; a record emitted while one is
    being written (the log's own warning) is not logged again."""

    def __init__(self, mlog: McapLog):
        super().__init__(logging.INFO)
        self.mlog = mlog
        self._inside = threading.local()

    def emit(self, record: logging.LogRecord) -> None:
        if getattr(self._inside, "on", False):
            return
        self._inside.on = True
        try:
            m = self.mlog
            t = m._t_ns(m._now())
            m._do(m._record, (t, M.log_level(record.levelno), record.getMessage(),
                              record.name, record.pathname or "", record.lineno or 0), 1)
        except Exception:
            pass
        finally:
            self._inside.on = False
