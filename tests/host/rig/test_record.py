"""host record (host.rig.record): a labelled dataset from any camera without the rig,
written atomically and read back by the dataset loader."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from host.cli import main
from host.data.dataset import load_trial, read_index
from host.data.load import load_spec
from tests.realdata import real_data_dir


def test_record_from_the_simulator_appends_labelled_trials(tmp_path, capsys):
    out = tmp_path / "ds"
    assert main(["record", "--camera", "sim://drag-90", "--imu", "sim://drag-90",
                 "--label", "hard", "--seconds", "0.5", "--out", str(out), "--json"]) == 0
    first = json.loads(capsys.readouterr().out)
    assert main(["record", "--camera", "sim://press-soft", "--label", "soft",
                 "--seconds", "0.25", "--out", str(out)]) == 0
    idx = read_index(out)
    assert idx["source"] == "record" and idx["record_labels"] == ["hard", "soft"]
    assert [t["label"] for t in idx["trials"]] == ["hard", "soft"]
    t0 = load_trial(out, 0)
    assert t0["frames"].shape[0] == first["frames"] == 60          # 0.5 s at 120 fps
    assert t0["imu"].shape == (60, 6) and np.isfinite(t0["imu"]).all()
    assert (t0["surface"] == 0).all() and (load_trial(out, 1)["surface"] == 1).all()
    assert np.all(np.diff(t0["t_s"]) > 0)
    assert not list(out.glob("*.tmp")) and not list(out.glob(".*tmp"))


def test_record_into_a_folder_another_writer_holds_is_refused(tmp_path, capsys):
    from host.data.dataset import DatasetWriter
    out = tmp_path / "ds"
    with DatasetWriter(out, source="record"):
        rc = main(["record", "--camera", "sim://press-soft", "--label", "soft",
                   "--seconds", "0.1", "--out", str(out)])
        err = capsys.readouterr().err.strip()
    assert rc == 2 and "another writer" in err and len(err.splitlines()) == 1
    assert not (out / "dataset.json").exists() and not list(out.glob(".*tmp"))


def test_a_recorded_real_clip_trains_like_the_clip_itself(tmp_path):
    """The real clips as file sources: the recorded trials load as windows with
    contact from the pipeline, the same windows as a CSV manifest of the clips."""
    clips = real_data_dir("roboskin/smooth.avi", "roboskin/concrete.avi") / "roboskin"
    out = tmp_path / "ds"
    # no --imu: smooth.avi has no gyro file, and a folder mixing trials with and
    # without an IMU is refused (host.data.spec_folder)
    assert main(["record", "--camera", str(clips / "concrete.avi"), "--label", "concrete",
                 "--seconds", "1.5", "--out", str(out)]) == 0
    assert main(["record", "--camera", str(clips / "smooth.avi"), "--label", "smooth",
                 "--seconds", "1.5", "--out", str(out)]) == 0
    ws = load_spec(str(out), "texture", 3, contact_only=True, progress=False)
    assert set(ws.labels) == {"concrete", "smooth"}
    assert ws.source["contact_from"] == ["pipeline"]
    man = tmp_path / "clips.csv"
    man.write_text(f"path,label,start_frame,end_frame\n{clips / 'concrete.avi'},concrete,0,"
                   f"{load_trial(out, 0)['frames'].shape[0]}\n")
    ref = load_spec(str(man), "texture", 3, contact_only=True, progress=False, min_classes=1)
    n0 = int((ws.groups == ws.groups[0]).sum())
    assert n0 == len(ref)
    assert np.array_equal(ws.vectors[:n0], ref.vectors)


def test_record_refuses_bad_input_with_one_line(tmp_path, capsys):
    assert main(["record", "--camera", "sim://drag-90", "--label", "no touch!",
                 "--seconds", "1", "--out", str(tmp_path / "a")]) == 2
    assert "--label" in capsys.readouterr().err
    assert main(["record", "--camera", "sim://drag-90", "--label", "x",
                 "--seconds", "-1", "--out", str(tmp_path / "a")]) == 2
    assert "--seconds" in capsys.readouterr().err
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    assert main(["record", "--camera", "sim://drag-90", "--label", "x", "--seconds", "0.1",
                 "--out", str(tmp_path / "other")]) == 2
    assert "not a tacfoot dataset" in capsys.readouterr().err


def test_a_failed_recording_leaves_the_dataset_as_it_was(tmp_path, capsys):
    folder = tmp_path / "imgs"
    folder.mkdir()
    for i, size in enumerate([(40, 40)] * 3 + [(50, 40)]):
        cv2.imwrite(str(folder / f"f{i}.png"), np.full(size, 100, np.uint8))
    out = tmp_path / "ds"
    assert main(["record", "--camera", "sim://drag-90", "--label", "a", "--seconds", "0.1",
                 "--out", str(out)]) == 0
    before = sorted(p.name for p in out.iterdir())
    assert main(["record", "--camera", str(folder), "--label", "b", "--seconds", "10",
                 "--out", str(out)]) == 2
    assert "first is 40x40" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == before
    assert len(read_index(out)["trials"]) == 1


def test_record_adds_to_a_folder_a_stopped_writer_left_only_temporary_files_in(tmp_path):
    """The folder rule is the dataset writer's: a folder holding only a stopped
    writer's temporary files is taken (the command line accepts it too)."""
    from device.pi.sources.camera import open_camera
    from host.data.dataset import is_dataset
    from host.rig.record import record

    out = tmp_path / "ds"
    out.mkdir()
    (out / ".record.pid99999.abc.tmp").write_bytes(b"partial")
    with open_camera("sim://press-soft") as cam:
        entry = record(cam, None, "hard", 0.05, out)
    assert entry["label"] == "hard" and is_dataset(out)


