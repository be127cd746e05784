"""Fixtures for the host/data tests: a small simulated dataset folder, a shared
feature cache, and helpers to write manifests and check time splits."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from host.data.simulate import simulate_to_dataset


@pytest.fixture(scope="session")
def sim_ds(tmp_path_factory):
    """A dataset folder: press-hard (seeds 0, 1) and press-soft (seed 0), 96 frames each."""
    out = tmp_path_factory.mktemp("data") / "ds"
    simulate_to_dataset("press-hard", out, seed=0, trials=2, progress=False)
    simulate_to_dataset("press-soft", out, seed=0, trials=1, progress=False)
    return out


@pytest.fixture(scope="session")
def cache():
    """A feature cache shared by the tests that load ``sim_ds``."""
    return {}


def _write_csv(path: Path, rows: list[str]) -> Path:
    path.write_text("\n".join(rows) + "\n")
    return path


@pytest.fixture(scope="session")
def write_csv():
    """``write_csv(path, rows)``: a manifest file from its lines."""
    return _write_csv


def _assert_time_split_ok(ws, tr, te, gap):
    assert len(np.intersect1d(tr, te)) == 0
    T = ws.window
    for g in np.unique(ws.groups):
        a = tr[ws.groups[tr] == g]
        b = te[ws.groups[te] == g]
        if len(a) and len(b):
            last_train = ws.t_index[a].max()
            first_test = (ws.t_index[b] - T + 1).min()
            assert first_test - last_train > gap


@pytest.fixture(scope="session")
def assert_time_split_ok():
    """``assert_time_split_ok(ws, train_idx, test_idx, gap)``: no window on both sides and
    at least ``gap`` frames between a trial's last train frame and first test frame."""
    return _assert_time_split_ok
