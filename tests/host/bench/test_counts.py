"""host/bench/counts.py: instructions per frame with callgrind. valgrind itself is
not run here (a counted run takes minutes): the parser, the arithmetic, the frames
and the commands are, and a stand-in ``valgrind`` on PATH checks the plumbing."""
from __future__ import annotations

import os
import stat
import sys

import numpy as np
import pytest

from host.bench import counts as C


CALLGRIND_OUT = """\
# callgrind format
version: 1
creator: callgrind-3.19.0
pid: 4242
cmd:  python -m host.bench.count_drivers pipeline frames 220
part: 1

desc: I1 cache:
positions: line
events: Ir
summary: 1838330219

fl=(1) ???
fn=(1) 0x0000000000001100
0 3
totals: 1838330219
"""


def test_parse_callgrind_reads_the_summary_line(tmp_path):
    f = tmp_path / "callgrind.out"
    f.write_text(CALLGRIND_OUT)
    assert C.parse_callgrind(f) == 1_838_330_219


def test_parse_callgrind_falls_back_to_totals_and_prefers_summary(tmp_path):
    f = tmp_path / "a.out"
    f.write_text(CALLGRIND_OUT.replace("summary: 1838330219\n", ""))
    assert C.parse_callgrind(f) == 1_838_330_219
    f.write_text("events: Ir\ntotals: 7\nsummary: 5\n")
    assert C.parse_callgrind(f) == 5
    f.write_text("events: Ir Dr\nsummary: 12 34\n")     # several events: Ir is the first
    assert C.parse_callgrind(f) == 12


def test_parse_callgrind_without_a_total_names_the_file(tmp_path):
    f = tmp_path / "empty.out"
    f.write_text("events: Ir\n")
    with pytest.raises(C.CountError, match="empty.out: no 'summary:' or 'totals:'"):
        C.parse_callgrind(f)


def test_per_frame_is_the_difference_over_the_extra_frames():
    # 952,880,852 at 20 frames, 1,838,330,219 at 220: 4,427,246.835 per frame
    assert C.per_frame(952_880_852, 1_838_330_219, 20, 220) == pytest.approx(4_427_246.835)
    assert C.per_frame(100, 100, 1, 2) == 0.0
    with pytest.raises(ValueError, match="n1=20, n2=20"):
        C.per_frame(1, 2, 20, 20)


def test_pi4_ms_divides_by_the_named_rate():
    assert C.PI4_INSTR_PER_S == 1.75e9
    assert C.pi4_ms(1.75e6) == pytest.approx(1.0)
    assert C.pi4_ms(8.91e6) == pytest.approx(8.91e6 / 1.75e9 * 1e3)
    assert C.FRAME_BUDGET_MS == pytest.approx(8.333, abs=1e-3)


def test_write_pgm_round_trips_through_opencv(tmp_path):
    import cv2
    g = np.arange(7 * 5, dtype=np.uint8).reshape(5, 7) * 7
    C.write_pgm(tmp_path / "f.pgm", g)
    assert (tmp_path / "f.pgm").read_bytes()[:11] == b"P5\n7 5\n255\n"
    back = cv2.imread(str(tmp_path / "f.pgm"), cv2.IMREAD_UNCHANGED)
    assert back.dtype == np.uint8 and np.array_equal(back, g)
    with pytest.raises(ValueError, match=r"shape \(5, 7, 3\)"):
        C.write_pgm(tmp_path / "c.pgm", np.zeros((5, 7, 3), np.uint8))


def _clip(path, n=6):
    import cv2
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (32, 24))
    for i in range(n):
        f = np.zeros((24, 32, 3), np.uint8)
        f[:, :, 2] = 40 * i                       # red rises: gray is BGR2GRAY of it
        f[5:10, 5:10] = 255
        vw.write(f)
    vw.release()
    return path


