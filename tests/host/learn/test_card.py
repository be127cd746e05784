"""host/learn/card.py: the model card and train.toml written from a model spec, and
the recordings of data specs with their checksums."""
from __future__ import annotations

import hashlib
import shutil

import numpy as np
from pathlib import Path

import pytest

from device.config import ConfigError
from device.pi.models.artefact import read_spec
from host.learn.card import (card_text, data_source, read_train_toml, recordings_of,
                             toml_text, write_model_docs, write_train_toml)

ROOT = Path(__file__).resolve().parents[3]


def test_the_card_of_the_shipped_texture_model_says_what_the_issue_asks(tmp_path):
    folder = ROOT / "models" / "texture"
    spec, _ = read_spec(folder)
    text = card_text(spec, "texture")
    test = spec.metrics["test"]
    int8_bytes = (folder / "model.int8.onnx").stat().st_size
    for want in ("texture while the foot is in contact", "`concrete`, `lego`, `smooth`",
                 "profile `roboskin`, 133 pins, sha256 `" + spec.profile["sha256"][:16],
                 "- real data", "| roboskin/concrete.avi |", "## Protocol",
                 "after a gap of 15 frames", f"held-out test: accuracy {test['accuracy']:.3f}",
                 f"n={test['n']}", "argmax agreement 1.0000",
                 f"`model.int8.onnx`: {int8_bytes} bytes (loaded by default)",
                 "cost per decision"):
        assert want in text, want
    # the shipped texture model is tested on later frames of its training recordings
    assert test["same_recordings"] is True and "optimistic" in text
    # an interval and a count where the metrics carry them; no warning without
    # same-recordings
    spec.metrics["test"] = dict(test, accuracy=0.957, accuracy_ci95=[0.9, 0.98],
                                n_windows=211, same_recordings=False)
    text = card_text(spec, "texture")
    assert "accuracy 0.957 [0.900, 0.980] (95 % interval), n=211" in text
    assert "optimistic" not in text


def test_model_docs_write_the_card_and_a_train_toml_that_reads_back(tmp_path):
    folder = tmp_path / "surface"
    shutil.copytree(ROOT / "models" / "surface", folder)
    (folder / "README.md").unlink()
    (folder / "train.toml").unlink()
    out = write_model_docs(folder)
    assert set(out) == {"README.md", "train.toml"}
    spec, _ = read_spec(folder)
    assert read_train_toml(folder / "train.toml") == spec.config
    assert "python -m host.bench.shipped --only surface" in (folder / "train.toml").read_text()
    assert (folder / "README.md").read_text() == card_text(spec, "surface")


def test_toml_text_round_trips_and_refuses_what_toml_cannot_hold(tmp_path):
    cfg = {"task": "texture", "T": 15, "alpha": 0.001, "quantise": True, "data": ["a b", "c"],
           "cv": None, "extra": {"k": 1}}
    write_train_toml(tmp_path, cfg)
    assert read_train_toml(tmp_path / "train.toml") == {k: v for k, v in cfg.items()
                                                        if v is not None}
    with pytest.raises(ValueError, match="train.toml: alpha must be a finite number"):
        toml_text({"alpha": float("nan")})
    with pytest.raises(ValueError, match="train.toml: x must be a string"):
        toml_text({"x": object()})
    (tmp_path / "bad.toml").write_text("task = ")
    with pytest.raises(ConfigError, match="bad.toml: not valid TOML"):
        read_train_toml(tmp_path / "bad.toml")


def test_recordings_of_data_specs_carry_checksums_and_frame_ranges(tmp_path):
    (tmp_path / "a.avi").write_bytes(b"clip a")
    (tmp_path / "m.csv").write_text("path,label,start_frame,end_frame\n"
                                    "a.avi,lego,0,100\nsim://walk?seed=1,smooth,,\n")
    (tmp_path / "v.npz").write_bytes(b"npz")
    recs = recordings_of([str(tmp_path / "m.csv"), str(tmp_path / "v.npz")])
    assert recs[0] == {"path": str(tmp_path / "a.avi"),
                       "sha256": hashlib.sha256(b"clip a").hexdigest(), "frames": "0..100"}
    assert recs[1] == {"path": "sim://walk?seed=1", "sha256": None, "frames": None}
    assert recs[2]["sha256"] == hashlib.sha256(b"npz").hexdigest()
    assert data_source(recs[:1]) == "real" and data_source(recs[1:2]) == "simulated"
    assert data_source(recs[:2]) == "real+simulated" and data_source(recs[2:]) == "unknown"


def test_the_card_carries_the_identity_warning_the_spec_holds():
    """The recording-identity check's warning (metrics.test.identity_warning, written by
    host train when the check flags) is on the card, as the spec words it; no
    warning in the spec, none on the card."""
    from host.learn.identity import WARNING
    spec, _ = read_spec(ROOT / "models" / "texture")
    spec.metrics["test"] = {k: v for k, v in spec.metrics["test"].items()
                            if k != "identity_warning"}
    assert WARNING not in card_text(spec, "texture")
    warning = f"{WARNING}: the fnn tells apart the recordings of class(es) ['qz-7'] far above"
    spec.metrics["test"]["identity_warning"] = warning
    text = card_text(spec, "texture")
    assert f"- warning: {warning}" in text
    assert text.index("## Accuracy") < text.index(warning) < text.index("## int8")


