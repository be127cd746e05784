"""host/bench/sim.py: the pipeline benchmark scores pins with the analysis code."""
from __future__ import annotations


def test_the_benchmark_scores_pins_with_the_one_recall_precision():
    from host.analysis import recall
    from host.bench import sim

    assert sim.recall_precision is recall.recall_precision


def test_bench_pipeline_times_the_users_own_recordings_with_their_profile(tmp_path, capsys):
    """``host bench pipeline --data SPEC --profile P``: the spec's recordings (named by
    the user), measured with the profile; no built-in clip."""
    import json

    import cv2

    from host.cli import main
    from tests.realdata import read_video, real_data_dir

    src = real_data_dir("roboskin/smooth.avi") / "roboskin" / "smooth.avi"
    frames = read_video(src, 0, 30)
    h, w = frames[0].shape[:2]
    out = cv2.VideoWriter(str(tmp_path / "my_skin.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 30,
                          (w, h))
    for f in frames:
        out.write(f)
    out.release()
    (tmp_path / "mine.csv").write_text("path,label\nmy_skin.avi,smooth\n")
    rc = main(["bench", "pipeline", "--data", str(tmp_path / "mine.csv"), "--profile",
               "tactip331", "--repeats", "1", "--frames", "20", "--json"])
    assert rc == 0
    res = json.loads(capsys.readouterr().out)
    assert res["profile"] == "tactip331"
    assert sorted(res["sets"]) == ["real my_skin.avi", "sim drag-45"]
    assert res["sets"]["real my_skin.avi"]["frames"] == 20


def test_bench_pipeline_with_a_missing_file_or_profile_is_one_line_and_exit_2(tmp_path,
                                                                             capsys):
    import time

    from host.cli import main

    (tmp_path / "mine.csv").write_text("path,label\ngone.avi,smooth\n")
    t0 = time.perf_counter()
    assert main(["bench", "pipeline", "--data", str(tmp_path / "mine.csv")]) == 2
    assert time.perf_counter() - t0 < 1.0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "gone.avi" in err[0]
    assert main(["bench", "pipeline", "--profile", str(tmp_path / "mine.toml")]) == 2
    assert "no such file" in capsys.readouterr().err
