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
