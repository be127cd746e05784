"""host/learn/evaluate.py: a model folder measured on windows through the Pi's loaders."""
from __future__ import annotations

import numpy as np
import pytest

from host.learn.evaluate import evaluate_model


def test_evaluate_reports_metrics_latency_size_and_kept_fraction(surface_model, surface_sets):
    res, out = surface_model
    _, ws_te = surface_sets
    ev = evaluate_model(out, ws_te)
    assert ev["variant"] == "int8" and ev["n_windows"] == len(ws_te)
    assert ev["metrics"]["accuracy"] == pytest.approx(res["int8"]["metrics"]["accuracy"])
    conf = np.array(ev["metrics"]["confusion"]["matrix"])
    assert conf.sum() == len(ws_te) and np.trace(conf) == round(ev["metrics"]["accuracy"]
                                                                * len(ws_te))
    assert set(ev["metrics"]["per_class"]) == set(res["classes"])
    lat = ev["latency_ms"]
    assert 0 < lat["p50"] <= lat["p99"] and lat["n"] == len(ws_te)
    assert ev["model_bytes"] == (out / "model.int8.onnx").stat().st_size
    assert ev["kept_fraction"] == ws_te.kept_fraction and ev["threads"] == 1
    evf = evaluate_model(out, ws_te, variant="float")
    assert evf["model_bytes"] == (out / "model.onnx").stat().st_size
    assert evf["metrics"]["accuracy"] == pytest.approx(res["metrics"]["test"]["accuracy"])
    from dataclasses import replace

    with pytest.raises(ValueError, match="the windows have T=5 frames, the model sees T=3"):
        evaluate_model(out, replace(ws_te.subset(np.arange(4)), window=5))


def _manifest(folder, variant, name="manifest.json"):
    from device.pi.models.manifest import write_spec
    from host.learn.onnx_io import new_spec
    onnx = "model.int8.onnx" if variant == "int8" else "model.onnx"
    write_spec(folder, new_spec(4, {"kind": "surface", "T": 1, "classes": ["a", "b"],
                                    "variant": variant}, onnx, "0" * 64), name)


def test_the_variant_is_picked_by_the_pis_picker_and_must_exist(tmp_path, monkeypatch):
    """evaluate picks the manifest with device.pi.models.manifest.manifest_for (one
    picker), and refuses a variant the folder does not have."""
    from device.pi.models import manifest as artefact
    from device.pi.models.spec import ModelError
    from host.learn import evaluate

    picks = []
    real = artefact.manifest_for
    monkeypatch.setattr(evaluate, "manifest_for", lambda f, v: picks.append(v) or real(f, v))
    q, f = tmp_path / "quantised", tmp_path / "float-only"
    _manifest(q, "int8")
    _manifest(q, "float", "manifest.float.json")
    _manifest(f, "float")
    assert evaluate.variant_manifest(q, None) == q / "manifest.json"
    assert evaluate.variant_manifest(q, "int8") == q / "manifest.json"
    assert evaluate.variant_manifest(q, "float") == q / "manifest.float.json"
    assert evaluate.variant_manifest(f, "float") == f / "manifest.json"
    assert picks == ["int8", "float", "float"]
    with pytest.raises(ModelError, match="no int8 model .train with --quantise"):
        evaluate.variant_manifest(f, "int8")
    with pytest.raises(ValueError, match="variant must be one of"):
        evaluate.variant_manifest(q, "int4")


def test_labels_the_model_does_not_know_are_refused(small_model, synthetic_windows):
    _, out, _ = small_model
    ws = synthetic_windows()
    assert evaluate_model(out, ws)["n_windows"] == len(ws)
    ws.labels[::7] = "lava"
    with pytest.raises(ValueError, match=r"the data hold label\(s\) \['lava'\] that the model "
                                         r"does not know \(its classes: \['a', 'b'\]\)"):
        evaluate_model(out, ws)


def test_evaluate_reports_each_recording_with_an_interval(surface_model, surface_sets):
    """host eval: the accuracy has its block-bootstrap interval and window count, and
    each recording (here each simulated scene run) its own accuracy and interval."""
    _, out = surface_model
    _, ws_te = surface_sets
    m = evaluate_model(out, ws_te, variant="float")["metrics"]
    lo, hi = m["accuracy_ci95"]
    assert lo <= m["accuracy"] <= hi and m["n_windows"] == len(ws_te)
    by = m["by_recording"]
    assert set(by) == set(ws_te.recording_ids().tolist()) and len(by) == 4
    assert all(k.startswith("simulated:") for k in by)
    assert sum(r["n_windows"] for r in by.values()) == len(ws_te)
    for r in by.values():
        assert r["accuracy_ci95"][0] <= r["accuracy"] <= r["accuracy_ci95"][1]


def test_windows_of_another_pin_count_name_the_models_profile_as_the_fix(tmp_path):
    """The input-size error says which profile the model was trained for."""
    from host.learn.train import train_model
    from tests.windows import synthetic
    ws = synthetic(n_groups=4, per_group=10, n_pins=133, Tn=1, imu=False, targets=True)
    ws.task = "pressure"
    train_model("pressure", "ridge", ws, out_dir=tmp_path / "m", progress=False)
    other = synthetic(n_groups=2, per_group=5, n_pins=6, Tn=1, imu=False, targets=True)
    other.task = "pressure"
    with pytest.raises(ValueError, match=r"the windows have 6 pins, the model's sensor profile "
                                         r"'roboskin' has 133: load the data with the model's "
                                         r"profile"):
        evaluate_model(tmp_path / "m", other)


def test_the_text_summary_is_short_and_carries_the_headline_with_its_interval(
        surface_model, surface_sets):
    """host eval without --json prints this summary, not the JSON: a few lines, the
    accuracy with its interval and window count, and the identity verdict lines."""
    import json

    from host.learn.evaluate import eval_summary
    res = evaluate_model(surface_model[1], surface_sets[1])
    text = eval_summary(res)
    lines = text.splitlines()
    assert 2 <= len(lines) <= 4 and not text.lstrip().startswith("{")
    acc, ci = res["metrics"]["accuracy"], res["metrics"]["accuracy_ci95"]
    assert f"accuracy {acc:.4g} [{ci[0]:.4g}, {ci[1]:.4g}] (95 %)" in lines[0]
    assert f"on {res['n_windows']} windows" in lines[0]
    res["identity_check"] = {"flagged": False, "warning": None, "classes": {"a": {
        "mode": "one recording", "verdict": "no verdict", "settle": "record a second session"}}}
    assert "identity check: a (one recording): no verdict; record a second session" in \
        eval_summary(res)
    json.dumps(res)
