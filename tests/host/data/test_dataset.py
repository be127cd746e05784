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
    real = np.savez_compressed

    def dying(fh, **arrays):
        real(fh, **{k: v for k, v in list(arrays.items())[:2]})
        raise KeyboardInterrupt("power cut")

    monkeypatch.setattr(np, "savez_compressed", dying)
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
