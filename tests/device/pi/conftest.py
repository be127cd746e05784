"""Fixtures of the Pi tests: a small learned model set for the runtime."""
from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def model_dir(tmp_path_factory):
    """models/surface (a tiny FNN, int8 + float) and models/pressure (ridge), trained
    on synthetic windows over the 133-pin roboskin layout."""
    from host.learn.train import train_model
    from tests.windows import synthetic

    d = tmp_path_factory.mktemp("models")
    ws = synthetic(n_groups=4, per_group=30, n_pins=133, Tn=3,
                   classes=("hard", "no-touch", "slippery", "soft"))
    train_model("surface", "fnn", ws, quantise=True, out_dir=d / "surface", progress=False,
                hidden=(8, 4), epochs=20, min_agreement=0.01)
    wp = synthetic(n_groups=4, per_group=12, n_pins=133, Tn=3, targets=True, imu=False)
    train_model("pressure", "ridge", wp, out_dir=d / "pressure", progress=False)
    return d
