"""The dataset folder (host/data/dataset.py): written trial by trial, so a crash loses
only the trial being written, and a folder that is not a dataset is a clear error."""
from __future__ import annotations

import numpy as np
import pytest

from host.data import dataset
from host.data.simulate import simulate_to_dataset


def test_a_crash_mid_trial_loses_only_that_trial(tmp_path, monkeypatch):
    out = tmp_path / "ds"
    simulate_to_dataset("no-touch", out, seed=0, progress=False)
    real = dataset.write_npz

    def dying(fh, arrays, level=1):
        real(fh, dict(list(arrays.items())[:2]), level)
        raise KeyboardInterrupt("power cut")

    monkeypatch.setattr(dataset, "write_npz", dying)
    with pytest.raises(KeyboardInterrupt):
        simulate_to_dataset("no-touch", out, seed=1, progress=False)
    monkeypatch.undo()
    files = sorted(p.name for p in out.iterdir())
    assert files == ["dataset.json", "trial_0000.npz"]          # no temp file left behind
    assert len(dataset.read_index(out)["trials"]) == 1
    assert dataset.load_trial(out, 0)["frames"].shape[0] > 0
    simulate_to_dataset("no-touch", out, seed=1, progress=False)   # and it carries on
    assert len(dataset.read_index(out)["trials"]) == 2


def test_reading_a_non_dataset_is_a_clear_error(tmp_path):
    with pytest.raises(dataset.DatasetError, match="not a tacfoot dataset"):
        dataset.read_index(tmp_path)
    (tmp_path / "dataset.json").write_text("{broken")
    with pytest.raises(dataset.DatasetError, match="corrupt index"):
        dataset.read_index(tmp_path)


def test_a_dataset_index_that_is_not_a_table_is_a_dataset_error(tmp_path):
    (tmp_path / "dataset.json").write_text("[]")       
    with pytest.raises(dataset.DatasetError, match="not a tacfoot dataset index"):
        dataset.read_index(tmp_path)


@pytest.mark.parametrize("edit, why", [
    ({"trials": "x"}, r"dataset\.json: trials must be a list of trial entries, got 'x'"),
    ({"trials": [5]}, r"dataset\.json: trials\[0\] must be an entry naming its \.npz file in "
                      r"the folder, got 5"),
    ({"trials": [{"file": "../../etc/passwd.npz"}]}, r"trials\[0\] must be an entry naming"),
    ({"trials": [{"file": "trial_0000.npz", "frames": "many"}]},
     r"trials\[0\]\.frames must be a whole number >= 0, got 'many'"),
    ({"version": "x"}, r"dataset\.json: index version must be a whole number >= 0, got 'x'"),
])
def test_an_index_with_fields_of_the_wrong_type_is_a_dataset_error(tmp_path, edit, why):
    import json
    (tmp_path / "dataset.json").write_text(json.dumps(
        {"format": "tacfoot-dataset", "version": 1, "trials": [], **edit}))
    with pytest.raises(dataset.DatasetError, match=why):
        dataset.read_index(tmp_path)


