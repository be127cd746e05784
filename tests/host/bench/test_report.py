"""host/bench/report.py: rows, the int8 fallback, the Pareto front and the table."""
from __future__ import annotations

import numpy as np

from host.bench import report
from host.learn.tasks import QuantisationError


def row(model, variant, T, acc, p50):
    return {"task": "surface", "data": "sim", "model": model, "variant": variant, "T": T,
            "accuracy": acc, "mae": None, "latency_p50_ms": p50, "latency_p99_ms": 2 * p50,
            "size_bytes": 1024, **{f"delay_{f}fps_ms": 1000.0 * T / f for f in report.FPS}}


def test_a_failed_int8_check_keeps_the_float_row_and_says_why(monkeypatch, tmp_path):
    """When the int8 copy fails its check the float model is still written (trained
    once) and measured; the int8 row carries the agreement it reached, taken from
    the check's fields."""
    import json

    import host.learn.train
    from tests.windows import synthetic

    def failing_quantise(*a, **k):
        raise QuantisationError("int8 check failed: the agreement is too low",
                                kind="classifier", agreement=0.9718, required=0.99)

    fits = []
    real_fit = host.learn.train.fit_estimator
    monkeypatch.setattr(host.learn.train, "quantise_model", failing_quantise)
    monkeypatch.setattr(host.learn.train, "fit_estimator",
                        lambda *a, **k: fits.append(1) or real_fit(*a, **k))
    ws = synthetic()
    why = report.train_row("surface", "fnn", ws, ws, tmp_path / "m", 0)
    assert len(fits) == 1                                  # trained once, not twice
    assert why == ("int8 check failed: 97.18% argmax agreement with float (< 99 %); "
                   "float kept")
    assert (tmp_path / "m" / "model.onnx").is_file()
    assert not (tmp_path / "m" / "model.int8.onnx").exists()
    doc = json.loads((tmp_path / "m" / "manifest.json").read_text())
    assert doc["variant"] == "float" and doc["int8"]["agreement"] == 0.9718
    assert "the agreement is too low" in doc["int8"]["failed"]


def test_a_failed_regressor_check_is_reported_by_its_message(monkeypatch, tmp_path):
    import host.learn.train
    from tests.windows import synthetic

    def failing_quantise(*a, **k):
        raise QuantisationError("int8 check failed: raises the MAE by 0.5", kind="regressor",
                                mae_change=0.5, mae_change_of_range=0.1)

    monkeypatch.setattr(host.learn.train, "quantise_model", failing_quantise)
    ws = synthetic(targets=True, imu=False)
    why = report.train_row("pressure", "ridge", ws, ws, tmp_path / "p", 0)
    assert why == ("int8 check failed: raises the MAE by 0.5 (10.00% of the target range, "
                   "> 1%); float kept")                  # the prefix once, from the fields
    assert not (tmp_path / "p" / "model.int8.onnx").exists()


def test_a_verdict_without_numbers_says_int8_check_failed_once():
    exc = QuantisationError("int8 check failed: /m/model.int8.onnx the int8 model gives NaN "
                            "or inf; the int8 model was not kept")
    why = report._int8_why(exc.fields(), str(exc))
    assert why.count("int8 check failed") == 1
    assert why == "int8 check failed: /m/model.int8.onnx the int8 model gives NaN or inf; " \
                  "the int8 model was not kept"


def test_table_marks_the_pareto_front_and_lists_failures():
    rows = [row("fnn", "float", 3, 0.95, 0.1), row("fnn", "float", 1, 0.90, 0.1),
            row("rule", "float", 3, 0.80, 0.05),
            {"task": "surface", "model": "fnn", "variant": "int8", "T": 3,
             "error": "int8 check failed: 97% argmax agreement with float (< 99 %); float kept"},
            {"task": "surface", "model": "cnn", "T": 5, "error": "too few windows"}]
    text = report.table(rows)
    lines = text.splitlines()
    best, fast, dominated = lines[2], lines[3], lines[4]
    assert best.endswith("* |") and fast.endswith("* |")      # most accurate / fastest
    assert dominated.endswith("|  |")                          # slower and worse than T=1
    assert "| fnn | int8 | 3 | int8 check failed: 97%" in text
    assert "| cnn | - | 5 | not trained: too few windows" in text
    front = report.pareto([r for r in rows if "error" not in r], lower_better=False)
    assert front == {0, 1}
    assert np.isclose(rows[0]["delay_120fps_ms"], 25.0)
