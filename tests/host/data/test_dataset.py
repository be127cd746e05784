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
