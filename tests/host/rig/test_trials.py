"""Running rig trials (host/rig/trials.py): trial files checked before anything moves,
alignment onto the frames, and hardware-in-the-loop through ``--rig sim://`` (the
firmware behind a pty, pyserial on the other end) all the way to a trained and
evaluated model, with a link drop, a resume and a failed command."""
from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from host.rig import link as rig_link
from host.cli import main as host_main
from host.rig.plan import Plate, RigLimits, Trial, Variant
from host.rig.trials import align
from tests import REPO_ROOT

ROOT = REPO_ROOT
TRIALS = ROOT / "trials"


def test_a_bad_trial_file_is_refused_before_anything_moves(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text('[[plates]]\nname = "hard"\nsurface = "hard"\n'
                   '[[actions]]\naction = "press"\ndepths_mm = [2, 35]\n')
    out = tmp_path / "ds"
    rc = host_main(["rig", "run", str(bad), "--rig", "sim://", "--camera", "sim://",
                    "--out", str(out)])
    assert rc == 2
    err = capsys.readouterr().err
    assert "actions[0].depths_mm[1]" in err and "35" in err
    assert not out.exists()                            # nothing was started


# -- alignment never gives NaN ------------------------------------------------------------------
_trial = Trial("t/hard/press/r000", Plate("hard", "hard", "smooth", "hard"),
               Variant("press", "press", depth_mm=1.0), 0)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(0, 5), st.floats(-50, 50), st.floats(-10, 10),
                          st.floats(-5, 30)), min_size=2, max_size=30),
       st.lists(st.floats(-1, 6), min_size=2, max_size=30), st.floats(-1e6, 1e6))
def test_alignment_gives_finite_truth_for_any_samples(rows, t_frames, offset_ms):
    samples = [rig_link.Sample(t * 1000.0 + offset_ms, 0.0, z, x, ld, (0, 0, 1, 0, 0, 0), 0, 0)
               for t, z, x, ld in rows]
    tf = np.sort(np.asarray(t_frames))
    if np.unique(tf).size < 2:
        tf = np.array([0.0, 0.1])
    truth = align(samples, tf, offset_ms, _trial, RigLimits())
    for k, v in truth.items():
        assert np.all(np.isfinite(np.asarray(v, float))), k
    assert np.all(truth["load_n"] >= 0)
    assert np.array_equal(truth["contact"], truth["load_n"] >= 0.5)
    assert set(np.unique(truth["surface"])) <= {0, 1}


# -- hardware in the loop, end to end -------------------------------------------------------------
def _dataset_ids(out: Path) -> list:
    return [e["trial_id"] for e in json.loads((out / "dataset.json").read_text())["trials"]]


def test_sim_rig_to_dataset_to_model(tmp_path, capsys):
    out = tmp_path / "ds"
    t0 = time.monotonic()
    rc = host_main(["rig", "run", str(TRIALS / "sim-smoke.toml"), "--rig", "sim://",
                    "--camera", "sim://?fps=30", "--out", str(out), "--json"])
    s = json.loads(capsys.readouterr().out)
    assert rc == 0, s
    assert s["done"] == 8 and s["failed"] == [] and s["remaining"] == 0
    assert math.isfinite(s["clock"]["offset_ms"]) and s["clock"]["rtt_ms"] < 50
    assert time.monotonic() - t0 < 40
    from host.data.dataset import load_trial, read_index
    idx = read_index(out)
    assert idx["source"] == "rig" and len(idx["trials"]) == 8
    hard = load_trial(out, 0)                          # hard plate, 1.5 mm press
    assert hard["frames"].dtype == np.uint8 and hard["frames"].shape[1:] == (480, 640)
    assert 3.0 < hard["load_n"].max() < 4.5            # Hertz at 1.5 mm on the hard plate
    assert hard["contact"].any() and not hard["contact"].all()
    assert set(np.unique(hard["surface"])) == {0, 1}
    assert np.all(np.diff(hard["t_s"]) > 0)
    drag = [load_trial(out, i) for i, e in enumerate(idx["trials"]) if "drag" in e["variant"]]
    assert all(abs(d["rig_x_mm"].min() + 4.0) < 0.1 and d["slip"].any() for d in drag)
    soft = [load_trial(out, i) for i, e in enumerate(idx["trials"]) if e["plate"] == "foam"]
    assert all(set(np.unique(d["surface"])) == {0, 2} for d in soft)
    # the camera saw what the rig did: pins move with the load
    f = hard["frames"].astype(np.int16)
    moved = np.abs(f - f[0]).mean(axis=(1, 2))
    assert moved[np.argmax(hard["load_n"])] > 3 * moved[1] + 0.5

    model = tmp_path / "model"
    assert host_main(["train", "--task", "pressure", "--model", "ridge", "--window", "1",
                      "--data", str(out), "--out", str(model), "--json"]) == 0
    tr = json.loads(capsys.readouterr().out)
    assert tr["metrics"]["test"]["mae"] < 0.6 * tr["metrics"]["test"]["mae_predict_mean"]
    assert host_main(["eval", str(model), "--data", str(out), "--json"]) == 0
    ev = json.loads(capsys.readouterr().out)
    assert ev["n_windows"] > 50
    assert ev["metrics"]["mae"] < 0.5 * ev["metrics"]["mae_predict_mean"]

    # without --resume, an existing dataset is not silently appended to
    assert host_main(["rig", "run", str(TRIALS / "sim-smoke.toml"), "--rig", "sim://",
                      "--camera", "sim://", "--out", str(out)]) == 2
    assert "--resume" in capsys.readouterr().err


