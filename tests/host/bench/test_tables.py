"""host/bench/tables.py: the real-frame tables of docs/BENCHMARKS.md, rewritten
between their markers by ``host bench tables``."""
from __future__ import annotations

import json
import time

import pytest

from host.bench.costs import PI4_FACTOR, machine, machine_line
from host.bench.specs import write_default_specs
from host.bench.tables import (marker_names, pipeline_table, replace_section,
                               runtime_rows)
from host.cli import main
from tests.realdata import real_data_dir

DOC = """# B
hand-written intro
<!-- bench:machine -->
old machine
<!-- /bench:machine -->
middle prose
<!-- bench:pipeline-real -->
old pipeline
<!-- /bench:pipeline-real -->
<!-- bench:runtime-real -->
old runtime
<!-- /bench:runtime-real -->
closing prose
"""


def test_replace_section_swaps_only_what_is_between_the_markers():
    out = replace_section(DOC, "pipeline-real", "| new |")
    assert "old pipeline" not in out and "| new |" in out
    assert "old machine" in out and "old runtime" in out
    assert out.startswith("# B\nhand-written intro") and out.endswith("closing prose\n")
    assert replace_section(out, "pipeline-real", "| new |") == out     # idempotent
    assert marker_names(out) == ["machine", "pipeline-real", "runtime-real"]


@pytest.mark.parametrize("doc", ["no markers", "<!-- /bench:x -->\n<!-- bench:x -->"])
def test_replace_section_refuses_a_document_without_its_markers(doc):
    with pytest.raises(ValueError, match="bench:x"):
        replace_section(doc, "x", "body")


def _runtime_result(p99):
    return {"source": "file:///d/roboskin/concrete.avi", "models": ["surface"],
            "command": "python -m device.pi run ...",
            "latency_ms_p50": 1.0, "latency_ms_p99": p99,
            "unpaced_latency_ms_p50": 0.8, "unpaced_latency_ms_p99": 1.5,
            "cpu_ms_per_frame_p50": 0.9, "cpu_ms_per_frame_p99": 1.2,
            "throughput_fps": 1200.0, "rss_mb_peak": 99.5,
            "load_avg_1min_per_run": {"paced": [0.5, 0.7], "unpaced": [0.7, 0.9]},
            "real": True,
            "meets": {"latency_ms_p50": True, "latency_ms_p99": p99 <= 1.5,
                      "rss_mb_peak": True, "throughput_fps": True}}


def test_runtime_rows_give_median_p99_load_and_the_pi4_estimate():
    rows = runtime_rows(_runtime_result(p99=3.0))
    latency = next(r for r in rows if "paced at 120 fps" in r)
    assert latency.startswith("| concrete.avi |")
    assert "| 1.00 | 3.00 |" in latency
    assert f"{1.0 * PI4_FACTOR:.2f} / {3.0 * PI4_FACTOR:.2f}" in latency
    assert "0.50 -> 0.70" in latency and "p99 <= 1.5 ms: **missed**" in latency
    assert "p50 <= 0.8 ms: ok" in latency
    thr = next(r for r in rows if "throughput" in r)
    assert f"| {1200 / PI4_FACTOR:.0f} |" in thr and ">= 1000 frames/s: ok" in thr
    assert "ok" in runtime_rows(_runtime_result(p99=1.5))[0]


def test_machine_line_names_cores_and_load():
    line = machine_line(machine())
    assert "cores" in line and "load average" in line


def test_host_bench_tables_rewrites_the_real_tables(tmp_path, capsys):
    data = real_data_dir("roboskin/smooth.avi", "roboskin/concrete.avi",
                         "roboskin/concrete_gyro.npy")
    spec = write_default_specs(data, tmp_path / "specs")["bench"]
    doc = tmp_path / "BENCH.md"
    doc.write_text(DOC)
    rc = main(["bench", "tables", "--data", str(spec), "--doc", str(doc),
               "--frames", "40", "--repeats", "1", "--json"])
    assert rc == 0
    res = json.loads(capsys.readouterr().out)
    text = doc.read_text()
    assert "old pipeline" not in text and "old runtime" not in text
    assert "hand-written intro" in text and "closing prose" in text
    for clip in ("smooth.avi", "concrete.avi"):
        assert f"| {clip} | total |" in text
        assert f"| {clip} | latency, paced at 120 fps |" in text
    assert [r["real"] for r in res["runtime"]] == [True, True]
    assert all(r["frames_run"] > 0 for r in res["runtime"])
    assert pipeline_table(res["pipeline"]).count("baseline:") == 2


def test_host_bench_tables_refuses_a_doc_without_markers(tmp_path, capsys):
    data = real_data_dir("roboskin/smooth.avi")
    spec = tmp_path / "mine.csv"
    spec.write_text(f"path,label\n{data / 'roboskin' / 'smooth.avi'},smooth\n")
    doc = tmp_path / "plain.md"
    doc.write_text("# nothing to fill\n")
    assert main(["bench", "tables", "--data", str(spec), "--doc", str(doc)]) == 2
    assert "bench:machine" in capsys.readouterr().err
    assert doc.read_text() == "# nothing to fill\n"


def test_host_bench_tables_with_a_missing_recording_is_one_line_and_exit_2(tmp_path, capsys):
    (tmp_path / "mine.csv").write_text("path,label,imu\nmine.avi,smooth,mine_gyro.npy\n")
    (tmp_path / "mine.avi").write_bytes(b"")
    doc = tmp_path / "BENCH.md"
    doc.write_text(DOC)
    t0 = time.perf_counter()
    rc = main(["bench", "tables", "--data", str(tmp_path / "mine.csv"), "--doc", str(doc)])
    assert time.perf_counter() - t0 < 1.0
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "mine_gyro.npy" in err[0]
    assert doc.read_text() == DOC
    assert main(["bench", "tables", "--doc", str(doc)]) == 2
    assert "--data SPEC" in capsys.readouterr().err