def test_frame_folder_writes_gray_pgms_once_and_reuses_them(tmp_path):
    import cv2
    clip = _clip(tmp_path / "walk.avi")
    folder = C.frame_folder(clip, 4, cache=tmp_path / "cache")
    assert folder == tmp_path / "cache" / "walk"
    names = sorted(p.name for p in folder.glob("*.pgm"))
    assert names == [f"frame_{i:05d}.pgm" for i in range(4)]
    cap = cv2.VideoCapture(str(clip))
    ok, first = cap.read()
    cap.release()
    got = cv2.imread(str(folder / "frame_00000.pgm"), cv2.IMREAD_UNCHANGED)
    assert ok and got.ndim == 2 and np.array_equal(got, cv2.cvtColor(first, cv2.COLOR_BGR2GRAY))
    stamp = (folder / "frame_00003.pgm").stat().st_mtime_ns
    assert C.frame_folder(clip, 3, cache=tmp_path / "cache") == folder      # cached
    assert (folder / "frame_00003.pgm").stat().st_mtime_ns == stamp
    with pytest.raises(C.CountError, match="6 frames decoded, 9 needed"):
        C.frame_folder(clip, 9, cache=tmp_path / "cache")


def test_imu_for_finds_the_gyro_file_beside_the_clip(tmp_path):
    for name in ("lego_train.avi", "lego_gyro_train.npy", "concrete.avi",
                 "concrete_gyro.npy", "smooth.avi"):
        (tmp_path / name).write_bytes(b"")
    assert C.imu_for(tmp_path / "lego_train.avi") == f"file://{tmp_path / 'lego_gyro_train.npy'}"
    assert C.imu_for(tmp_path / "concrete.avi") == f"file://{tmp_path / 'concrete_gyro.npy'}"
    assert C.imu_for(tmp_path / "smooth.avi") == "none"


def test_stall_config_is_the_default_config_with_stall_periods_100(tmp_path):
    from device.pi.runtime.config import load_leg_config
    path = C.stall_config(tmp_path)
    cfg, default = load_leg_config(path), load_leg_config()
    assert cfg.camera.stall_periods == 100.0 and default.camera.stall_periods != 100.0
    assert cfg.camera.fps == default.camera.fps and cfg.serial == default.serial


def test_commands():
    cmd = C.callgrind_cmd("/tmp/cg.out", ["python", "-m", "x", 3])
    assert cmd == ["valgrind", "--tool=callgrind", "--callgrind-out-file=/tmp/cg.out",
                   "python", "-m", "x", "3"]
    rt = C.runtime_argv("frames/lego", "file://g.npy", 220, "leg.toml", python="py")
    assert rt == ["py", "-m", "device.pi", "run", "--camera", "frames/lego", "--imu",
                  "file://g.npy", "--serial", "loop://", "--frames", "220", "--config",
                  "leg.toml", "--json"]
    assert C.driver_argv("pipeline", "d", 20, "t.json", python="py") == [
        "py", "-m", "host.bench.count_drivers", "pipeline", "d", "20", "--timings", "t.json"]
    assert C.driver_argv("peer", "d", 20, python="py")[-2:] == ["d", "20"]


def _runs(per, n1=20, n2=220, base=1_000_000_000):
    """Fake raw runs: each name costs ``base + per[name] * n``."""
    return {name: {n: {"instructions": base + p * n, "seconds": 1.0, "command": name}
                   for n in (n1, n2)} for name, p in per.items()}


def test_summarise_takes_stages_from_the_cumulative_variants(tmp_path):
    per = {"runtime": 9_000_000, "pipeline": 4_400_000, "peer": 23_000_000,
           "stage:detect": 3_100_000, "stage:track": 3_900_000, "stage:grid": 4_150_000,
           "stage:features": 4_300_000}
    runs = _runs(per)
    runs["pipeline"][20]["timings"] = {"timings_ms": {"detect": 10.0, "track": 5.0,
                                                      "total": 15.0}}
    runs["pipeline"][220]["timings"] = {"timings_ms": {"detect": 40.0, "track": 15.0,
                                                       "total": 55.0}}
    res = C.summarise(tmp_path / "lego_train.avi", runs, 20, 220)
    assert res["figures"]["pipeline"]["per_frame"] == pytest.approx(4.4e6)
    assert res["figures"]["peer"]["pi4_ms"] == pytest.approx(23e6 / 1.75e9 * 1e3)
    st = {k: v["per_frame"] for k, v in res["stages"].items()}
    assert st == pytest.approx({"detect": 3.1e6, "track": 0.8e6, "grid": 0.25e6,
                                "features": 0.15e6, "rest": 0.1e6})
    assert res["timer_split"] == pytest.approx({"detect": 0.75, "track": 0.25})
    text = C.format_counts({"clips": [res]})
    assert "marker pipeline" in text and "4.40" in text and "23.00" in text
    assert "13.14" in text                         # the peer's Pi 4 ms: 23e6 / 1.75e9


