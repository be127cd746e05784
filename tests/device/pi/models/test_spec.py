"""device/pi/models/spec.py: the one model-spec schema, its round trip, and the
errors that name the file and the field."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from device.pi.models.params import ClassifierParams
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
                measured={"trained_on": {"data": "real",
                                         "recordings": [{"path": "r/a.avi", "sha256": "ab",
                                                         "frames": "0..100"}],
                                         "split": "later frames"},
                          "int8": {"agreement": 0.99}, "cost_per_decision": {"files": {}}},
                config={"task": "texture", "T": 15}, params={"roughness": True})
    base.update(kw)
    return ModelSpec(**base)


def test_a_spec_round_trips_through_its_manifest_with_metrics_content_unrestricted():
    spec = _spec()
    doc = json.loads(json.dumps(spec.to_manifest()))
    assert doc["version"] == SPEC_VERSION and doc["params"]["roughness"] is True
    assert list(doc["metrics"]) == list(METRIC_KEYS)
    back = ModelSpec.from_manifest(doc, "m/manifest.json")
    assert back.metrics["test"]["accuracy_ci95"] == [0.8, 0.95]
    assert back.params == ClassifierParams(roughness=True) and back.n_pins == 133
    assert back.measured.int8 == {"agreement": 0.99} and back.measured.identity is None
    assert back.pipeline_profile().n_pins == 133
    assert back.to_manifest() == doc


@pytest.mark.parametrize("edit, match", [
    (lambda d: d.update(version=1), r"m/manifest\.json: manifest version 1"),
    (lambda d: d.update(window=15), r"m/manifest\.json: window: an old key.*'T'"),
    (lambda d: d["metrics"].update(heldout={}), r"metrics must have exactly.*'heldout' is now"),
    (lambda d: d["metrics"].pop("cv"), r"m/manifest\.json: metrics must have exactly"),
    (lambda d: d.update(T=0), r"m/manifest\.json: T must be a whole number of frames in "
                              r"\[1, 1000\], got 0"),
    (lambda d: d.pop("T"), r"m/manifest\.json: manifest lacks 'T'"),
    (lambda d: d.update(extra=1), r"m/manifest\.json: extra is not a field of the model spec"),
    (lambda d: d["params"].update(roughness="yes"), r"m/manifest\.json: params\.roughness must "
                                                    r"be true or false, got 'yes'"),
    (lambda d: d["params"].update(shade=1), r"m/manifest\.json: params\.shade is not a "
                                            r"parameter of a classifier model.*got 1"),
    (lambda d: d["measured"].update(cost=1), r"m/manifest\.json: measured\.cost is not a "
                                             r"measured fact.*got 1"),
    (lambda d: d.update(classes=["a", "a"]), r"m/manifest\.json: classes names \['a'\] more "
                                             r"than once"),
    (lambda d: d.pop("profile"), r"m/manifest\.json: manifest lacks 'profile'"),
    (lambda d: d["profile"].update(toml=d["profile"]["toml"].replace("n_pins = 133",
                                                                       "n_pins = 134")),
     r"profile\.sha256 does not match the profile's content"),
    (lambda d: d["measured"]["trained_on"].update(held_out="x"),
     r"measured\.trained_on names its protocol under"),
    (lambda d: d["measured"]["trained_on"].update(data="lab"),
     r"measured\.trained_on\.data must be one of.*got 'lab'"),
    (lambda d: d["measured"]["trained_on"]["recordings"].append("a.avi"),
     r"measured\.trained_on\.recordings\[1\] must be a table with a path"),
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
        assert spec.measured.trained_on["data"] in ("real", "simulated", "real+simulated")


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


def test_measured_facts_sit_in_their_own_record_never_among_the_params():
    """cost, the int8 and identity verdicts and the training data are ``measured``;
    a version 2 manifest's top-level cost is read into it, not into the params."""
    doc = json.loads(json.dumps(_spec().to_manifest()))
    assert set(doc["measured"]) == {"trained_on", "int8", "identity", "cost_per_decision"}
    assert not set(doc["params"]) & set(doc["measured"])
    v2 = {k: v for k, v in doc.items() if k not in ("params", "measured")}
    v2.update(version=2, **doc["params"], **{k: v for k, v in doc["measured"].items()
                                             if k != "identity"})
    back = ModelSpec.from_manifest(v2, "old/manifest.json")
    assert back.measured.cost_per_decision == {"files": {}}
    assert back.params == ClassifierParams(roughness=True)
    assert "cost_per_decision" not in back.params.to_doc()
    assert back.to_manifest() == doc            # the old manifest reads as the new one


def test_T_is_required_by_the_writer_and_the_reader():
    """No silent T = 1: the host's spec builder and the manifest reader both refuse
    a model without it, naming T."""
    from host.learn.onnx_io import new_spec
    with pytest.raises(SpecError, match=r"^T: a texture model's spec needs"):
        new_spec(10, {"kind": "texture", "classes": ["a", "b"]}, "model.onnx", "0" * 64)
    doc = json.loads(json.dumps(_spec().to_manifest()))
    doc.pop("T")
    with pytest.raises(SpecError, match=r"m/manifest\.json: manifest lacks 'T'"):
        ModelSpec.from_manifest(doc, "m/manifest.json")


def test_writer_and_reader_agree_on_the_default_model():
    """A writer that names no ``model`` and an old manifest without one both get the
    kind as the model."""
    from host.learn.onnx_io import new_spec
    spec = new_spec(10, {"kind": "texture", "classes": ["a", "b"], "T": 2}, "model.onnx", "0" * 64)
    doc = json.loads(json.dumps(spec.to_manifest()))
    assert doc["model"] == "texture"
    v2 = {k: v for k, v in doc.items() if k not in ("params", "measured", "model")}
    v2["version"] = 2
    assert ModelSpec.from_manifest(v2, "old/manifest.json").model == spec.model
