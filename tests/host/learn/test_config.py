"""host/learn/config.py: the one typed training config (TrainConfig)."""
from __future__ import annotations

import dataclasses

import pytest

from host.learn.config import REPLAY_KEYS, TrainConfig
from host.learn.tasks import DEFAULT_MODEL, DEFAULT_WINDOW, TrainError


def test_a_config_is_frozen_and_fills_the_task_defaults():
    cfg = TrainConfig("texture")
    assert cfg.model == DEFAULT_MODEL["texture"] and cfg.T is None
    assert cfg.window == DEFAULT_WINDOW["texture"]
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.seed = 3
    assert TrainConfig("surface", "cnn").model == "cnn"
    assert TrainConfig("surface", rates=["3of5"], hidden=[8, 4]).rates == ("3of5",)


@pytest.mark.parametrize("kw,msg", [
    ({"task": "walk"}, r"task must be one of .* got task='walk'"),
    ({"task": "pressure", "model": "cnn"}, r"model='cnn' does not serve task='pressure'"),
    ({"task": "surface", "model": "svm"}, r"model must be one of .* got model='svm'"),
    ({"task": "surface", "quantise": "yes"}, "quantise must be True, False or 'if-passes'"),
    ({"task": "surface", "quantise": 1}, "quantise must be True, False or 'if-passes'"),
    ({"task": "surface", "cv": 1}, r"cv must be a whole number >= 2, got cv=1"),
    ({"task": "surface", "seed": -1}, r"seed must be a whole number >= 0, got seed=-1"),
    ({"task": "surface", "min_agreement": 0}, r"min_agreement must be in \(0, 1\]"),
    ({"task": "surface", "data": "a.csv"}, r"data must be a list of data specs, got "
                                           r"data='a.csv'"),
    ({"task": "surface", "identity": "yes"}, "identity must be true or false"),
])
def test_a_bad_setting_is_one_error_naming_the_field_and_value(kw, msg):
    with pytest.raises(TrainError, match=msg):
        TrainConfig(**kw)


def test_replay_gives_the_train_toml_settings_and_reads_them_back(tmp_path):
    data = tmp_path / "d.csv"
    cfg = TrainConfig("texture", "fnn", T=2, data=(str(data),), cv=3, quantise=True, seed=4,
                      identity=True, measure=True)
    doc = cfg.replay()
    assert tuple(doc) == REPLAY_KEYS and doc["data"] == [str(data.resolve())]
    back = TrainConfig.from_replay(doc, "train.toml", identity=True, measure=True)
    assert back == dataclasses.replace(cfg, data=(str(data.resolve()),))
    with pytest.raises(TrainError, match=r"--config t.toml: unknown setting\(s\) \['epochs'\]"):
        TrainConfig.from_replay(dict(doc, epochs=3), "t.toml")
    with pytest.raises(TrainError, match="--config t.toml: data must be a non-empty list"):
        TrainConfig.from_replay(dict(doc, data=[]), "t.toml")
    with pytest.raises(TrainError, match=r"--config t.toml: seed must be a whole number"):
        TrainConfig.from_replay(dict(doc, seed="x"), "t.toml")
