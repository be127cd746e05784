"""device/pi/models/spec.py: the one model-spec schema, its round trip, and the
errors that name the file and the field."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from device.pi.models.spec import (METRIC_KEYS, SPEC_VERSION, ModelSpec, SpecError,
                                   check_same_profiles, profile_from_text, profile_record)

ROOT = Path(__file__).resolve().parents[4]


def _spec(**kw) -> ModelSpec:
    base = dict(kind="texture", task="texture", model="fnn", classes=["a", "b"], T=15,
                input_layout="vectors", n_inputs=3990, profile=profile_record("roboskin"),
                onnx="model.onnx", sha256={"model.onnx": "0" * 64},
                metrics={"train": {"accuracy": 1.0}, "test": {"accuracy": 0.9,
                                                             "accuracy_ci95": [0.8, 0.95],
                                                             "n_windows": 200}, "cv": None},
                trained_on={"data": "real", "recordings": [{"path": "r/a.avi", "sha256": "ab",
                                                            "frames": "0..100"}],
                            "split": "later frames"},
                config={"task": "texture", "T": 15}, params={"roughness": True})
    base.update(kw)
    return ModelSpec(**base)


def test_a_spec_round_trips_through_its_manifest_with_metrics_content_unrestricted():
    spec = _spec()
    doc = json.loads(json.dumps(spec.to_manifest()))
    assert doc["version"] == SPEC_VERSION and doc["roughness"] is True
    assert list(doc["metrics"]) == list(METRIC_KEYS)
    back = ModelSpec.from_manifest(doc, "m/manifest.json")
    assert back.metrics["test"]["accuracy_ci95"] == [0.8, 0.95]
    assert back.params == {"roughness": True} and back.n_pins == 133
    assert back.pipeline_profile().n_pins == 133
    assert back.to_manifest() == doc


@pytest.mark.parametrize("edit, match", [
    (lambda d: d.update(version=1), r"m/manifest\.json: manifest version 1"),
    (lambda d: d.update(window=15), r"m/manifest\.json: window: an old key.*'T'"),
    (lambda d: d["metrics"].update(heldout={}), r"metrics must have exactly.*'heldout' is now"),
    (lambda d: d["metrics"].pop("cv"), r"m/manifest\.json: metrics must have exactly"),
    (lambda d: d.update(T=0), r"m/manifest\.json: T must be a whole number >= 1, got 0"),
    (lambda d: d.pop("profile"), r"m/manifest\.json: manifest lacks 'profile'"),
    (lambda d: d["profile"].update(toml=d["profile"]["toml"].replace("n_pins = 133",
                                                                       "n_pins = 134")),
     r"profile\.sha256 does not match the profile's content"),
    (lambda d: d["trained_on"].update(held_out="x"), r"trained_on names its protocol under"),
    (lambda d: d["trained_on"].update(data="lab"), r"trained_on\.data must be one of"),
    (lambda d: d["trained_on"]["recordings"].append("a.avi"),
     r"trained_on\.recordings\[1\] must be a table with a path"),
])
def test_a_manifest_off_the_schema_is_refused_naming_the_file_and_field(edit, match):
    doc = json.loads(json.dumps(_spec().to_manifest()))
    edit(doc)
    with pytest.raises(SpecError, match=match):
        ModelSpec.from_manifest(doc, "m/manifest.json")


def test_models_with_different_profiles_or_a_different_given_profile_are_named():
    rob = profile_record("roboskin")
    tac = profile_record("tactip331")
    assert check_same_profiles({"a/manifest.json": rob, "b/manifest.json": rob})["n_pins"] == 133
    with pytest.raises(SpecError, match=r"a/manifest\.json \(roboskin, 133 pins.*vs "
                                        r"b/manifest\.json \(.*331 pins"):
        check_same_profiles({"a/manifest.json": rob, "b/manifest.json": tac})
    with pytest.raises(SpecError, match=r"profile given, .*tactip331\.toml .*is not the "
                                        r"model's: a/manifest\.json"):
        check_same_profiles({"a/manifest.json": rob}, tac)
    assert check_same_profiles({}, tac)["n_pins"] == 331


def test_every_shipped_manifest_follows_the_spec_and_names_its_sensor():
    manifests = sorted((ROOT / "models").glob("*/manifest*.json"))
    assert manifests
    for m in manifests:
        spec = ModelSpec.from_manifest(json.loads(m.read_text()), m)
        assert spec.profile["name"] == "roboskin" and spec.n_pins == 133
        assert spec.trained_on["data"] in ("real", "simulated", "real+simulated")


def test_profile_source_loads_the_records_own_profile(tmp_path):
    """A built-in profile's record names the built-in; a calibrated one (any other
    content) is written to a file that loads the same record, so the runtime runs
    the model's own sensor."""
    from device.pi.models.spec import profile_source

    rob = profile_record("roboskin")
    assert profile_source(rob) == "roboskin"
    text = rob["toml"].replace("n_pins = 133", "n_pins = 132", 1)
    assert text != rob["toml"]
    own = profile_from_text(text, "roboskin")
    src = profile_source(own)
    assert src.endswith(".toml") and profile_record(src)["sha256"] == own["sha256"]
    assert profile_source(own) == src            # written once, by its hash
