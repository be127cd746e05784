"""The paper's rule classifier (device/pi/models/rules.py) as an artefact: a rule
table edited after training is refused."""
from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from device.pi.models.artefact import ModelError
from device.pi.models.classifier import Classifier
from device.pi.models.rules import RuleClassifier, window_measures
from device.pi.protocol import SURFACE_CLASSES
from host.learn.train import train_model
from tests.windows import synthetic

RULE = {"contact_px": 1.0, "expected_mag_px": 6.0, "soft_ratio": 0.6,
        "expected_motion_px": 0.5, "wet_ratio": 0.3}


def test_an_edited_rule_is_refused(tmp_path):
    ws = synthetic(classes=("hard", "soft"), imu=False)
    train_model("surface", "rule", ws, out_dir=tmp_path / "r", progress=False)
    RuleClassifier.load(tmp_path / "r")
    doc = json.loads((tmp_path / "r" / "manifest.json").read_text())
    doc["params"]["rule"]["contact_px"] += 1.0
    (tmp_path / "r" / "manifest.json").write_text(json.dumps(doc))
    with pytest.raises(ModelError, match=r"r/manifest\.json: the rule table does not match"):
        Classifier.load(tmp_path / "r")



@given(arrays(np.float32, st.tuples(st.integers(1, 4), st.integers(1, 9), st.just(2)),
              elements=st.floats(width=32, allow_nan=True, allow_infinity=True)))
@settings(max_examples=150, deadline=None)
def test_window_measures_and_the_rule_are_finite_and_match_the_plain_formulas(v):
    """NaN and inf count as no displacement; the magnitude is the mean |v| of the last
    frame, the motion the per-frame move of the average vector; the probabilities of
    any window are finite and sum to 1."""
    m = window_measures(v)
    c = np.nan_to_num(v.astype(np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    assert m["magnitude_px"] == np.hypot(c[-1, :, 0], c[-1, :, 1]).mean()
    avg = c.mean(axis=1)
    assert (m["shear_x_px"], m["shear_y_px"]) == (avg[-1, 0], avg[-1, 1])
    if len(c) >= 2:
        assert m["motion_px"] == float(np.hypot(*(avg[-1] - avg[0]))) / (len(c) - 1)
    else:
        assert m["motion_px"] is None
    rc = RuleClassifier(RULE, SURFACE_CLASSES, v.shape[0], v.shape[1])
    k, p = rc.predict(v.reshape(-1))
    assert np.isfinite(p).all() and p.sum() == pytest.approx(1.0) and k == int(np.argmax(p))
    assert rc.last == m


def test_the_rule_decides_each_class_from_the_gait_context():
    rc = RuleClassifier(RULE, SURFACE_CLASSES, 3, 5)
    still = np.zeros((3, 5, 2), np.float32)
    pressed = still.copy()
    pressed[:, :, 0] = 4.0                     # 4 px everywhere, the skin does not move

    def call(v, **ctx):
        return SURFACE_CLASSES[rc.predict(v.reshape(-1), **ctx)[0]]

    assert call(still) == "no-touch"
    assert call(pressed, expected_mag_px=5.0, expected_motion_px=0.0) == "hard"
    assert call(pressed, expected_mag_px=20.0, expected_motion_px=0.0) == "soft"
    assert call(pressed, expected_mag_px=5.0, expected_motion_px=1.0) == "slippery"
    moving = pressed.copy()
    moving[:, :, 1] = np.array([0.0, 1.0, 2.0])[:, None]
    assert call(moving, expected_mag_px=5.0, expected_motion_px=1.0) == "hard"


def test_a_rule_model_naming_a_class_twice_is_refused_naming_it():
    """Two slots of one class would split its probability between them: refused."""
    with pytest.raises(ValueError, match=r"each be named once.*hard repeated"):
        RuleClassifier(RULE, ["hard", "soft", "hard"], 3, 5)
    assert RuleClassifier(RULE, ["hard", "soft"], 3, 5).n_classes == 2