def test_a_truncated_or_missing_trial_file_is_a_dataset_error_naming_it(tmp_path):
    out = tmp_path / "ds"
    simulate_to_dataset("minimal", out, seed=0, progress=False)
    f = out / "trial_0000.npz"
    whole = f.read_bytes()
    for cut in (100, len(whole) // 2, len(whole) - 30):
        f.write_bytes(whole[:cut])
        with pytest.raises(dataset.DatasetError,
                           match=r"trial_0000\.npz: corrupt or truncated trial file"):
            dataset.load_trial(out, 0)
    f.unlink()
    with pytest.raises(dataset.DatasetError, match=r"trial_0000\.npz: trial file missing"):
        dataset.load_trial(out, 0)


# -- one writer at a time, stale temporary files, sources per trial -----------------

def _frames(n=3):
    return np.zeros((n, 8, 8), np.uint8)


def test_a_second_writer_to_one_folder_is_refused(tmp_path, capsys):
    from host.cli import main
    out = tmp_path / "ds"
    first = dataset.DatasetWriter(out, meta={"source": "simulator"})
    with pytest.raises(dataset.DatasetError, match="another writer"):
        dataset.DatasetWriter(out)
    # host simulate into the folder: exit 2, one line
    rc = main(["simulate", "no-touch", "--out", str(out), "--json"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "another writer" in err and len(err.splitlines()) == 1
    first.add_trial(_frames(), {}, {})
    first.close()
    # once the first writer is done, the next one appends
    with dataset.DatasetWriter(out) as w:
        w.add_trial(_frames(), {}, {})
    assert len(dataset.read_index(out)["trials"]) == 2


_KILLED_WRITER = """
import os, sys
from pathlib import Path
from host.data.dataset import atomic_write
def write(fh):
    fh.write(b"x" * 100000)
    fh.flush()
    if sys.argv[2] == "die":
        os._exit(9)                 # killed mid-write: no clean-up runs
    sys.stdout.write("writing\\n")
    sys.stdout.flush()
    sys.stdin.readline()            # a live writer, still at work
atomic_write(Path(sys.argv[1]) / "trial_0000.npz", write)
"""


def test_the_next_writer_removes_temp_files_of_dead_writers_only(tmp_path):
    import os
    import subprocess
    import sys
    out = tmp_path / "ds"
    out.mkdir()
    env = dict(os.environ, PYTHONPATH=os.getcwd())
    subprocess.run([sys.executable, "-c", _KILLED_WRITER, str(out), "die"], env=env,
                   timeout=60)
    live = subprocess.Popen([sys.executable, "-c", _KILLED_WRITER, str(out), "live"], env=env,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert live.stdout.readline().strip() == "writing"
        assert len(list(out.glob(".*.tmp"))) == 2
        with dataset.DatasetWriter(out) as w:
            # the dead writer's file is gone; the live one's is kept
            left = list(out.glob(".*.tmp"))
            assert len(left) == 1 and str(live.pid) in left[0].name
            assert w.removed_temp_files == 1
    finally:
        live.kill()
        live.wait()
    with dataset.DatasetWriter(out):
        assert list(out.glob(".*.tmp")) == []


def test_sources_are_kept_per_trial_and_a_mixed_folder_says_so(tmp_path):
    out = tmp_path / "ds"
    with dataset.DatasetWriter(out, meta={"source": "simulator"}) as w:
        w.add_trial(_frames(), {}, {})
    assert dataset.read_index(out)["source"] == "simulator"
    # a resumed rig run into the simulator's folder
    with dataset.DatasetWriter(out, meta={"source": "rig"}) as w:
        w.add_trial(_frames(), {}, {})
    idx = dataset.read_index(out)
    assert [t["source"] for t in idx["trials"]] == ["simulator", "rig"]
    assert idx["source"] == "mixed" and idx["sources"] == ["rig", "simulator"]


def test_a_folder_written_before_per_trial_sources_keeps_its_trials_source(tmp_path):
    import json
    out = tmp_path / "ds"
    out.mkdir()
    (out / "dataset.json").write_text(json.dumps(
        {"format": "tacfoot-dataset", "version": 1, "source": "simulator",
         "trials": [{"file": "trial_0000.npz", "frames": 3}]}))
    np.savez_compressed(out / "trial_0000.npz", frames=_frames())
    with dataset.DatasetWriter(out, meta={"source": "rig"}) as w:
        w.add_trial(_frames(), {}, {})
    idx = dataset.read_index(out)
    assert [t["source"] for t in idx["trials"]] == ["simulator", "rig"]
    assert idx["source"] == "mixed"


# -- an index listing a trial twice, or a missing trial file ------------------------

def _two_trials(out):
    with dataset.DatasetWriter(out, meta={"source": "simulator"}) as w:
        w.add_trial(_frames(), {}, {})
        w.add_trial(_frames(), {}, {})


def _edit_index(out, edit):
    import json
    idx = json.loads((out / "dataset.json").read_text())
    edit(idx["trials"])
    (out / "dataset.json").write_text(json.dumps(idx))


def test_a_trial_listed_twice_is_refused_when_read_and_when_appending(tmp_path):
    out = tmp_path / "ds"
    _two_trials(out)
    _edit_index(out, lambda t: t.append(dict(t[0])))
    why = r"1 trial file\(s\) listed twice: trials\[2\] trial_0000\.npz \(also trials\[0\]\)"
    with pytest.raises(dataset.DatasetError, match=why):
        dataset.read_index(out)
    with pytest.raises(dataset.DatasetError, match=why):
        dataset.DatasetWriter(out)
    with dataset.DatasetWriter(tmp_path / "ds2"):    # the refused writer let go of no lock
        pass
    with pytest.raises(dataset.DatasetError, match="listed twice"):   # nor one of out's
        dataset.DatasetWriter(out)


def test_a_missing_trial_file_is_refused_when_read_and_when_appending(tmp_path):
    out = tmp_path / "ds"
    _two_trials(out)
    (out / "trial_0001.npz").unlink()
    why = r"1 listed trial file\(s\) missing from .*: trials\[1\] trial_0001\.npz"
    with pytest.raises(dataset.DatasetError, match=why):
        dataset.read_index(out)
    with pytest.raises(dataset.DatasetError, match=why):
        dataset.DatasetWriter(out)
    assert len(dataset.read_index(out, check_files=False)["trials"]) == 2   # unchanged


def test_write_npz_is_read_back_exactly_by_np_load(tmp_path):
    """A trial's arrays round-trip bit for bit through the level-1 writer, any dtype."""
    arrays = {"frames": np.arange(2 * 6 * 5, dtype=np.uint8).reshape(2, 6, 5),
              "t_s": np.array([0.0, 1 / 120]), "label": np.array(["hard", "soft"]),
              "empty": np.zeros((0, 2), np.float32)}
    with open(tmp_path / "t.npz", "wb") as fh:
        dataset.write_npz(fh, arrays)
    back = np.load(tmp_path / "t.npz")
    assert sorted(back.files) == sorted(arrays)
    for k, v in arrays.items():
        assert back[k].dtype == v.dtype and np.array_equal(back[k], v)


def test_a_new_trial_never_takes_a_name_the_index_lists(tmp_path):
    """An index whose entries were edited down to trial_0001 alone: the next trial is
    not named trial_0001.npz (it would overwrite that trial and list it twice)."""
    out = tmp_path / "ds"
    _two_trials(out)
    _edit_index(out, lambda t: t.pop(0))
    (out / "trial_0000.npz").unlink()
    with dataset.DatasetWriter(out) as w:
        w.add_trial(_frames(5), {}, {})
    idx = dataset.read_index(out)
    assert [t["file"] for t in idx["trials"]] == ["trial_0001.npz", "trial_0002.npz"]
    assert dataset.load_trial(out, 0)["frames"].shape[0] == 3
