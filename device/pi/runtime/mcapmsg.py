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


_ENCODE = json.JSONEncoder(separators=(",", ":")).encode     # one encoder, made once


def _json(doc) -> bytes:
    return _ENCODE(doc).encode()


_IMU = '{"frame":%d,"acc_g":[%.5f,%.5f,%.5f],"gyro_dps":[%.4f,%.4f,%.4f],"faults":%d}'
_LAT = '{"frame":%d,"latency_ms":%s,"pipeline_ms":%.4f}'
_GRID = '{"frame":%d,"n":%d,"cells":[%s],"contact":%s}'
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


def grid_bytes(k: int, grid, contact: bool) -> bytes:
    """``/tacfoot/grid``: the n x n contact grid, row-major, 3 places."""
    g = np.asarray(grid, np.float64)
    n = int(g.shape[0]) if g.ndim else 0
    cells = g.ravel()
    if not _finite(cells):
        return _json({"frame": k, "n": n, "cells": _nums(cells, 3), "contact": bool(contact)})
    body = _joined("%.3f", cells.size) % tuple(cells.tolist())
    return (_GRID % (k, n, body, "true" if contact else "false")).encode()


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
