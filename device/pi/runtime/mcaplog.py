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
size ``[mcap] chunk_kb``), so a crash loses at most the chunk being filled:
:func:`read_log` reads the complete chunks of a file that has no footer, and
:func:`recover` rewrites them as a well-formed file.

The log is not the job: :class:`McapLog` never raises into the loop. A failed
write (a full disk, a vanished mount, a bad frame) is counted in ``messages_lost``
(the status file's ``mcap_messages_lost``) and warned about once; the broken file
is dropped and the next one is tried after :data:`RETRY_S`.

``--foxglove [HOST:]PORT`` serves the same channels live (:class:`LiveView`, over
``foxglove-sdk``'s WebSocket server): the runtime's one hook, ``LegRuntime.mcap``,
is an :class:`McapLog` with a file, a live view, or both.

The ``mcap`` and ``foxglove-sdk`` packages are the ``viz`` extra (``pip install
.[viz]``): this module imports them only when a log or a view is opened, so the
base install runs without them.
"""
from __future__ import annotations

import base64
import json
import sys
from pathlib import Path

import cv2
import numpy as np

from device.pi import protocol as P
from device.pi.faults import fault_names

#: after a failed write, the next file is tried this much later (runtime clock, s)
RETRY_S = 1.0
#: messages the live server queues per viewer before it drops the oldest
LIVE_BACKLOG = 256
#: the frame id the images and annotations share
FRAME_ID = "tactip"
INSTALL_HINT = "MCAP logging needs the viz extra: pip install .[viz]"

_TIME = {"type": "object", "title": "time",
         "properties": {"sec": {"type": "integer", "minimum": 0},
                        "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999}}}
_COLOR = {"type": "object", "title": "foxglove.Color",
          "properties": {k: {"type": "number"} for k in ("r", "g", "b", "a")}}
_POINT2 = {"type": "object", "title": "foxglove.Point2",
           "properties": {"x": {"type": "number"}, "y": {"type": "number"}}}

#: Foxglove's JSON schemas (https://github.com/foxglove/foxglove-sdk, schemas/jsonschema)
COMPRESSED_IMAGE = {
    "title": "foxglove.CompressedImage", "description": "A compressed image",
    "type": "object",
    "properties": {"timestamp": _TIME, "frame_id": {"type": "string"},
                   "data": {"type": "string", "contentEncoding": "base64"},
                   "format": {"type": "string"}}}
IMAGE_ANNOTATIONS = {
    "title": "foxglove.ImageAnnotations", "description": "Array of annotations for a 2D image",
    "type": "object",
    "properties": {
        "circles": {"type": "array", "items": {"type": "object"}},
        "points": {"type": "array", "items": {
            "type": "object", "title": "foxglove.PointsAnnotation",
            "properties": {
                "timestamp": _TIME,
                "type": {"title": "foxglove.PointsAnnotationType", "type": "integer",
                         "oneOf": [{"title": n, "const": i} for i, n in enumerate(
                             ("UNKNOWN", "POINTS", "LINE_LOOP", "LINE_STRIP", "LINE_LIST"))]},
                "points": {"type": "array", "items": _POINT2},
                "outline_color": _COLOR, "outline_colors": {"type": "array", "items": _COLOR},
                "fill_color": _COLOR, "thickness": {"type": "number", "minimum": 0}}}},
        "texts": {"type": "array", "items": {"type": "object"}}}}
POINTS, LINE_LIST = 1, 4


def _obj(title: str, **props) -> dict:
    return {"title": title, "type": "object", "properties": props}


_NUM, _INT, _STR, _BOOL = ({"type": "number"}, {"type": "integer"}, {"type": "string"},
                           {"type": "boolean"})
_NUMS = {"type": "array", "items": _NUM}
_STRS = {"type": "array", "items": _STR}

#: topic -> JSON schema (its title is the schema name)
CHANNELS = {
    "/tacfoot/image": COMPRESSED_IMAGE,
    "/tacfoot/pins": IMAGE_ANNOTATIONS,
    "/tacfoot/grid": _obj("tacfoot.ContactGrid", frame=_INT, n=_INT, cells=_NUMS,
                          contact=_BOOL),
    "/tacfoot/decision": _obj("tacfoot.Decision", frame=_INT, t_s=_NUM, **{"class": _STR},
                              probs=_NUMS, surface_conf=_NUM, contact=_BOOL, slip=_BOOL,
                              slip_conf=_NUM, texture=_STR, texture_conf=_NUM,
                              pressure=_NUM, shear_dir_deg=_NUM, shear_mag_px=_NUM,
                              pins=_INT, faults=_STRS, latency_ms=_NUM),
    "/tacfoot/imu": _obj("tacfoot.Imu", frame=_INT, acc_g=_NUMS, gyro_dps=_NUMS,
                         faults=_INT),
    "/tacfoot/latency": _obj("tacfoot.Latency", frame=_INT, latency_ms=_NUM,
                             pipeline_ms=_NUM),
    "/tacfoot/packets/out": _obj("tacfoot.Packet", type=_STR, seq=_INT, t_ms=_INT),
    "/tacfoot/packets/in": _obj("tacfoot.Packet", type=_STR, seq=_INT, t_ms=_INT),
    "/tacfoot/faults": _obj("tacfoot.Faults", faults=_INT, names=_STRS, raised=_STRS,
                            pins_lost=_INT),
}


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


def _stamp(ns: int) -> dict:
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def _r(x, nd=4):
    return None if x is None else round(float(x), nd)


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
    :meth:`packet` for every packet and :meth:`close` at the end."""

    def __init__(self, path, cfg, *, max_mb: float = 256.0, clock=None, channels=None,
                 live=None):
        #: topic -> JSON schema: :data:`CHANNELS` and any more (``host export mcap``)
        self.channels = {**CHANNELS, **(channels or {})}
        self.live = live             # a LiveView (--foxglove), or None
        self.cfg = cfg
        self.clock = clock
        self.files: list[str] = []
        self.messages_written = 0
        self.messages_lost = 0
        self.warned = False
        self._w = None
        self._retry_at = None
        self._offset_s = None        # frame time - runtime clock, at the last frame
        self._frames = 0
        self.path = None if path is None else Path(path)
        self._file_on = path is not None
        if path is None:             # the live view alone
            return
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

    # -- writing ---------------------------------------------------------------
    def write(self, topic: str, t_ns: int, doc: dict) -> None:
        """One message on ``topic`` at ``t_ns``; a failure is counted, never raised."""
        self._write(topic, int(t_ns), doc)

    def image(self, t_ns: int, image, ff, reference=None) -> None:
        """The frame on ``/tacfoot/image`` and its pins on ``/tacfoot/pins``."""
        try:
            self._image(int(t_ns), image, ff, reference)
        except Exception as exc:
            self._fail(exc)

    def _on(self, topic: str) -> bool:
        """Whether a message on ``topic`` goes anywhere (the file, or a live viewer
        subscribed to it): nothing is built for a topic no one takes."""
        return self._file_on or (self.live is not None and self.live.wants(topic))

    def _write(self, topic: str, t_ns: int, doc: dict) -> None:
        data = None
        if self.live is not None and self.live.wants(topic):
            data = json.dumps(doc, separators=(",", ":")).encode()
            self.live.publish(topic, t_ns, data)
        if not self._file_on:
            return
        if self._w is None:
            now = self._now()
            if self._retry_at is None or now < self._retry_at:
                self.messages_lost += 1
                return
            try:
                self._retry_at = None
                self._open()
            except Exception as exc:
                return self._fail(exc)
        try:
            if data is None:
                data = json.dumps(doc, separators=(",", ":")).encode()
            self._w.add_message(self._ids[topic], log_time=t_ns, publish_time=t_ns, data=data)
            self.messages_written += 1
            if self._fh.size >= self.max_bytes:
                self._finish()
                self._open()
        except Exception as exc:
            self._fail(exc)

    def _fail(self, exc: Exception) -> None:
        self.messages_lost += 1
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
        frame came and when its packet went (runtime clock, s) and the reference pins."""
        if not self._file_on and not self.live.any():     # no file, no viewer: nothing
            self._offset_s = float(frame.t_s) - t_avail
            self._frames += 1
            return
        try:
            tex = getattr(decision, "texture", None)
            self._frame(dict(dec, texture_conf=None if not tex else _r(tex[1])), frame, ef,
                        imu, faults, t_avail, t_done, reference)
        except Exception as exc:            # never into the loop
            self._fail(exc)

    def _frame(self, dec, frame, ef, imu, faults, t_avail, t_done, reference) -> None:
        t_s = float(frame.t_s)
        self._offset_s = t_s - t_avail
        t = max(0, int(round(t_s * 1e9)))
        k = int(dec["frame"])
        ff = ef.features
        if self._frames % self.cfg.image_every == 0 and (
                self._on("/tacfoot/image") or self._on("/tacfoot/pins")):
            self._image(t, frame.image, ff, reference)
        self._frames += 1
        g = np.asarray(ff.grid, np.float64)
        self._write("/tacfoot/grid", t, {"frame": k, "n": int(g.shape[0]),
                                         "cells": np.round(g.ravel(), 3).tolist(),
                                         "contact": bool(ff.contact)})
        probs = dec.get("probs") or [0.0]
        self._write("/tacfoot/decision", t, dict(dec, surface_conf=round(max(probs), 4)))
        imu = np.asarray(imu, np.float64)
        self._write("/tacfoot/imu", t, {"frame": k, "acc_g": [_r(x, 5) for x in imu[:3]],
                                        "gyro_dps": [_r(x, 4) for x in imu[3:6]],
                                        "faults": int(faults)})
        self._write("/tacfoot/latency", t, {"frame": k, "latency_ms": dec.get("latency_ms"),
                                            "pipeline_ms": _r((t_done - t_avail) * 1e3)})

    def _image(self, t: int, image, ff, reference) -> None:
        img = np.asarray(image)
        h, w = img.shape[:2]
        s = self.cfg.image_width / float(w)
        small = cv2.resize(img, (self.cfg.image_width, max(1, int(round(h * s)))),
                           interpolation=cv2.INTER_AREA)
        ok, buf = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY,
                                                self.cfg.jpeg_quality])
        if not ok:
            raise ValueError("cv2.imencode refused the frame")
        stamp = _stamp(t)
        self._write("/tacfoot/image", t, {"timestamp": stamp, "frame_id": FRAME_ID,
                                          "format": "jpeg",
                                          "data": base64.b64encode(buf).decode("ascii")})
        self._write("/tacfoot/pins", t, annotations(stamp, ff, reference, s,
                                                    self.cfg.vector_scale))

    def packet(self, direction: str, msg, clock_s: float, seq=None, t_ms=None) -> None:
        """A packet sent (``direction`` "out") or received ("in"), decoded; a FAULT
        sent is also logged on ``/tacfoot/faults``."""
        topic = f"/tacfoot/packets/{direction}"
        if not (self._on(topic) or self._on("/tacfoot/faults")):
            return
        try:
            t = self._t_ns(clock_s)
            d = P.message_dict(msg)
            d.update(seq=seq, t_ms=t_ms)
            self._write(topic, t, d)
            if direction == "out" and isinstance(msg, P.Fault):
                self._write("/tacfoot/faults", t, {
                    "faults": int(msg.faults), "names": fault_names(msg.faults),
                    "raised": fault_names(msg.raised), "pins_lost": int(msg.pins_lost)})
        except Exception as exc:
            self._fail(exc)

    def close(self) -> None:
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
              "mcap_messages_lost": self.messages_lost, "mcap_files": list(self.files)}
        if self.live is not None:
            st.update(self.live.status())
        return st


class LiveView:
    """``--foxglove [HOST:]PORT``: the same channels served live over Foxglove's
    WebSocket protocol (``foxglove-sdk``, its own context). A channel no viewer is
    subscribed to costs one check per message (:meth:`wants`); with no viewer at
    all, :meth:`McapLog.frame` builds nothing. A message is handed to the server's
    queue and never waited for: for a viewer that falls behind, the server drops
    messages beyond :data:`LIVE_BACKLOG` queued ones rather than slow the loop."""

    def __init__(self, host: str, port: int, channels=None, backlog: int | None = None):
        try:
            import foxglove
        except ImportError:
            raise McapLogError(INSTALL_HINT.replace("MCAP logging", "--foxglove")) from None
        self._ctx = foxglove.Context()
        try:
            self.server = foxglove.start_server(
                name="tacfoot", host=host, port=int(port), context=self._ctx,
                message_backlog_size=backlog or LIVE_BACKLOG)
        except Exception as exc:
            raise McapLogError(f"--foxglove {host}:{port}: cannot serve ({exc})") from None
        self.host, self.port = host, int(self.server.port)
        self._ch = {}
        for topic, schema in (channels or CHANNELS).items():
            sch = foxglove.Schema(name=schema["title"], encoding="jsonschema",
                                  data=json.dumps(schema).encode())
            self._ch[topic] = foxglove.Channel(topic, schema=sch, message_encoding="json",
                                               context=self._ctx)
        self.messages_sent = 0
        self.errors = 0

    def wants(self, topic: str) -> bool:
        ch = self._ch.get(topic)
        return ch is not None and ch.has_sinks()

    def any(self) -> bool:
        return any(ch.has_sinks() for ch in self._ch.values())

    def publish(self, topic: str, t_ns: int, data: bytes) -> None:
        try:
            self._ch[topic].log(data, log_time=int(t_ns))
            self.messages_sent += 1
        except Exception:
            self.errors += 1

    def close(self) -> None:
        try:
            self.server.stop()
        except Exception:
            pass

    def status(self) -> dict:
        return {"foxglove_port": self.port, "foxglove_messages_sent": self.messages_sent,
                "foxglove_errors": self.errors}


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


def annotations(stamp: dict, ff, reference, scale: float, vector_scale: float) -> dict:
    """foxglove.ImageAnnotations: one point per detected pin (green) and, for each
    reference pin still tracked, a segment from its reference place along its
    vector times ``vector_scale`` (red); pixel coordinates times ``scale``."""
    pins = np.round(np.asarray(ff.pins, np.float64).reshape(-1, 2) * scale, 2)
    pts = [{"x": x, "y": y} for x, y in pins.tolist()]
    segs = []
    if reference is not None and len(reference) == len(ff.vectors):
        ref = np.asarray(reference, np.float64).reshape(-1, 2)
        ok = ~np.asarray(ff.lost, bool)
        a = ref[ok] * scale
        b = (ref[ok] + vector_scale * np.asarray(ff.vectors, np.float64)[ok]) * scale
        ends = np.round(np.stack([a, b], 1).reshape(-1, 2), 2)    # a0, b0, a1, b1 ...
        segs = [{"x": x, "y": y} for x, y in ends.tolist()]
    green = {"r": 0.1, "g": 0.9, "b": 0.2, "a": 1.0}
    red = {"r": 1.0, "g": 0.2, "b": 0.1, "a": 1.0}
    none = {"r": 0.0, "g": 0.0, "b": 0.0, "a": 0.0}
    return {"circles": [], "texts": [], "points": [
        {"timestamp": stamp, "type": POINTS, "points": pts, "outline_color": green,
         "outline_colors": [], "fill_color": green, "thickness": 3.0},
        {"timestamp": stamp, "type": LINE_LIST, "points": segs, "outline_color": red,
         "outline_colors": [], "fill_color": none, "thickness": 1.5}]}


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
