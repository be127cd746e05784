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


def _double_loop_pairs(ref, pins):
    """The baseline's old matching, pin by pin (the reference the vectorised one must
    equal): for each reference pin the first pin at the least squared distance."""
    import numpy as np

    out = np.full(len(ref), -1, np.int64)
    for i, r in enumerate(ref):
        best, bd = -1, 1e18
        for j, c in enumerate(pins):
            d = (c[0] - r[0]) ** 2 + (c[1] - r[1]) ** 2
            if d < bd:
                best, bd = j, d
        out[i] = best
    return out


def test_vectorised_baseline_gives_the_double_loops_pairs_on_synthetic_point_sets():
    import numpy as np

    from host.bench.sim import nearest_pins

    rng = np.random.default_rng(3)
    for m, n in ((133, 130), (40, 55), (7, 1), (5, 0), (0, 4)):
        ref = rng.uniform(0, 480, (m, 2)).astype(np.float32)
        base = ref[rng.integers(0, max(m, 1), n)] if m else rng.uniform(0, 480, (n, 2))
        pins = (base + rng.normal(0, 3.0, (n, 2))).astype(np.float32).reshape(-1, 2)
        got = nearest_pins(ref, pins)
        assert got.dtype == np.int64 and got.shape == (m,)
        assert np.array_equal(got, _double_loop_pairs(ref, pins)), (m, n)
    # exact ties (a lattice, pins half way between two references) go to the first pin
    ref = np.array([[0, 0], [10, 0]], np.float32)
    pins = np.array([[5, 0], [5, 0], [-5, 0]], np.float32)
    assert nearest_pins(ref, pins).tolist() == _double_loop_pairs(ref, pins).tolist() == [0, 0]


def test_vectorised_baseline_gives_the_double_loops_pairs_and_vectors_on_real_frames():
    import numpy as np

    from device.pi.vision.extract import to_gray
    from host.bench.sim import BaselineBlobTracker
    from tests.realdata import read_video, real_data_dir

    src = real_data_dir("roboskin/concrete.avi") / "roboskin" / "concrete.avi"
    frames = read_video(src, 0, 200)[::40]           # 5 frames across the drag
    base = BaselineBlobTracker()
    moved = 0.0
    for f in frames:
        pins, vec = base.process(to_gray(f))
        want = _double_loop_pairs(base.ref, pins)
        assert len(pins) > 100
        assert np.array_equal(base.match(pins), want)
        assert np.array_equal(vec, pins[want] - base.ref)
        moved = max(moved, float(np.abs(vec).max()))
    assert moved > 1.0                               # the frames do move the pins
