"""The paper's rule classifier (device/pi/models/rules.py) as an artefact: a rule
table edited after training is refused."""
from __future__ import annotations

import json

import pytest

from device.pi.models.artefact import ModelError
from device.pi.models.classifier import Classifier
from device.pi.models.rules import RuleClassifier
from host.learn.train import train_model
from tests.windows import synthetic


def test_an_edited_rule_is_refused(tmp_path):
    ws = synthetic(classes=("hard", "soft"), imu=False)
    train_model("surface", "rule", ws, out_dir=tmp_path / "r", progress=False)
    RuleClassifier.load(tmp_path / "r")
    doc = json.loads((tmp_path / "r" / "manifest.json").read_text())
    doc["rule"]["contact_px"] += 1.0
    (tmp_path / "r" / "manifest.json").write_text(json.dumps(doc))
    with pytest.raises(ModelError, match=r"r/manifest\.json: the rule table does not match"):
        Classifier.load(tmp_path / "r")