def test_record_start_and_frames_are_frame_exact_and_exclusive_of_seconds(tmp_path, capsys):
    """--start K --frames N records exactly frames K .. K+N-1 of the source; the
    trial names its recording and profile; --seconds with --frames is refused, and a
    source shorter than asked adds nothing."""
    from device.pi.sources.camera import open_camera
    out = tmp_path / "ds"
    assert main(["record", "--camera", "sim://press-soft", "--label", "soft",
                 "--start", "7", "--frames", "13", "--out", str(out)]) == 0
    t = load_trial(out, 0)
    assert t["frames"].shape[0] == 13
    with open_camera("sim://press-soft", start_frame=7, end_frame=8) as cam:
        first = next(iter(cam)).image
    first = cv2.cvtColor(first, cv2.COLOR_BGR2GRAY) if first.ndim == 3 else first
    assert np.array_equal(t["frames"][0], first)
    e = read_index(out)["trials"][0]
    assert e["recording"]["id"] == "simulated:press-soft seed 0"
    assert e["recording"]["start_frame"] == 7
    assert e["profile"] == "roboskin" and len(e["profile_sha256"]) == 64
    capsys.readouterr()
    assert main(["record", "--camera", "sim://press-soft", "--label", "soft",
                 "--seconds", "1", "--frames", "5", "--out", str(out)]) == 2
    assert "not both" in capsys.readouterr().err
    assert main(["record", "--camera", "sim://press-soft", "--label", "soft",
                 "--start", "90", "--frames", "50", "--out", str(out)]) == 2
    assert "ends after" in capsys.readouterr().err
    assert len(read_index(out)["trials"]) == 1


def _source_frames(clip, start: int, n: int) -> np.ndarray:
    from device.pi.sources.camera import open_camera
    with open_camera(str(clip), start_frame=start, end_frame=start + n) as cam:
        return np.stack([cv2.cvtColor(f.image, cv2.COLOR_BGR2GRAY) for f in cam])


def test_a_recorded_clip_is_stored_compactly_and_loads_frame_exact(tmp_path):
    """A trial of 10 % of a real clip, starting 11 frames after a keyframe (the most
    lead-in roboskin's 12-frame keyframe interval allows), stores the remuxed packets:
    at most 2x the source's bytes for those frames (the frame array took 13x), and it
    loads as exactly the frames read from the source. Its stored clip starts at the
    keyframe, and video_range says which of its frames is the trial's first. A trial
    shorter than its lead-in stores the frame array and says why."""
    clip = real_data_dir("roboskin/smooth.avi") / "roboskin" / "smooth.avi"
    total = 540
    out = tmp_path / "ds"
    assert main(["record", "--camera", str(clip), "--label", "smooth", "--start", "131",
                 "--frames", "54", "--out", str(out)]) == 0
    assert main(["record", "--camera", str(clip), "--label", "smooth", "--start", "5",
                 "--frames", "4", "--out", str(out)]) == 0
    e = read_index(out)["trials"]
    assert e[0]["frames_codec"] == "source-video" and "frames_note" not in e[0]
    size = (out / e[0]["file"]).stat().st_size
    assert size == e[0]["bytes"] <= 2 * clip.stat().st_size * 54 / total
    with np.load(out / e[0]["file"]) as z:
        assert z["video_range"].tolist() == [11, 65]
    assert np.array_equal(load_trial(out, 0)["frames"], _source_frames(clip, 131, 54))
    assert e[1]["frames_codec"] == "npz" and "under half" in e[1]["frames_note"]
    assert np.array_equal(load_trial(out, 1)["frames"], _source_frames(clip, 5, 4))