def test_link_drop_mid_trial_then_resume(tmp_path, capsys):
    trials = tmp_path / "drop.toml"
    trials.write_text('name = "drop"\nrepetitions = 1\n'
                      '[[plates]]\nname = "hard"\nsurface = "hard"\n'
                      '[[actions]]\naction = "press"\ndepths_mm = [1.0, 2.0, 1.5]\n'
                      'press_speed_mm_s = 2\nhold_s = 0.1\n')
    out = tmp_path / "ds"
    rc = host_main(["rig", "run", str(trials), "--rig", "sim://?drop_at_press=2&drop_s=2",
                    "--camera", "sim://?fps=30", "--out", str(out), "--json"])
    s = json.loads(capsys.readouterr().out)
    assert rc == 1
    assert [f["trial"] for f in s["failed"]] == ["drop/hard/press-2mm/r000"]
    assert "link lost" in s["failed"][0]["reason"]
    assert s["sim"]["firmware_link_lost_stops"] >= 1   # the firmware stopped the motors
    assert s["reconnects"] == 1 and s["done"] == 2
    assert _dataset_ids(out) == ["drop/hard/press-1mm/r000", "drop/hard/press-1.5mm/r000"]
    state = json.loads((out / "rig_run.json").read_text())
    assert list(state["failed"]) == ["drop/hard/press-2mm/r000"]

    rc = host_main(["rig", "run", str(trials), "--rig", "sim://", "--camera", "sim://?fps=30",
                    "--out", str(out), "--resume", "--json"])
    s = json.loads(capsys.readouterr().out)
    assert rc == 0 and s["done"] == 1 and s["done_before"] == 2 and s["failed"] == []
    assert sorted(_dataset_ids(out)) == sorted(["drop/hard/press-1mm/r000",
                                                "drop/hard/press-2mm/r000",
                                                "drop/hard/press-1.5mm/r000"])
    assert json.loads((out / "rig_run.json").read_text())["failed"] == {}


def test_a_rig_that_cannot_be_opened_is_a_clear_error_and_writes_nothing(tmp_path, capsys):
    out = tmp_path / "ds"
    rc = host_main(["rig", "run", str(TRIALS / "sim-smoke.toml"), "--rig",
                    str(tmp_path / "ttyACM9"), "--camera", "v4l2:///dev/video0", "--out", str(out)])
    assert rc == 2
    err = capsys.readouterr().err
    assert "--rig" in err and "ttyACM9" in err and "cannot open" in err
    assert not out.exists()


def test_a_failed_command_fails_only_its_trial_with_the_reason(tmp_path, capsys):
    trials = tmp_path / "limit.toml"
    trials.write_text('name = "lim"\n[rig]\nsurface_mm = 38\n'
                      '[[plates]]\nname = "foam"\nsurface = "soft"\n'
                      '[[actions]]\naction = "drag"\ndirections = ["centre"]\n'
                      'loads_n = [0.3, 10]\npress_speed_mm_s = 10\nhold_s = 0.05\n')
    out = tmp_path / "ds"
    rc = host_main(["rig", "run", str(trials), "--rig", "sim://", "--camera", "sim://?fps=30",
                    "--out", str(out), "--json"])
    s = json.loads(capsys.readouterr().out)
    assert rc == 1 and s["done"] == 1
    # 10 N on foam needs ~9 mm past the surface; only 2 mm of travel are left
    assert [f["trial"] for f in s["failed"]] == ["lim/foam/drag-centre-10N/r000"]
    assert "limit" in s["failed"][0]["reason"]
    assert _dataset_ids(out) == ["lim/foam/drag-centre-0.3N/r000"]


def test_resume_into_a_simulator_dataset_keeps_each_trials_source(tmp_path, capsys):
    from host.data.dataset import read_index
    from host.data.simulate import simulate_to_dataset
    plan = tmp_path / "one.toml"
    plan.write_text('name = "one"\nrepetitions = 1\n[[plates]]\nname = "hard"\n'
                    'surface = "hard"\n[[actions]]\naction = "press"\ndepths_mm = [1.0]\n'
                    'press_speed_mm_s = 10\nhold_s = 0.1\n')
    out = tmp_path / "ds"
    simulate_to_dataset("no-touch", out, progress=False)
    rc = host_main(["rig", "run", str(plan), "--rig", "sim://", "--camera", "sim://?fps=30",
                    "--out", str(out), "--resume", "--json"])
    assert rc == 0, capsys.readouterr().err
    idx = read_index(out)
    assert [t["source"] for t in idx["trials"]] == ["simulator", "rig"]
    assert idx["source"] == "mixed" and idx["sources"] == ["rig", "simulator"]


def test_a_second_rig_run_into_a_folder_being_written_is_refused(tmp_path, capsys):
    from host.data.dataset import DatasetWriter
    out = tmp_path / "ds"
    with DatasetWriter(out, source="simulator"):
        rc = host_main(["rig", "run", str(TRIALS / "sim-smoke.toml"), "--rig", "sim://",
                        "--camera", "sim://?fps=30", "--out", str(out)])
        err = capsys.readouterr().err.strip()
    assert rc == 2 and "another writer" in err and len(err.splitlines()) == 1
