"""host analyse (host.cli.analyse): one JSON line per frame, localised pins with
--localiser, the windowed pressure with --pressure."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from device.sim import Simulator, load_scene
from host.cli import main
from tests import REPO_ROOT
from tests.mcapread import read_mcap
from tests.realdata import real_data_dir

LOCALISER = REPO_ROOT / "models" / "localiser-roboskin"
PRESSURE = REPO_ROOT / "models" / "pressure"


def _lines(path):
    return [json.loads(x) for x in path.read_text().splitlines()]


def test_analyse_writes_a_line_per_frame_and_a_summary(tmp_path):
    out = tmp_path / "a.jsonl"
    assert main(["analyse", "sim://drag-90", "--out", str(out)]) == 0
    lines = _lines(out)
    n = Simulator(load_scene("drag-90")).n_frames
    assert len(lines) == n + 1 and lines[-1]["summary"] and lines[-1]["frames"] == n
    frames = lines[:-1]
    assert {"frame", "t", "pins", "contact", "shear_x", "shear_y", "magnitude", "pressure",
            "faults", "timings_ms"} <= set(frames[0])
    assert any(f["contact"] for f in frames) and not frames[-1]["faults"]
    assert lines[-1]["contact_frames"] == sum(f["contact"] for f in frames)
    assert all("localised_px" not in f for f in frames)   # only with --localiser


def _assert_localised(frames, n_pins=133):
    for f in frames:
        pins = np.asarray(f["localised_px"], float)
        assert pins.shape == (n_pins, 2)
        assert np.isfinite(pins).all()
        assert np.array_equal(pins, np.round(pins, 2))


def test_analyse_with_a_localiser_writes_its_pins_on_a_simulated_drag(tmp_path):
    out = tmp_path / "a.jsonl"
    assert main(["analyse", "sim://drag-45", "--localiser", str(LOCALISER),
                 "--out", str(out)]) == 0
    lines = _lines(out)
    frames = lines[:-1]
    assert lines[-1]["summary"] and lines[-1]["frames"] == len(frames)
    _assert_localised(frames)
    # the pins sit on the dome and move with the drag: the mean pin moves by
    # several px between rest and the deepest drag
    rest = np.asarray(frames[5]["localised_px"]).mean(axis=0)
    deepest = max(frames, key=lambda f: f["magnitude"])
    moved = np.asarray(deepest["localised_px"]).mean(axis=0) - rest
    assert np.hypot(*moved) > 3.0
    assert 200 < math.degrees(math.atan2(moved[1], moved[0])) % 360 < 250


def test_analyse_with_a_localiser_on_the_real_smooth_clip(tmp_path):
    clip = real_data_dir("roboskin/smooth.avi") / "roboskin" / "smooth.avi"
    out = tmp_path / "smooth.jsonl"
    assert main(["analyse", str(clip), "--localiser", str(LOCALISER), "--out", str(out)]) == 0
    lines = _lines(out)
    frames = lines[:-1]
    assert len(frames) > 100 and lines[-1]["reference_set"]
    _assert_localised(frames)
    sound = [f for f in frames if "localiser" not in f["faults"]]
    assert len(sound) > 0.9 * len(frames)
    # the localised pins lie inside the frame
    pins = np.asarray([f["localised_px"] for f in sound])
    assert pins[..., 0].min() > 0 and pins[..., 0].max() < 640
    assert pins[..., 1].min() > 0 and pins[..., 1].max() < 480


@pytest.mark.parametrize("name", ["concrete", "smooth"])
def test_analyse_with_the_pressure_model_on_real_clips(tmp_path, name):
    """``host analyse CLIP --pressure models/pressure`` over a whole real clip. The pins
    the pipeline finds in each clip's reference frame differ (about 393 in smooth.avi,
    405 in concrete.avi), so the model must read the runtime's window encoding on the
    profile's fixed layout (798 features), not the per-reference-pin vectors."""
    clip = real_data_dir(f"roboskin/{name}.avi") / "roboskin" / f"{name}.avi"
    out = tmp_path / f"{name}.jsonl"
    assert main(["analyse", str(clip), "--pressure", str(PRESSURE), "--out", str(out)]) == 0
    lines = _lines(out)
    frames = lines[:-1][:40]
    T = json.loads((PRESSURE / "manifest.json").read_text())["T"]
    start = next(i for i, f in enumerate(frames) if "reference_not_set" not in f["faults"])
    assert all(f["pressure"] is None for f in frames[:start])
    full = frames[max(start, T - 1):]
    assert len(full) >= 30
    assert all(isinstance(f["pressure"], float) and math.isfinite(f["pressure"])
               for f in full)
    assert len({f["pressure"] for f in full}) > 1       # it follows the frames
    assert lines[-1]["summary"] and lines[-1]["frames"] == len(lines) - 1


