"""device/pi/runtime/mcapmsg.py: the template encoders write the JSON the dict
versions would (annotations_bytes == annotations, the small messages as their
schemas name them), a value that is not finite is null (still JSON), and the
pins template serves any pin count."""
from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

from device.pi import protocol as P
from device.pi.runtime import mcapmsg as M


def _ff(n=5, seed=0):
    rng = np.random.default_rng(seed)
    return SimpleNamespace(pins=rng.uniform(0, 400, (n, 2)), vectors=rng.normal(0, 2, (n, 2)),
                           lost=rng.random(n) < 0.3)


@pytest.mark.parametrize("n", [0, 1, 7, 130])
def test_annotations_bytes_is_the_json_of_annotations(n):
    ff = _ff(n, n)
    ref = ff.pins + 1.0
    t = 12_345_678_901
    got = json.loads(M.annotations_bytes(t, ff.pins, ff.vectors, ff.lost, ref, 0.5, 3.0))
    want = M.annotations({"sec": 12, "nsec": 345_678_901}, ff, ref, 0.5, 3.0)
    assert got == json.loads(json.dumps(want))
    assert len(got["points"][0]["points"]) == n
    assert len(got["points"][1]["points"]) == 2 * int((~ff.lost).sum())


def test_annotations_without_a_matching_reference_have_no_segments():
    ff = _ff(4)
    got = json.loads(M.annotations_bytes(0, ff.pins, ff.vectors, ff.lost, None, 1.0, 3.0))
    assert got["points"][1]["points"] == [] and len(got["points"][0]["points"]) == 4


def test_small_messages_read_back_as_their_fields():
    assert json.loads(M.imu_bytes(3, [0.1, -0.2, 0.98, 1.5, -2.25, 0.0], 4)) == {
        "frame": 3, "acc_g": [0.1, -0.2, 0.98], "gyro_dps": [1.5, -2.25, 0.0], "faults": 4}
    assert json.loads(M.latency_bytes(3, None, 2.5)) == {
        "frame": 3, "latency_ms": None, "pipeline_ms": 2.5}
    assert json.loads(M.latency_bytes(3, 1.23456, 2.5))["latency_ms"] == 1.2346
    g = np.arange(9, dtype=np.float64).reshape(3, 3) / 7
    assert json.loads(M.grid_bytes(5, g, True)) == {
        "frame": 5, "n": 3, "cells": np.round(g.ravel(), 3).tolist(), "contact": True}
    d = json.loads(M.decision_bytes({"frame": 1, "probs": [0.1, 0.9]}, 0.75))
    assert d == {"frame": 1, "probs": [0.1, 0.9], "surface_conf": 0.9, "texture_conf": 0.75}


def test_a_value_that_is_not_finite_is_null_not_invalid_json():
    imu = json.loads(M.imu_bytes(0, [np.nan, 0, 1, np.inf, 0, 0], 0))
    assert imu["acc_g"] == [None, 0.0, 1.0] and imu["gyro_dps"] == [None, 0.0, 0.0]
    g = json.loads(M.grid_bytes(0, np.array([[np.nan, 1.0], [2.0, -np.inf]]), False))
    assert g["cells"] == [None, 1.0, 2.0, None] and g["n"] == 2
    lat = json.loads(M.latency_bytes(0, float("nan"), float("inf")))
    assert lat == {"frame": 0, "latency_ms": None, "pipeline_ms": 0.0}
    ann = json.loads(M.annotations_bytes(0, [[np.nan, 2.0]], [[0, 0]], [False], None, 1, 1))
    assert ann["points"][0]["points"] == [{"x": -1.0, "y": 2.0}]


def test_packets_and_faults_decode_their_message():
    f = P.Fault(faults=1, raised=1, pins_lost=3)
    d = json.loads(M.packet_bytes(f, 7, 99))
    assert d["type"] == "fault" and d["seq"] == 7 and d["t_ms"] == 99
    assert json.loads(M.faults_bytes(f)) == {"faults": 1, "names": d["faults_names"],
                                             "raised": d["raised_names"], "pins_lost": 3}


def test_jpeg_is_the_configured_width():
    import cv2
    jpg, s = M.jpeg(np.zeros((480, 640), np.uint8), 320, 75)
    assert s == 0.5
    assert cv2.imdecode(np.frombuffer(jpg, np.uint8), cv2.IMREAD_UNCHANGED).shape == (240, 320)
    img = json.loads(M.image_bytes(1_500_000_000, jpg))
    assert img["timestamp"] == {"sec": 1, "nsec": 500_000_000} and img["format"] == "jpeg"