def test_a_clip_that_does_not_decode_to_the_frames_read_is_stored_as_frames(tmp_path,
                                                                           monkeypatch):
    """The stored clip is checked on write: a remux that is off by one frame is not
    kept; the trial stores the frame array, loads exactly, and its entry says why."""
    import host.rig.record as rec
    clip = real_data_dir("roboskin/smooth.avi") / "roboskin" / "smooth.avi"
    real = rec.remux_clip

    def off_by_one(video, start, n, folder):
        path, first = real(video, start, n + 1, folder)
        return path, first + 1
    monkeypatch.setattr(rec, "remux_clip", off_by_one)
    out = tmp_path / "ds"
    assert main(["record", "--camera", str(clip), "--label", "smooth", "--start", "20",
                 "--frames", "30", "--out", str(out)]) == 0
    e = read_index(out)["trials"][0]
    assert e["frames_codec"] == "npz" and "not decode to exactly" in e["frames_note"]
    assert np.array_equal(load_trial(out, 0)["frames"], _source_frames(clip, 20, 30))


def test_without_pyav_a_trial_of_most_of_a_clip_stores_the_whole_file(tmp_path, monkeypatch):
    """Without PyAV a trial covering at least half of the clip stores the file's own
    bytes, and its entry says the clip was not remuxed."""
    import sys
    clip = real_data_dir("roboskin/lego_train.avi") / "roboskin" / "lego_train.avi"
    monkeypatch.setitem(sys.modules, "av", None)          # import av fails
    out = tmp_path / "ds"
    assert main(["record", "--camera", str(clip), "--label", "lego", "--start", "10",
                 "--frames", "200", "--out", str(out)]) == 0
    e = read_index(out)["trials"][0]
    assert e["frames_codec"] == "source-video" and "PyAV" in e["frames_note"]
    assert e["bytes"] <= 2 * clip.stat().st_size
    assert np.array_equal(load_trial(out, 0)["frames"], _source_frames(clip, 10, 200))


def _mjpg(path, n: int, size=(32, 24), fps: float = 120.0):
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, size)
    for k in range(n):
        vw.write(np.full((size[1], size[0], 3), (7 * k) % 250, np.uint8))
    vw.release()
    return path


def _vfr_mkv(tmp_path, n: int = 100):
    """An MJPG Matroska file of ``n`` frames 20 ms and 5 ms apart by turns (its own
    times, in ms: 0, 20, 25, 45, ...), for which OpenCV estimates 249 frames."""
    import fractions

    import av
    src = _mjpg(tmp_path / "cfr.avi", n)
    dst = tmp_path / "vfr.mkv"
    ms = fractions.Fraction(1, 1000)
    with av.open(str(src)) as ic, av.open(str(dst), "w") as oc:
        out = oc.add_stream_from_template(ic.streams.video[0])
        out.time_base = ms
        t = 0
        for i, p in enumerate(q for q in ic.demux(ic.streams.video[0]) if q.size):
            p.stream, p.time_base, p.pts, p.dts = out, ms, t, t
            oc.mux(p)
            t += 5 if i % 2 else 20
    return dst, np.cumsum([0] + [5 if i % 2 else 20 for i in range(n - 1)]) / 1000.0


def test_record_reads_no_further_into_the_source_than_the_frames_asked_for(tmp_path,
                                                                          monkeypatch):
    """--start 5 --frames 10 of a 300-frame file: every PyAV read of the source stops
    within a reorder window after frame 14 (the whole file's packets were read into
    memory: 10 frames of a 297 MB MJPG peaked at 425 MB), and the trial is exact."""
    import av

    from host.data.video import REORDER_PACKETS
    src = _mjpg(tmp_path / "long.avi", 300)
    real_open = av.open
    reads: list[int] = []

    class Counted:
        def __init__(self, c):
            self.c = c

        def __getattr__(self, name):
            return getattr(self.c, name)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return self.c.__exit__(*exc)

        def demux(self, *a, **k):
            reads.append(0)
            for p in self.c.demux(*a, **k):
                reads[-1] += 1
                yield p

    def counting_open(file, *a, **k):
        c = real_open(file, *a, **k)
        return Counted(c) if str(file) == str(src) else c
    monkeypatch.setattr(av, "open", counting_open)
    out = tmp_path / "ds"
    assert main(["record", "--camera", str(src), "--label", "x", "--start", "5",
                 "--frames", "10", "--out", str(out)]) == 0
    assert reads and max(reads) <= 15 + REORDER_PACKETS + 1, reads
    assert np.array_equal(load_trial(out, 0)["frames"], _source_frames(src, 5, 10))