def test_model_docs_time_the_cost_per_decision_into_the_spec_and_the_card(tmp_path):
    """write_model_docs times each model file single-threaded and records median and p99
    with the machine in both manifests; the card shows the spec's figures (changed in
    the spec, they change on the card)."""
    import json
    folder = tmp_path / "surface"
    shutil.copytree(ROOT / "models" / "surface", folder)
    write_model_docs(folder)
    spec, _ = read_spec(folder)
    cost = spec.measured.cost_per_decision       # a measured fact, not a parameter
    assert set(cost["files"]) == {"model.onnx", "model.int8.onnx"} and cost["threads"] == 1
    for r in cost["files"].values():
        assert 20 <= r["n"] <= 200 and 0 < r["median_ms"] <= r["p99_ms"] < 1e3
    assert "cores" in cost["machine"] and "onnxruntime" in cost["machine"]
    float_doc = json.loads((folder / "manifest.float.json").read_text())
    assert float_doc["measured"]["cost_per_decision"] == cost
    text = (folder / "README.md").read_text()
    r = cost["files"]["model.int8.onnx"]
    assert (f"cost per decision, `model.int8.onnx`: median {r['median_ms']:.3g} ms, "
            f"p99 {r['p99_ms']:.3g} ms over {r['n']} runs") in text
    assert cost["machine"] in text
    doc = json.loads((folder / "manifest.json").read_text())
    doc["measured"]["cost_per_decision"]["files"]["model.onnx"] = {
        "median_ms": 12.5, "p99_ms": 31.25, "n": 77}
    doc["measured"]["cost_per_decision"]["machine"] = "a test machine"
    (folder / "manifest.json").write_text(json.dumps(doc))
    write_model_docs(folder, measure=False)
    text = (folder / "README.md").read_text()
    assert "`model.onnx`: median 12.5 ms, p99 31.2 ms over 77 runs" in text
    assert "on a test machine" in text


def test_measure_cost_times_given_inputs_and_refuses_too_few_runs():
    from host.learn.card import measure_cost
    folder = ROOT / "models" / "surface"
    spec, _ = read_spec(folder)
    with pytest.raises(ValueError, match="runs must be a whole number >= 20, got 5"):
        measure_cost(folder, spec, runs=5)
    import numpy as np
    x = np.zeros((3, spec.n_inputs), np.float32)
    c = measure_cost(folder, spec, inputs=x, runs=20, budget_s=0.0)
    assert c["inputs"] == "a window of its own inputs"
    assert all(r["n"] == 20 for r in c["files"].values())


def test_the_card_records_the_identity_verdict_or_why_there_is_none():
    """The check's verdict per class (host.learn.identity) is on the card; one
    recording a class gives 'no verdict' and what would settle it; no check recorded
    says it was not run."""
    import dataclasses
    from host.learn.identity import identity_check
    from tests.windows import synthetic
    spec, _ = read_spec(ROOT / "models" / "texture")
    ws = synthetic(n_groups=2, per_group=60, classes=("a", "b"), imu=False)
    ws.recordings = np.array(["ra", "rb"], object)[ws.groups]
    check = identity_check(ws, "texture", "fnn")
    spec = dataclasses.replace(spec, measured=dataclasses.replace(spec.measured,
                                                                  identity=check))
    text = card_text(spec, "texture")
    assert "- recording-identity check: no verdict" in text
    assert "record a second session of a to check" in text
    none = dataclasses.replace(spec, measured=dataclasses.replace(spec.measured, identity=None))
    assert "- recording-identity check: not run" in card_text(none, "texture")


def test_a_dataset_folder_names_each_clip_with_its_checksum(tmp_path):
    """A dataset folder's recordings are its trials, each with the clip it was
    recorded from and that clip's full sha256, on the card too."""
    import dataclasses
    import json
    sha = hashlib.sha256(b"clip").hexdigest()
    (tmp_path / "trial_0000.npz").write_bytes(b"t0")
    (tmp_path / "trial_0001.npz").write_bytes(b"t1")
    (tmp_path / "dataset.json").write_text(json.dumps({"trials": [
        {"file": "trial_0000.npz", "frames": 100,
         "recording": {"id": "a.avi sha256:x", "file": "a.avi", "sha256": sha,
                       "start_frame": 5}},
        {"file": "trial_0001.npz", "frames": 50, "recording": {"id": "simulated:walk seed 1"}},
    ]}))
    recs = recordings_of([str(tmp_path)])
    assert recs[0] == {"path": str(tmp_path / "trial_0000.npz"), "sha256": sha,
                       "frames": "5..105", "clip": "a.avi"}
    assert recs[1]["sha256"] == hashlib.sha256(b"t1").hexdigest()
    assert recs[1]["clip"] == "simulated:walk seed 1"
    spec, _ = read_spec(ROOT / "models" / "texture")
    t = dict(spec.measured.trained_on, recordings=recs)
    spec = dataclasses.replace(spec, measured=dataclasses.replace(spec.measured, trained_on=t))
    assert f"| a.avi | {sha} | 5..105 |" in card_text(spec, "texture")
