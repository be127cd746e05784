"""device.pi.runtime.foxglove_layout: the Foxglove layout is built from code
(foxglove-sdk's foxglove.layouts), every panel names only channels and fields the
runtime writes, and docs/foxglove-layout.json is exactly what the code builds."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

from device.pi.runtime import foxglove_layout as fl
from device.pi.runtime.mcapmsg import channels
from device.shipped import layout_file
from tests import REPO_ROOT
from tests.mcapread import read_mcap, sim_run_command

COMMITTED = REPO_ROOT / "docs" / "foxglove-layout.json"


def test_the_committed_layout_is_what_the_code_builds(tmp_path, capsys):
    text = fl.layout_json()
    assert COMMITTED.read_text() == text
    assert layout_file() == COMMITTED
    assert fl.main(["--check", str(COMMITTED)]) == 0
    stale = tmp_path / "layout.json"
    stale.write_text(text.replace("Decisions", "Decision"))
    assert fl.main(["--check", str(stale)]) == 1
    assert "differs from the layout the code builds" in capsys.readouterr().err
    assert fl.main(["--out", str(stale)]) == 0 and stale.read_text() == text


def test_every_panel_names_a_channel_and_field_the_runtime_writes(tmp_path):
    """Each panel of the built layout names at least one topic; every topic is a
    channel of a real run's MCAP log, and every field is in its messages (or, for a
    topic this short run did not write to, in its schema)."""
    doc = json.loads(fl.layout_json())
    panels = []

    def walk(node):
        if isinstance(node, dict):
            if node.get("type") == "panel":
                panels.append(node)
            for v in node.values():
                walk(v)
        elif isinstance(node, list):
            for v in node:
                walk(v)
    walk(doc)
    assert len(panels) == sum(len(col) for col in fl.COLUMNS) == 8
    assert all(fl.references(p) for p in panels), [p["title"] for p in panels]
    refs = fl.references(doc)
    assert {"/tacfoot/image", "/tacfoot/pins", "/tacfoot/imu", "/tacfoot/decision",
            "/tacfoot/latency", "/tacfoot/faults", "/tacfoot/log"} <= {t for t, _ in refs}
    log = tmp_path / "run.mcap"
    subprocess.run(sim_run_command(tmp_path, "--mcap", log, frames=30), check=True,
                   capture_output=True, timeout=120)
    chans, msgs = read_mcap(log)
    for topic, fld in refs:
        assert topic in chans, topic
        if fld is not None:
            seen = msgs[topic][-1][1] if msgs.get(topic) else channels()[topic]["properties"]
            assert fld in seen, f"{topic}.{fld}"


def test_a_panel_naming_an_unlogged_topic_or_field_is_refused():
    bad_topic = [[("raw", "x", {"topic": "/tacfoot/nope"})]]
    with pytest.raises(fl.LayoutError, match="topic '/tacfoot/nope' is not a channel"):
        fl.layout_json(bad_topic)
    bad_field = [[("plot", "x", {"series": [("/tacfoot/imu.acc_x", "ax")]})]]
    with pytest.raises(fl.LayoutError, match="/tacfoot/imu has no field 'acc_x'"):
        fl.layout_json(bad_field)
    with pytest.raises(fl.LayoutError, match="not TOPIC"):
        fl.parse_path("tacfoot.imu")
    assert fl.parse_path("/tacfoot/packets/out.seq") == ("/tacfoot/packets/out", "seq")
    assert fl.parse_path("/tacfoot/imu.acc_g[2]") == ("/tacfoot/imu", "acc_g")


def test_the_command_prints_the_layout():
    run = subprocess.run([sys.executable, "-m", "device.pi.runtime.foxglove_layout"],
                         capture_output=True, text=True, timeout=60, cwd=REPO_ROOT)
    assert run.returncode == 0 and run.stdout == COMMITTED.read_text()