def test_analyse_with_a_missing_model_is_exit_2(tmp_path, capsys):
    assert main(["analyse", "sim://drag-90", "--pressure", str(tmp_path / "none"),
                 "--out", str(tmp_path / "a.jsonl")]) == 2
    assert "host analyse: error" in capsys.readouterr().err


def test_a_calibrated_profile_reads_the_rest_frames_of_its_clip_as_rest(tmp_path):
    """``host calibrate smooth.avi`` (its 16 leading frames, the default), then ``host
    analyse`` of those frames: the 12 that have a reference are the clip's rest, and
    the calibrated profile calls no more of them contact than the default profile."""
    clip = real_data_dir("roboskin/smooth.avi") / "roboskin" / "smooth.avi"
    prof = tmp_path / "smooth.toml"
    assert main(["calibrate", str(clip), "--out", str(prof)]) == 0

    def rest_contact(profile):
        out = tmp_path / "a.jsonl"
        assert main(["analyse", f"file://{clip}?end_frame=16", "--profile", profile,
                     "--out", str(out)]) == 0
        rest = [f for f in _lines(out)[:-1] if "reference_not_set" not in f["faults"]]
        assert len(rest) == 12
        return sum(f["contact"] for f in rest)

    default, calibrated = rest_contact("roboskin"), rest_contact(str(prof))
    assert default <= 1 and calibrated <= default


def test_realism_on_the_users_own_spec_and_profile_names_no_built_in_clip(tmp_path, capsys):
    """``host realism --data my.csv --profile my-sensor.toml`` on renamed slices of the
    real clips: every row measured, a label with no simulated drag scene said so in
    one note, and no built-in clip named anywhere in the output."""
    import shutil
    root = real_data_dir("roboskin/smooth.avi", "roboskin/concrete.avi") / "roboskin"
    (tmp_path / "my_floor.avi").symlink_to(root / "smooth.avi")
    (tmp_path / "my_grit.avi").symlink_to(root / "concrete.avi")
    spec = tmp_path / "my.csv"
    spec.write_text("path,label,start_frame,end_frame\n"
                    f"{tmp_path / 'my_floor.avi'},smooth,0,120\n"
                    f"{tmp_path / 'my_grit.avi'},felt,0,60\n")
    prof = tmp_path / "my-sensor.toml"
    shutil.copy(REPO_ROOT / "device" / "profiles" / "roboskin.toml", prof)
    main(["realism", "--data", str(spec), "--profile", str(prof), "--sim2real-trials", "0",
          "--json"])
    res = json.loads(capsys.readouterr().out)
    assert [(p["recording"], p["label"], p["frames"]) for p in res["pairs"]] == [
        ("my_floor.avi", "smooth", 120), ("my_grit.avi", "felt", 60)]
    floor, grit = res["pairs"]
    assert floor["sim_scene"] == "smooth-drag" and floor["rest_frames"] == 15
    assert [r["figure"] for r in floor["rows"]][-1] == "drag displacement p90 [px]"
    assert grit["sim_scene"] is None and "no simulated scene felt-drag" in grit["notes"][0]
    assert all("drag" not in r["figure"] for r in grit["rows"])
    assert res["profile"] == str(prof)
    text = json.dumps(res)
    for clip in ("smooth.avi", "concrete.avi", "lego_train.avi", "roboskin/"):
        assert clip not in text


