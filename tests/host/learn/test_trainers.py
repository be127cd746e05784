"""host/learn/trainers.py: each model kind's trainer, in steps."""
from __future__ import annotations

import pytest

from host.learn.config import TrainConfig
from host.learn.tasks import TrainError
from host.learn.train import TRAINERS, split_run, train_model
from host.learn.trainers import plan
from tests.windows import synthetic


def test_the_cnn_refuses_a_setting_it_does_not_read_before_training(tmp_path):
    ws = synthetic()
    with pytest.raises(TrainError, match=r"model cnn: the CNN does not take cv, augment; drop "
                                         r"them or choose another kind"):
        train_model("surface", "cnn", ws, out_dir=tmp_path / "m", progress=False, cv=2,
                    augment=1)
    assert not (tmp_path / "m").exists()
    assert TRAINERS["cnn"].__name__ == "train_frames_cnn"


def test_the_plan_reads_the_kind_and_refuses_what_it_cannot_read():
    ws = synthetic()
    run = split_run(TrainConfig("surface", "fnn", hidden=(8, 4)), ws)
    p = plan(run)
    assert p.layout == "vectors" and p.temporal and p.hp["hidden"] == [8, 4]
    assert p.uses_imu == (ws.imu is not None)
    grid = split_run(TrainConfig("surface", "grid-fnn", augment=2), ws)
    with pytest.raises(TrainError, match="augment=2 rotates pin vectors; grid-fnn reads grids"):
        plan(grid)
    rule = split_run(TrainConfig("surface", "rule", temporal=True), ws)
    with pytest.raises(TrainError, match="temporal=True needs the fnn"):
        plan(rule)
