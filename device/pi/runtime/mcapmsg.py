"""The messages of the leg's MCAP channels (:mod:`device.pi.runtime.mcaplog`): their
JSON schemas (:data:`CHANNELS`) and the encoders that turn one frame's values into
the bytes of each message.

The per-frame messages are the log's hot path, so the small ones are built from
precomputed ``%``-format templates (one C-level format call per message, no dict
and no ``json.dumps``) and the pins and vectors from a template cached per pin
count. A value that is not finite is written as ``null`` (valid JSON, which
``json.dumps`` would have written as ``NaN``, not JSON at all). Every encoder
returns bytes that ``json.loads`` reads as the documented message.
"""
from __future__ import annotations

import base64
import json
import math

import cv2
import numpy as np

from device.pi import protocol as P
from device.pi.faults import fault_names

#: the frame id the images and annotations share
FRAME_ID = "tactip"

#: the topics that carry Foxglove's well-known messages -> their schema names; the
#: schemas are Foxglove's own, built from the installed ``foxglove-sdk`` (:func:`channels`)
FOXGLOVE = {"/tacfoot/image": "foxglove.CompressedImage",
            "/tacfoot/pins": "foxglove.ImageAnnotations",
            "/tacfoot/grid": "foxglove.Grid",
            "/tacfoot/log": "foxglove.Log"}
POINTS, LINE_LIST = 1, 4


def _obj(title: str, **props) -> dict:
    return {"title": title, "type": "object", "properties": props}


_NUM, _INT, _STR, _BOOL = ({"type": "number"}, {"type": "integer"}, {"type": "string"},
                           {"type": "boolean"})
_NUMS = {"type": "array", "items": _NUM}
#: null where the value is missing or not finite (the encoders write null, never NaN)
_NNUM, _NINT, _NSTR = ({"type": ["number", "null"]}, {"type": ["integer", "null"]},
                       {"type": ["string", "null"]})
_NNUMS = {"type": "array", "items": _NNUM}
_STRS = {"type": "array", "items": _STR}

_GAIT = {"type": ["object", "null"], "title": "tacfoot.GaitContext",
         "properties": {"stance": _BOOL, "load_n": _NUM, "vel_mm_s": _NUM, "age_ms": _NUM}}
_PACKET = _obj("tacfoot.Packet", type=_STR, seq=_NINT, t_ms=_NINT)
_PACKET["description"] = ("a packet decoded, with its header's seq and t_ms; both null "
                          "on /tacfoot/packets/in, whose reader does not keep the header")

#: topic -> JSON schema (its title is the schema name). A field is null where its value
#: is missing: no texture model (texture, texture_conf), no pressure estimate, no packet
#: sent this frame (latency_ms), no fresh gait context (gait, expected_*).
#: The Foxglove topics (:data:`FOXGLOVE`) hold a title only until :func:`channels`.
CHANNELS = {
    "/tacfoot/image": {"title": FOXGLOVE["/tacfoot/image"], "type": "object"},
    "/tacfoot/pins": {"title": FOXGLOVE["/tacfoot/pins"], "type": "object"},
    "/tacfoot/grid": {"title": FOXGLOVE["/tacfoot/grid"], "type": "object"},
    "/tacfoot/decision": _obj("tacfoot.Decision", frame=_INT, index=_INT, t_s=_NUM,
                              **{"class": _STR}, class_id=_INT, probs=_NUMS,
                              surface_conf=_NUM, contact=_BOOL, pipeline_contact=_BOOL,
                              slip=_BOOL, slip_conf=_NUM,
                              texture=_NSTR, texture_conf=_NNUM, pressure=_NNUM,
                              shear_dir_deg=_NUM, shear_mag_px=_NUM, pins=_INT,
                              faults=_STRS, expected_mag_px=_NNUM,
                              expected_motion_px=_NNUM, gait=_GAIT, magnitude_px=_NUM,
                              motion_px=_NNUM, model_probs=_NUMS, rule_probs=_NUMS,
                              latency_ms=_NNUM),
    "/tacfoot/imu": _obj("tacfoot.Imu", frame=_INT, acc_g=_NNUMS, gyro_dps=_NNUMS,
                         faults=_INT),
    "/tacfoot/latency": _obj("tacfoot.Latency", frame=_INT, latency_ms=_NNUM,
                             pipeline_ms=_NUM),
    "/tacfoot/packets/out": _PACKET,
    "/tacfoot/packets/in": _PACKET,
    "/tacfoot/faults": _obj("tacfoot.Faults", faults=_INT, names=_STRS, raised=_STRS,
                            pins_lost=_INT),
    "/tacfoot/log": {"title": FOXGLOVE["/tacfoot/log"], "type": "object"},
}

