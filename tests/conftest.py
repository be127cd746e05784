"""Fixtures shared across the test tree."""
from __future__ import annotations

import pytest

from tests import REPO_ROOT
from tests.windows import synthetic


@pytest.fixture
def repo_root():
    """The repository root."""
    return REPO_ROOT


@pytest.fixture
def synthetic_windows():
    """A factory of easy-to-learn synthetic windows (tests/windows.py)."""
    return synthetic


@pytest.fixture(scope="session")
def small_model(tmp_path_factory):
    """(training result, model folder, windows): a quick surface FNN, int8 + float, on
    synthetic windows (for numerics, quantisation and refusal tests; copy the folder
    before changing it)."""
    from host.learn.train import train_model

    ws = synthetic()
    out = tmp_path_factory.mktemp("small") / "m"
    res = train_model("surface", "fnn", ws, quantise=True, out_dir=out, progress=False,
                      hidden=(8, 4), epochs=60, min_agreement=0.9)
    return res, out, ws


@pytest.fixture(scope="session")
def drag_frames():
    """The first 40 frames of the simulated drag-0 scene (seed 3)."""
    from device.sim import Simulator, load_scene

    sim = Simulator(load_scene("drag-0"), seed=3)
    return [sim.render(i) for i in range(0, min(sim.n_frames, 40))]
