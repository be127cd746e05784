"""device/pi/runtime/mcapmsg.py: the template encoders write the JSON the dict
versions would (annotations_bytes == annotations, the small messages as their
schemas name them), a value that is not finite is null (still JSON), and the
pins template serves any pin count. And the log follows the rules strict readers
apply (issue 32 items 8-10): every message validates (``jsonschema``) against its
channel's schema, Foxglove's topics carry Foxglove's own schemas (from the installed
foxglove-sdk), log times never step back within a topic and are Unix-epoch ns, and
each file holds a ``tacfoot`` Metadata record; on a ``sim://`` run and a real clip."""
from __future__ import annotations

import json
import subprocess
import sys
import time
from types import SimpleNamespace

import numpy as np
import pytest

from device.pi import protocol as P
from device.pi.runtime import mcapmsg as M
from tests.realdata import real_data_dir


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
    doc = json.loads(M.grid_bytes(5_000_000_123, g))
    assert doc == M.grid_doc(5_000_000_123, g)
    assert doc["timestamp"] == {"sec": 5, "nsec": 123} and doc["frame_id"] == M.FRAME_ID
    assert (doc["column_count"], doc["row_stride"], doc["cell_stride"]) == (3, 12, 4)
    assert doc["fields"] == [{"name": "contact", "offset": 0, "type": 7}]     # FLOAT32
    assert np.array_equal(M.grid_cells(doc), g.astype(np.float32))
    d = json.loads(M.decision_bytes({"frame": 1, "probs": [0.1, 0.9]}, 0.75))
    assert d == {"frame": 1, "probs": [0.1, 0.9], "surface_conf": 0.9, "texture_conf": 0.75}


def test_a_value_that_is_not_finite_is_null_not_invalid_json():
    imu = json.loads(M.imu_bytes(0, [np.nan, 0, 1, np.inf, 0, 0], 0))
    assert imu["acc_g"] == [None, 0.0, 1.0] and imu["gyro_dps"] == [None, 0.0, 0.0]
    g = json.loads(M.grid_bytes(0, np.array([[np.nan, 1.0], [2.0, -np.inf]])))
    cells = M.grid_cells(g).ravel()                # in the bytes, not in the JSON
    assert np.isnan(cells[0]) and cells[1:3].tolist() == [1.0, 2.0] and cells[3] == -np.inf
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


# -- the log against its schemas, its times and its metadata (issue 32 items 8-10) --
def _run(tmp_path, camera, imu, frames):
    f = tmp_path / "run.mcap"
    t0 = time.time_ns()
    r = subprocess.run([sys.executable, "-m", "device.pi", "run", "--camera", camera,
                        "--imu", imu, "--serial", "loop://", "--frames", str(frames),
                        "--json", "--mcap", str(f)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    return f, json.loads(r.stdout), t0, time.time_ns()


def _read(path):
    from mcap.reader import make_reader
    """(schema name -> JSON schema, [(topic, schema name, log_time, message)], metadata)."""
    with open(path, "rb") as fh:
        rd = make_reader(fh)
        msgs = [(ch.topic, s.name, m.log_time, json.loads(m.data), json.loads(s.data))
                for s, ch, m in rd.iter_messages(log_time_order=False)]
        fh.seek(0)
        meta = {m.name: dict(m.metadata) for m in make_reader(fh).iter_metadata()}
    return msgs, meta


def _check(path, t0, t1) -> dict:
    jsonschema = pytest.importorskip("jsonschema")
    msgs, meta = _read(path)
    assert msgs
    bad, back, validators = [], {}, {}
    last: dict[str, int] = {}
    for topic, name, t, doc, schema in msgs:
        v = validators.get(name)
        if v is None:
            v = validators[name] = jsonschema.Draft202012Validator(schema)
        errs = list(v.iter_errors(doc))
        if errs:
            bad.append(f"{topic}: {errs[0].message}")
        if topic in last and t < last[topic]:
            back[topic] = back.get(topic, 0) + 1
        last[topic] = t
        # Unix-epoch ns: within the run's wall-clock span (plus a minute's slack)
        assert t0 - 60 * 10**9 <= t <= t1 + 60 * 10**9, (topic, t, t0)
    assert not bad, f"{len(bad)} of {len(msgs)} messages break their schema: {bad[:3]}"
    assert not back, f"log times step back: {back}"
    return meta


def test_foxglove_topics_carry_foxglove_sdk_schemas():
    pytest.importorskip("foxglove")
    ch = M.channels()
    ann = ch["/tacfoot/pins"]
    assert ann["title"] == "foxglove.ImageAnnotations"
    # every field of the SDK's message, not a hand copy's subset
    assert {"circles", "points", "texts", "metadata"} <= set(ann["properties"])
    pts = ann["properties"]["points"]["items"]["properties"]
    assert {"timestamp", "type", "points", "outline_color", "outline_colors", "fill_color",
            "thickness", "metadata"} <= set(pts)
    assert ch["/tacfoot/image"]["properties"]["data"]["contentEncoding"] == "base64"
    # the contact grid and the log lines: Foxglove's Grid and Log, whole
    grid, line = ch["/tacfoot/grid"], ch["/tacfoot/log"]
    assert (grid["title"], line["title"]) == ("foxglove.Grid", "foxglove.Log")
    assert {"timestamp", "frame_id", "pose", "column_count", "cell_size", "row_stride",
            "cell_stride", "fields", "data"} <= set(grid["properties"])
    assert {"timestamp", "level", "message", "name", "file", "line"} <= set(line["properties"])


def test_grid_and_log_lines_validate_against_foxglove_schemas():
    jsonschema = pytest.importorskip("jsonschema")
    pytest.importorskip("foxglove")
    ch = M.channels()
    g = json.loads(M.grid_bytes(7, np.full((4, 4), np.nan)))
    jsonschema.validate(g, ch["/tacfoot/grid"])
    level, text = M.fault_line(P.Fault(faults=1, raised=1, pins_lost=2))
    ln = json.loads(M.log_bytes(3 * 10**9 + 5, level, text, "tacfoot.faults"))
    jsonschema.validate(ln, ch["/tacfoot/log"])
    assert ln["level"] == 3 and ln["timestamp"] == {"sec": 3, "nsec": 5}
    assert "raised" in ln["message"] and "pins lost 2" in ln["message"]
    assert [M.log_level(x) for x in (10, 20, 30, 40, 50)] == [1, 2, 3, 4, 5]


def test_a_sim_run_validates_is_monotonic_in_epoch_ns_with_metadata(tmp_path):
    pytest.importorskip("mcap")
    f, status, t0, t1 = _run(tmp_path, "sim://walk", "sim://walk", 60)
    meta = _check(f, t0, t1)
    md = meta["tacfoot"]
    assert set(md) == {"version", "profile", "profile_sha256", "models", "config"}
    assert md["profile"] and len(md["profile_sha256"]) == 64
    models = json.loads(md["models"])
    assert len(models) >= 1 and len(status["models"]) >= 1      # the shipped models ran
    assert all(len(h) == 64 for hs in models.values() for h in hs.values())
    assert json.loads(md["config"])["mcap"]["image_every"] >= 1
    assert status["mcap_messages_lost"] == 0


def test_a_real_clip_validates_and_is_monotonic(tmp_path):
    pytest.importorskip("mcap")
    d = real_data_dir("roboskin/concrete.avi", "roboskin/concrete_gyro.npy") / "roboskin"
    f, _, t0, t1 = _run(tmp_path, str(d / "concrete.avi"),
                        f"file://{d / 'concrete_gyro.npy'}", 150)
    _check(f, t0, t1)