def test_a_variable_rate_file_keeps_its_own_frame_times(tmp_path, capsys):
    """A file whose frames are 20 and 5 ms apart by turns keeps those times in t_s
    (they were put on a uniform 1/200 s grid with no note), and its entry says whose
    times they are; a file recorded without PyAV says in one line and in the entry
    that t_s is on the declared rate's grid."""
    clip, want = _vfr_mkv(tmp_path)
    out = tmp_path / "ds"
    assert main(["record", "--camera", str(clip), "--label", "x", "--start", "3",
                 "--frames", "40", "--out", str(out)]) == 0
    t = load_trial(out, 0)
    assert np.allclose(t["t_s"], want[3:43] - want[3], atol=1e-9), t["t_s"][:6]
    assert "own" in t["info"]["timestamps"]


def test_record_without_pyav_warns_that_times_are_on_a_grid(tmp_path, capsys, monkeypatch):
    import sys
    clip, _ = _vfr_mkv(tmp_path)
    monkeypatch.setitem(sys.modules, "av", None)
    out = tmp_path / "ds"
    assert main(["record", "--camera", str(clip), "--label", "x", "--frames", "10",
                 "--out", str(out)]) == 0
    err = [x for x in capsys.readouterr().err.splitlines() if "frame times" in x]
    assert len(err) == 1 and "uniform grid" in err[0] and "PyAV" in err[0]
    assert load_trial(out, 0)["info"]["timestamps"].startswith("uniform at 200 frames/s")


def test_how_a_trial_is_stored_follows_the_frames_counted_not_opencvs_estimate(
        tmp_path, monkeypatch):
    """60 of a 100-frame file (OpenCV estimates 249) are more than half of it: the
    trial keeps the file's bytes (it stored the frame array, "under half of the
    video's 249")."""
    import host.rig.record as rec
    from host.data.video import count_frames
    clip, _ = _vfr_mkv(tmp_path)
    cap = cv2.VideoCapture(str(clip))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) != 100       # the estimate is wrong
    cap.release()
    assert count_frames(clip, 10_000) == 100 and count_frames(clip, 30) == 30
    monkeypatch.setattr(rec, "remux_clip", lambda *a: "no remux: for this test")
    out = tmp_path / "ds"
    assert main(["record", "--camera", str(clip), "--label", "x", "--start", "20",
                 "--frames", "60", "--out", str(out)]) == 0
    e = read_index(out)["trials"][0]
    assert e["frames_codec"] == "source-video", e.get("frames_note")
    assert np.array_equal(load_trial(out, 0)["frames"], _source_frames(clip, 20, 60))


def _dead_pid() -> int:
    import subprocess
    import sys
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_a_killed_records_temporary_copies_are_removed_by_the_next_run(tmp_path,
                                                                       monkeypatch):
    """record keeps its clip copy in --out under a writer's temporary name, and
    nothing in the system's temp folder; reading a stored video uses a temp folder
    named by its process. A temporary of a process that is gone (what a SIGKILL left)
    is removed by the next run, in --out and in the temp folder; a live process's
    stays."""
    import os
    import tempfile

    from host.data.dataset import decode_video
    systmp = tmp_path / "systmp"
    systmp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(systmp))
    dead, live = _dead_pid(), os.getppid()
    out = tmp_path / "ds"
    out.mkdir()
    for pid in (dead, live):
        for d in (out / f".clip.pid{pid}.ab12.tmp", systmp / f"tacfoot-video-pid{pid}-cd34"):
            d.mkdir()
            (d / "clip.avi").write_bytes(b"partial")
    src = _mjpg(tmp_path / "c.avi", 12)
    assert main(["record", "--camera", str(src), "--label", "x", "--frames", "8",
                 "--out", str(out)]) == 0
    assert read_index(out)["trials"][0]["frames_codec"] == "source-video"
    assert not (out / f".clip.pid{dead}.ab12.tmp").exists()
    assert (out / f".clip.pid{live}.ab12.tmp" / "clip.avi").exists()
    assert sorted(p.name for p in systmp.iterdir()) == sorted(      # record made none
        [f"tacfoot-video-pid{dead}-cd34", f"tacfoot-video-pid{live}-cd34"])
    got = decode_video(src.read_bytes(), ".avi", 2, 5)             # as load_trial does
    assert got.shape == (3, 24, 32)
    assert [p.name for p in systmp.iterdir()] == [f"tacfoot-video-pid{live}-cd34"]
