"""``host bench runtime`` (host/bench/runtime.py): the leg runtime end to end on
simulated hardware, as JSON."""
from __future__ import annotations

import json

import pytest

from host.cli import main


def test_host_bench_runtime_json(capsys):
    assert main(["bench", "runtime", "--frames", "40", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["frames"] == 40 and res["latency_samples"] >= 35
    assert 0 < res["latency_ms_p50"] <= res["latency_ms_p99"] < 1000
    assert res["throughput_fps"] > 10 and 30 < res["rss_mb_peak"] < 2000
    assert res["rss_mb_peak_with_simulator"] > res["rss_mb_peak"]   # the sim is not free
    assert res["surface_packet_bytes"] <= 32 and res["meets"]["surface_packet_bytes"]
    assert res["meets"]["latency_ms_p99"] == (res["latency_ms_p99"] <= 2.0)



def test_host_bench_runtime_on_a_real_recording(capsys):
    from tests.realdata import real_data_dir
    clip = real_data_dir("roboskin/concrete.avi") / "roboskin"
    assert main(["bench", "runtime", "--camera", str(clip / "concrete.avi"), "--imu",
                 f"file://{clip / 'concrete_gyro.npy'}", "--frames", "30", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["real"] and res["source"].endswith("concrete.avi")
    assert res["models_fused"] is True          # as deployed: one model call per frame
    assert res["frames_run"] == 30 and res["rss_mb_peak_with_simulator"] is None
    assert 0 < res["latency_ms_p50"] <= res["latency_ms_p99"]
    assert res["pi4"]["latency_ms_p99"] == res["latency_ms_p99"] * res["pi4_factor"]
    assert res["pi4"]["throughput_fps"] == res["throughput_fps"] / res["pi4_factor"]
    assert res["meets"]["throughput_fps"] == (res["throughput_fps"] >= 1000)
    assert res["meets"]["latency_ms_p50"] == (res["latency_ms_p50"] <= 0.8)
    assert res["meets"]["rss_mb_peak"] == (res["rss_mb_peak"] <= 120)
    before, after = res["load_avg_1min_per_run"]["paced"]
    assert before >= 0 and after >= 0


def test_host_bench_runtime_refuses_a_missing_recording(tmp_path, capsys):
    assert main(["bench", "runtime", "--camera", str(tmp_path / "nope.avi")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_host_bench_runtime_bad_sources_are_one_line_and_exit_2(tmp_path, capsys):
    """A missing recording, a file that is no video and an IMU the runtime refuses:
    each is the runtime's own one-line reason and exit 2, not a traceback."""
    import cv2
    import numpy as np

    not_video = tmp_path / "notes.txt"
    not_video.write_text("not a video\n")
    clip = tmp_path / "clip.avi"
    vw = cv2.VideoWriter(str(clip), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (64, 48), False)
    for _ in range(5):
        vw.write(np.zeros((48, 64), np.uint8))
    vw.release()
    for argv, word in ((["--camera", str(tmp_path / "missing.avi")], "--camera"),
                       (["--camera", str(not_video)], "--camera"),
                       (["--camera", str(clip), "--imu", "bogus://x"], "--imu")):
        capsys.readouterr()
        assert main(["bench", "runtime", *argv, "--frames", "5"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and word in err[0], err


def test_host_bench_runtime_an_empty_imu_recording_is_one_line_naming_it(tmp_path, capsys):
    """Issue 21, item 6: a zero-length .npy was an EOFError traceback in the runtime
    (device.pi run) and so in the bench that runs it."""
    empty = tmp_path / "empty.npy"
    empty.write_bytes(b"")
    assert main(["bench", "runtime", "--camera", "sim://walk", "--imu", f"file://{empty}",
                 "--frames", "5"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--imu" in err[0] and "empty.npy" in err[0], err


def _tactip_models(tmp_path):
    """A models folder whose one model (a copy of the shipped pressure model) carries
    the tactip331 profile in its spec."""
    import json
    import shutil

    from device.pi.models.spec import ModelSpec, profile_record
    from tests import REPO_ROOT
    d = tmp_path / "models"
    shutil.copytree(REPO_ROOT / "models" / "pressure", d / "pressure")
    for mf in (d / "pressure").glob("manifest*.json"):
        spec = ModelSpec.from_manifest(json.loads(mf.read_text()), mf)
        spec.profile = {k: v for k, v in profile_record("tactip331").items() if k != "path"}
        mf.write_text(json.dumps(spec.to_manifest()))
    return d


def test_the_runtime_under_test_gets_the_models_profile_and_refuses_another(tmp_path, capsys):
    from device.pi.runtime.config import load_leg_config
    from host.bench.runtime import runtime_config
    assert runtime_config(None, None, tmp_path) is None          # shipped: roboskin
    models = _tactip_models(tmp_path)
    cfg = runtime_config(str(models), None, tmp_path)
    assert load_leg_config(cfg).models.profile == "tactip331"
    with pytest.raises(ValueError, match=r"roboskin\.toml \(roboskin, 133 pins.*is not the "
                                         r"model's: .*pressure/manifest\.json \(tactip331"):
        runtime_config(str(models), "roboskin", tmp_path)
    rc = main(["bench", "runtime", "--models", str(models), "--profile", "roboskin"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and "(tactip331, 331 pins" in err