def test_realism_with_a_missing_file_or_no_data_is_one_line_and_exit_2(tmp_path, capsys):
    import time
    spec = tmp_path / "my.csv"
    spec.write_text(f"path,label\n{tmp_path / 'gone.avi'},smooth\n")
    t0 = time.perf_counter()
    assert main(["realism", "--data", str(spec)]) == 2
    err = capsys.readouterr().err.strip()
    assert time.perf_counter() - t0 < 5
    assert len(err.splitlines()) == 1 and "gone.avi" in err
    assert main(["realism", "--data", str(spec), "--profile", str(tmp_path / "no.toml")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "no.toml" in err
    assert main(["realism"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "python -m host.bench.specs --real-data" in err


def test_analyse_takes_the_profile_from_its_models_and_refuses_another(tmp_path, capsys):
    """With --pressure the pipeline runs with the model's own profile; a --profile
    that is not the model's is exit 2 naming both (files, pin counts, hashes)."""
    out = tmp_path / "a.jsonl"
    assert main(["analyse", "sim://drag-90?end_frame=12", "--pressure", str(PRESSURE),
                 "--out", str(out)]) == 0
    assert _lines(out)[-1]["profile"] == "roboskin"
    rc = main(["analyse", "sim://drag-90?end_frame=12", "--pressure", str(PRESSURE),
               "--profile", "tactip331", "--out", str(tmp_path / "b.jsonl")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1
    assert "tactip331.toml (tactip331, 331 pins" in err and "pressure/manifest.json" in err
    assert "(roboskin, 133 pins" in err


def test_analyse_mcap_writes_the_leg_channels_a_message_per_frame_at_its_time(tmp_path):
    pytest.importorskip("mcap")
    from device.pi.runtime.mcaplog import CHANNELS
    out, log = tmp_path / "a.jsonl", tmp_path / "a.mcap"
    assert main(["analyse", "sim://drag-90", "--out", str(out), "--mcap", str(log),
                 "--mcap-image-every", "3"]) == 0
    lines = _lines(out)
    frames, summary = lines[:-1], lines[-1]
    chans, msgs = read_mcap(log)
    assert {t: CHANNELS[t]["title"] for t in CHANNELS} == {t: chans[t] for t in CHANNELS}
    assert chans["/tacfoot/analyse"] == "tacfoot.AnalyseFrame"
    n = len(frames)
    for topic in ("/tacfoot/latency", "/tacfoot/analyse"):
        assert [d["frame"] for _, d in msgs[topic]] == [f["frame"] for f in frames], topic
    assert len(msgs["/tacfoot/grid"]) == n                   # foxglove.Grid: no frame field
    assert len(msgs["/tacfoot/image"]) == len(msgs["/tacfoot/pins"]) == -(-n // 3)
    assert [d for _, d in msgs["/tacfoot/analyse"]] == frames        # the same lines
    for (t_ns, _), f in zip(msgs["/tacfoot/grid"], frames):
        assert abs(t_ns - f["t"] * 1e9) <= 1e3                       # the frame's time, ns
    assert [t for t, _ in msgs["/tacfoot/image"]] == [t for t, _ in msgs["/tacfoot/grid"]][::3]
    assert all(d["latency_ms"] is None and d["pipeline_ms"] > 0
               for _, d in msgs["/tacfoot/latency"])
    assert summary["mcap"]["messages"] == sum(len(v) for v in msgs.values())


def test_analyse_mcap_refuses_a_bad_file_before_it_starts(tmp_path, capsys):
    pytest.importorskip("mcap")
    rc = main(["analyse", "sim://drag-90", "--out", str(tmp_path / "a.jsonl"), "--mcap",
               str(tmp_path / "nope" / "a.mcap")])
    assert rc == 2 and "does not exist" in capsys.readouterr().err
    assert not (tmp_path / "a.jsonl").exists()
    rc = main(["analyse", "sim://drag-90", "--mcap", str(tmp_path / "b.mcap"),
               "--mcap-image-every", "0"])
    assert rc == 2 and "--mcap-image-every" in capsys.readouterr().err


def test_analyse_names_itself_in_its_mcap_warning(tmp_path, capsys, monkeypatch):
    """A write the disk refuses is warned about as ``host analyse``, not as the leg's
    runtime (issue 29, item 15)."""
    pytest.importorskip("mcap")
    import errno

    from device.pi.runtime import mcaplog
    real, n = mcaplog._CountingFile.write, [0]

    def write(self, data):
        n[0] += 1
        if n[0] > 2:                              # magic and header land, then the disk fills
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, data)
    monkeypatch.setattr(mcaplog._CountingFile, "write", write)
    rc = main(["analyse", "sim://drag-90", "--out", str(tmp_path / "a.jsonl"), "--mcap",
               str(tmp_path / "a.mcap")])
    err = capsys.readouterr().err
    warn = [x for x in err.splitlines() if "warning" in x]
    assert len(warn) == 1 and warn[0].startswith("host analyse: warning: --mcap"), err
    assert "device.pi run" not in err
    assert rc == 2 and "messages could not be written" in err
