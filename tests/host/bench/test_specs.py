"""host/bench/specs.py: every file of a data spec is checked before the long work,
the recordings a spec lists, and the authors' default specs written from the
real-data folder (the only place their clip names live)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from host.bench import specs
from host.data.windows import DataError


def test_a_manifest_lists_its_recordings_and_names_the_first_missing_file(tmp_path):
    (tmp_path / "a.avi").write_bytes(b"")
    (tmp_path / "g.npy").write_bytes(b"")
    (tmp_path / "ok.csv").write_text("path,label,imu\na.avi,lego,g.npy\n")
    recs = specs.recordings(tmp_path / "ok.csv")
    assert [(r.kind, r.name, r.label, r.imu) for r in recs] == [
        ("clip", "a.avi", "lego", str(tmp_path / "g.npy"))]
    (tmp_path / "bad.csv").write_text("path,label\na.avi,lego\nb.avi,smooth\n")
    with pytest.raises(DataError, match=r"bad\.csv row 2 .*no such file or folder: .*b\.avi"):
        specs.check_specs([tmp_path / "ok.csv", tmp_path / "bad.csv"])
    with pytest.raises(DataError, match=r"no such data spec: .*nope\.csv"):
        specs.check_specs([tmp_path / "nope.csv"])
    with pytest.raises(DataError, match="no data specs"):
        specs.check_specs([])


def test_a_dataset_folder_lists_its_trials_and_names_a_missing_one(tmp_path):
    d = tmp_path / "own"
    d.mkdir()
    np.savez(d / "trial_0000.npz", frames=np.zeros((5, 8, 8), np.uint8))
    index = {"format": "tacfoot-dataset", "version": 1,
             "trials": [{"file": "trial_0000.npz", "frames": 5}]}
    (d / "dataset.json").write_text(json.dumps(index))
    try:
        recs = specs.recordings(d)
    except DataError as exc:                          # the index format is the dataset's
        pytest.skip(f"hand-written index refused: {exc}")
    assert [(r.kind, r.name, r.end) for r in recs] == [("trial", "own/trial 0", 5)]
    assert len(specs.recording_frames(recs[0])) == 5
    index["trials"].append({"file": "trial_0001.npz", "frames": 5})
    (d / "dataset.json").write_text(json.dumps(index))
    with pytest.raises(DataError, match="trial_0001.npz"):
        specs.recordings(d)
    (tmp_path / "plain").mkdir()
    with pytest.raises(DataError, match="must be a dataset folder"):
        specs.recordings(tmp_path / "plain")


def test_check_profile_names_a_missing_or_unknown_profile(tmp_path):
    assert specs.check_profile("tactip331") == "tactip331"
    with pytest.raises(DataError, match=r"--profile: no such file: .*mine\.toml"):
        specs.check_profile(str(tmp_path / "mine.toml"))
    with pytest.raises(DataError, match="--profile nosuch"):
        specs.check_profile("nosuch")


def test_the_default_specs_are_written_from_the_real_data_folder_only(tmp_path, capsys):
    root = tmp_path / "data" / "roboskin"
    root.mkdir(parents=True)
    for f in ("lego_train.avi", "smooth.avi", "concrete.avi", "concrete_gyro.npy"):
        (root / f).write_bytes(b"")
    written = specs.write_default_specs(tmp_path / "data", tmp_path / "specs")
    assert sorted(written) == sorted(specs.DEFAULT_SPECS)
    bench = specs.recordings(written["bench"])
    assert [r.name for r in bench] == ["smooth.avi", "concrete.avi"]
    assert bench[1].imu == str(root / "concrete_gyro.npy") and bench[0].imu is None
    (root / "smooth.avi").unlink()
    assert specs.main(["--real-data", str(tmp_path / "data"), "--out",
                       str(tmp_path / "s2")]) == 2
    assert "no such file" in capsys.readouterr().err