def test_summarise_reports_a_failed_variant_and_keeps_the_rest(tmp_path):
    runs = _runs({"runtime": 9, "pipeline": 4, "peer": 20, "stage:detect": 3,
                  "stage:grid": 4, "stage:features": 4})
    runs["stage:track"] = {20: {"error": "track: AttributeError: no tracker"}, 220: {}}
    res = C.summarise(tmp_path / "x.avi", runs, 20, 220)
    assert res["figures"]["pipeline"]["per_frame"] == 4
    assert res["stages"]["detect"]["per_frame"] == 3
    assert res["stages"]["track"] == {"per_frame": None,
                                      "error": "track: AttributeError: no tracker"}
    assert res["stages"]["grid"]["per_frame"] is None
    assert res["stages"]["rest"]["per_frame"] is None
    assert "n/a  (track: AttributeError: no tracker)" in C.format_counts({"clips": [res]})


FAKE_VALGRIND = """#!{python}
import sys
out = [a.split("=", 1)[1] for a in sys.argv if a.startswith("--callgrind-out-file=")][0]
argv = sys.argv[sys.argv.index("--tool=callgrind") + 2:]
n = int(argv[argv.index("--frames") + 1]) if "--frames" in argv else int(argv[5])
kind = "runtime" if "--frames" in argv else argv[3]
if kind == "runtime" and argv[argv.index("--serial") + 1] != "loop://":
    import os
    with open(argv[argv.index("--serial") + 1], "wb", buffering=0) as port:
        assert os.isatty(port.fileno())
        port.write(b"a packet")       # the harness reads it, as a UART's far end would
    kind = "runtime_pty"
per = {{"runtime": 900, "runtime_pty": 850, "pipeline": 440, "peer": 2300, "detect": 310,
        "track": 390, "grid": 415, "features": 430}}[kind]
open(out, "w").write(f"events: Ir\\nsummary: {{1000000 + per * n}}\\n")
"""


def test_count_clip_through_a_stand_in_valgrind(tmp_path, monkeypatch):
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    fake = bin_dir / "valgrind"
    fake.write_text(FAKE_VALGRIND.format(python=sys.executable))
    fake.chmod(fake.stat().st_mode | stat.S_IXUSR)
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    clip = _clip(tmp_path / "walk.avi")
    seen = []
    res = C.count_clip(clip, n1=2, n2=5, jobs=2, cache=tmp_path / "cache", progress=seen.append)
    assert res["figures"]["runtime"]["per_frame"] == 900
    assert res["figures"]["runtime_pty"]["per_frame"] == 850
    assert "--serial PTY" in res["figures"]["runtime_pty"]["command_n2"]
    assert res["figures"]["pipeline"]["per_frame"] == 440
    assert res["figures"]["peer"]["per_frame"] == 2300
    assert {k: v["per_frame"] for k, v in res["stages"].items()} == {
        "detect": 310, "track": 80, "grid": 25, "features": 15, "rest": 10}
    cmd = res["figures"]["runtime"]["command_n2"]
    assert cmd.startswith("python -m device.pi run --camera ") and "--frames 5" in cmd
    assert "--serial loop://" in cmd and "--imu none" in cmd
    assert len(seen) == 16                      # 8 programs, two lengths each


def test_main_without_valgrind_says_so_in_one_line(monkeypatch, capsys):
    monkeypatch.setattr(C.shutil, "which", lambda name: None)
    assert C.main(["--skip-without-valgrind"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["instruction counts skipped: valgrind not found "
                   "(Debian: apt-get install valgrind)"]
    assert C.main([]) == 1


def test_bad_lengths_are_refused_before_anything_runs(tmp_path):
    with pytest.raises(ValueError, match="n1=20, n2=10"):
        C.bench_counts(tmp_path, n1=20, n2=10)
    if C.valgrind_found():
        with pytest.raises(C.CountError, match="no such clip: nope.avi"):
            C.bench_counts(tmp_path, clips=["nope.avi"])


def test_host_bench_counts_refuses_bad_lengths_in_one_line(capsys):
    from host.cli import main
    assert main(["bench", "counts", "--n1", "30", "--n2", "20"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].endswith("need 1 <= n1 < n2, got n1=30, n2=20")