# protobuf field types (google/protobuf/descriptor.proto) -> JSON schema, as Foxglove's
# own JSON schemas write them: 64-bit and 32-bit integers alike are integers, bytes base64
_PB_DOUBLE, _PB_FLOAT, _PB_BOOL, _PB_STRING, _PB_MESSAGE, _PB_BYTES, _PB_ENUM = (
    1, 2, 8, 9, 11, 12, 14)
_PB_UNSIGNED = {4, 6, 7, 13}                 # uint64, fixed64, fixed32, uint32
_PB_TIME = {".google.protobuf.Timestamp": {
    "type": "object", "title": "time",
    "properties": {"sec": {"type": "integer", "minimum": 0},
                   "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999}}},
    ".google.protobuf.Duration": {
    "type": "object", "title": "duration",
    "properties": {"sec": {"type": "integer"},
                   "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999}}}}


def foxglove_schema(name: str) -> dict:
    """Foxglove's well-known schema ``name`` (``"foxglove.ImageAnnotations"``) as JSON
    schema, built from the protobuf descriptors the installed ``foxglove-sdk`` ships
    (it ships no JSON schemas): every field of Foxglove's own message, none written
    by hand. Needs ``foxglove-sdk`` (the viz extra) and ``protobuf`` (onnxruntime's)."""
    import foxglove.messages as fm
    from google.protobuf import descriptor_pb2
    fds = descriptor_pb2.FileDescriptorSet.FromString(
        getattr(fm, name.split(".", 1)[1]).get_schema().data)
    msgs, enums = {}, {}

    def index(prefix, types, enum_types):
        for e in enum_types:
            enums[f"{prefix}.{e.name}"] = e
        for m in types:
            msgs[f"{prefix}.{m.name}"] = m
            index(f"{prefix}.{m.name}", m.nested_type, m.enum_type)
    for f in fds.file:
        index("." + f.package, f.message_type, f.enum_type)

    def field(fd) -> dict:
        if fd.type == _PB_MESSAGE:
            t = _PB_TIME.get(fd.type_name) or message(fd.type_name)
        elif fd.type == _PB_ENUM:
            e = enums[fd.type_name]
            t = {"title": fd.type_name[1:], "type": "integer",
                 "oneOf": [{"title": v.name, "const": v.number} for v in e.value]}
        elif fd.type in (_PB_DOUBLE, _PB_FLOAT):
            t = {"type": "number"}
        elif fd.type == _PB_BOOL:
            t = {"type": "boolean"}
        elif fd.type == _PB_STRING:
            t = {"type": "string"}
        elif fd.type == _PB_BYTES:
            t = {"type": "string", "contentEncoding": "base64"}
        else:
            t = {"type": "integer", **({"minimum": 0} if fd.type in _PB_UNSIGNED else {})}
        return {"type": "array", "items": t} if fd.label == 3 else t   # 3: repeated

    def message(full: str) -> dict:
        m = msgs[full]
        return {"title": full[1:], "type": "object",
                "properties": {fd.name: field(fd) for fd in m.field}}
    return message("." + name)


_channels_done = False


def channels() -> dict:
    """:data:`CHANNELS`, its Foxglove topics given Foxglove's schemas (once; the
    ``foxglove-sdk`` import is paid only by a run that opens a log or a view)."""
    global _channels_done
    if not _channels_done:
        for topic, name in FOXGLOVE.items():
            CHANNELS[topic] = foxglove_schema(name)
        _channels_done = True
    return CHANNELS


_ENCODE = json.JSONEncoder(separators=(",", ":")).encode     # one encoder, made once


def _json(doc) -> bytes:
    return _ENCODE(doc).encode()


_IMU = '{"frame":%d,"acc_g":[%.5f,%.5f,%.5f],"gyro_dps":[%.4f,%.4f,%.4f],"faults":%d}'
_LAT = '{"frame":%d,"latency_ms":%s,"pipeline_ms":%.4f}'
_GRID = ('{"timestamp":%s,"frame_id":"' + FRAME_ID + '","pose":{"position":{"x":0.0,"y":0.0,'
         '"z":0.0},"orientation":{"x":0.0,"y":0.0,"z":0.0,"w":1.0}},"column_count":%d,'
         '"cell_size":{"x":%s,"y":%s},"row_stride":%d,"cell_stride":4,"fields":[{"name":'
         '"contact","offset":0,"type":7}],"data":"%s"}')     # type 7: FLOAT32
_STAMP = '{"sec":%d,"nsec":%d}'
_IMAGE = '{"timestamp":%s,"frame_id":"' + FRAME_ID + '","format":"jpeg","data":"%s"}'
_PTS = ('{"timestamp":%s,"type":%d,"points":[%s],"outline_color":%s,"outline_colors":[],'
        '"fill_color":%s,"thickness":%s}')
_ANN = '{"circles":[],"texts":[],"points":[%s,%s]}'
GREEN = {"r": 0.1, "g": 0.9, "b": 0.2, "a": 1.0}
RED = {"r": 1.0, "g": 0.2, "b": 0.1, "a": 1.0}
CLEAR = {"r": 0.0, "g": 0.0, "b": 0.0, "a": 0.0}
_C = {id(c): _json(c).decode() for c in (GREEN, RED, CLEAR)}
_templates: dict[tuple[str, int], str] = {}


def _joined(fmt: str, n: int) -> str:
    """``fmt`` n times, comma-separated (cached): one format call for n values."""
    t = _templates.get((fmt, n))
    if t is None:
        if len(_templates) > 256:
            _templates.clear()
        t = _templates[(fmt, n)] = ",".join([fmt] * n)
    return t


def _finite(a: np.ndarray) -> bool:
    return bool(np.isfinite(a).all())


def _num(x, nd: int) -> str:
    """A number rounded to ``nd`` places, or null (None, NaN, inf)."""
    if x is None:
        return "null"
    x = float(x)
    return repr(round(x, nd)) if math.isfinite(x) else "null"


def _nums(a: np.ndarray, nd: int) -> list:
    return [None if not math.isfinite(v) else round(v, nd) for v in a.tolist()]


def imu_bytes(k: int, imu, faults: int) -> bytes:
    """``/tacfoot/imu``: acc in g (5 places), gyro in dps (4 places)."""
    v = np.asarray(imu, np.float64).ravel()[:6]
    if v.shape[0] == 6 and _finite(v):
        return (_IMU % (k, *v.tolist(), faults)).encode()
    v = np.resize(v, 6) if v.size else np.full(6, np.nan)
    return _json({"frame": k, "acc_g": _nums(v[:3], 5), "gyro_dps": _nums(v[3:], 4),
                  "faults": int(faults)})


def latency_bytes(k: int, latency_ms, pipeline_ms: float) -> bytes:
    """``/tacfoot/latency``: the packet latency (null when none went) and the
    frame's time from arrival to its packet, ms."""
    p = float(pipeline_ms)
    if not math.isfinite(p):
        p = 0.0
    return (_LAT % (k, _num(latency_ms, 4), p)).encode()


def grid_doc(t_ns: int, grid) -> dict:
    """``/tacfoot/grid``: the n x n contact grid as foxglove.Grid (what Foxglove's 3D
    panel draws): one float32 field ``contact`` per cell, row-major from the image's
    top-left, little-endian, base64 in JSON (a cell that is not finite stays NaN in
    the bytes; the JSON has no number that is not). The grid spans the pad as a
    1 x 1 square in the ``tactip`` frame (each cell 1/n wide)."""
    g = np.asarray(grid, "<f4")
    n = int(g.shape[-1]) if g.ndim else 0
    return json.loads(_grid_text(t_ns, g, n))


def _grid_text(t_ns: int, g: np.ndarray, n: int) -> str:
    c = repr(1.0 / n) if n else "1.0"
    return _GRID % (stamp(t_ns), n, c, c, 4 * n,
                    base64.b64encode(np.ascontiguousarray(g).tobytes()).decode("ascii"))


def grid_cells(doc: dict) -> np.ndarray:
    """A foxglove.Grid message's (:func:`grid_doc`) cells back as an n x n float32 array."""
    n = int(doc["column_count"])
    cells = np.frombuffer(base64.b64decode(doc["data"]), "<f4")
    return cells.reshape(-1, n) if n else cells


def grid_bytes(t_ns: int, grid) -> bytes:
    """:func:`grid_doc` as JSON bytes (one format call)."""
    g = np.asarray(grid, "<f4")
    n = int(g.shape[-1]) if g.ndim else 0
    return _grid_text(t_ns, g, n).encode()


def decision_bytes(dec: dict, texture_conf) -> bytes:
    """``/tacfoot/decision``: the --json-log line plus ``surface_conf`` (the top
    class probability) and ``texture_conf``."""
    probs = dec.get("probs") or [0.0]
    return _json(dict(dec, texture_conf=texture_conf, surface_conf=round(max(probs), 4)))


def stamp(t_ns: int) -> str:
    """A foxglove time (``{"sec", "nsec"}``) as JSON text."""
    return _STAMP % (t_ns // 1_000_000_000, t_ns % 1_000_000_000)


def jpeg(image, width: int, quality: int) -> tuple[bytes, float]:
    """The frame resized to ``width`` px wide, as JPEG; and the scale applied."""
    img = np.asarray(image)
    h, w = img.shape[:2]
    s = width / float(w)
    small = cv2.resize(img, (width, max(1, int(round(h * s)))), interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError("cv2.imencode refused the frame")
    return buf.tobytes(), s


def image_bytes(t_ns: int, jpg: bytes) -> bytes:
    """``/tacfoot/image``: foxglove.CompressedImage of a JPEG."""
    return (_IMAGE % (stamp(t_ns), base64.b64encode(jpg).decode("ascii"))).encode()


def _points(pts: np.ndarray) -> str:
    flat = np.nan_to_num(pts, nan=-1.0, posinf=-1.0, neginf=-1.0).ravel()
    return _joined('{"x":%.2f,"y":%.2f}', flat.size // 2) % tuple(flat.tolist())


def annotations_bytes(t_ns: int, pins, vectors, lost, reference, scale: float,
                      vector_scale: float) -> bytes:
    """``/tacfoot/pins``: the JSON of :func:`annotations`, from a template."""
    st = stamp(t_ns)
    pins = np.asarray(pins, np.float64).reshape(-1, 2) * scale
    segs = _segments(vectors, lost, reference, scale, vector_scale)
    a = _PTS % (st, POINTS, _points(pins), _C[id(GREEN)], _C[id(GREEN)], "3.0")
    b = _PTS % (st, LINE_LIST, _points(segs), _C[id(RED)], _C[id(CLEAR)], "1.5")
    return (_ANN % (a, b)).encode()


def _segments(vectors, lost, reference, scale, vector_scale) -> np.ndarray:
    """a0, b0, a1, b1 ...: each tracked reference pin and its place plus its vector
    times ``vector_scale``, times ``scale``; none without a matching reference."""
    vectors = np.asarray(vectors, np.float64).reshape(-1, 2)
    if reference is None or len(reference) != len(vectors):
        return np.zeros((0, 2))
    ref = np.asarray(reference, np.float64).reshape(-1, 2)
    ok = ~np.asarray(lost, bool).reshape(-1)
    a = ref[ok] * scale
    b = (ref[ok] + vector_scale * vectors[ok]) * scale
    return np.stack([a, b], 1).reshape(-1, 2)


def packet_bytes(msg, seq, t_ms) -> bytes:
    """``/tacfoot/packets/out`` and ``/in``: the packet decoded."""
    d = P.message_dict(msg)
    d.update(seq=seq, t_ms=t_ms)
    return _json(d)


def faults_bytes(msg) -> bytes:
    """``/tacfoot/faults``: a FAULT packet's bits, by name."""
    return _json({"faults": int(msg.faults), "names": fault_names(msg.faults),
                  "raised": fault_names(msg.raised), "pins_lost": int(msg.pins_lost)})


#: Python logging levels -> foxglove.Log.Level (DEBUG 1, INFO 2, WARNING 3, ERROR 4, FATAL 5)
LOG_LEVELS = ((40, 4), (30, 3), (20, 2), (1, 1))


def log_level(levelno: int) -> int:
    """foxglove.Log's level of a Python logging level (CRITICAL -> FATAL)."""
    if levelno >= 50:
        return 5
    for floor, level in LOG_LEVELS:
        if levelno >= floor:
            return level
    return 0


def log_bytes(t_ns: int, level: int, message: str, name: str, file: str = "",
              line: int = 0) -> bytes:
    """``/tacfoot/log``: one foxglove.Log line (``level`` is foxglove.Log's)."""
    return _json({"timestamp": {"sec": t_ns // 1_000_000_000, "nsec": t_ns % 1_000_000_000},
                  "level": int(level), "message": str(message), "name": str(name),
                  "file": str(file), "line": max(0, int(line))})


def fault_line(msg) -> tuple[int, str]:
    """A FAULT packet as a foxglove.Log line: WARNING when it raised a bit, INFO when
    it only cleared some; the message names the bits now set and those raised."""
    now, raised = fault_names(msg.faults), fault_names(msg.raised)
    text = (f"FAULT now {', '.join(now) or 'none'}"
            + (f"; raised {', '.join(raised)}" if raised else "")
            + f"; pins lost {int(msg.pins_lost)}")
    return (3 if raised else 2), text


def annotations(stamp: dict, ff, reference, scale: float, vector_scale: float) -> dict:
    """foxglove.ImageAnnotations: one point per detected pin (green) and, for each
    reference pin still tracked, a segment from its reference place along its
    vector times ``vector_scale`` (red); pixel coordinates times ``scale``.
    (:func:`annotations_bytes` writes the same JSON, faster.)"""
    pins = np.round(np.asarray(ff.pins, np.float64).reshape(-1, 2) * scale, 2)
    segs = np.round(_segments(ff.vectors, ff.lost, reference, scale, vector_scale), 2)
    return {"circles": [], "texts": [], "points": [
        {"timestamp": stamp, "type": POINTS, "points": [{"x": x, "y": y} for x, y in
                                                        pins.tolist()],
         "outline_color": GREEN, "outline_colors": [], "fill_color": GREEN, "thickness": 3.0},
        {"timestamp": stamp, "type": LINE_LIST, "points": [{"x": x, "y": y} for x, y in
                                                           segs.tolist()],
         "outline_color": RED, "outline_colors": [], "fill_color": CLEAR, "thickness": 1.5}]}
