"""host/bench/sweep.py: cells through joblib, the mean ± sd over seeds, the int8
verdict of a cell."""
from __future__ import annotations

import json
import math

import pytest

from host.bench import sweep
from host.bench.report_doc import section_table
from host.learn.tasks import QuantisationError
from tests.windows import synthetic


def test_mean_sd_is_the_sample_sd_and_ignores_missing_values():
    mean, sd, n = sweep.mean_sd([0.9, 1.0, None, float("nan")])
    assert (round(mean, 6), round(sd, 6), n) == (0.95, round(math.sqrt(0.005), 6), 2)
    assert sweep.mean_sd([0.7]) == (0.7, 0.0, 1)
    mean, sd, n = sweep.mean_sd([])
    assert n == 0 and math.isnan(mean) and math.isnan(sd)


def test_aggregate_groups_seeds_and_keeps_errors_apart():
    rows = [{"data": "d", "task": "texture", "kind": "fnn", "T": 2, "seed": s, "accuracy": a,
             "mae": None, "n_train": 10, "n_test": 5, "train_s": 1.0, "int8_accuracy": a}
            for s, a in ((0, 0.8), (1, 0.9), (2, 1.0))]
    rows.append({"data": "d", "task": "texture", "kind": "fnn", "T": 5, "seed": 0,
                 "n_train": 10, "n_test": 5, "error": "too few windows"})
    agg = {(a["kind"], a["T"]): a for a in sweep.aggregate(rows)}
    a = agg[("fnn", 2)]
    assert a["metric"] == "accuracy" and a["n"] == 3 and a["seeds"] == 3
    assert math.isclose(a["mean"], 0.9) and math.isclose(a["sd"], 0.1)
    assert math.isclose(a["int8_mean"], 0.9) and a["int8_n"] == 3
    failed = agg[("fnn", 5)]
    assert failed["n"] == 0 and failed["errors"] == ["too few windows"]


def test_jobs_2_gives_the_same_rows_as_jobs_1(tmp_path):
    """The cells are independent and seeded: two workers give the same scores and
    the same table as one."""
    ws = synthetic(n_groups=4, per_group=12, classes=("hard", "soft"))
    te = synthetic(n_groups=2, per_group=12, classes=("hard", "soft"), seed=1)
    windows = {("syn", ws.window): (ws, te)}
    cells = [sweep.Cell("syn", "surface", k, ws.window, s)
             for k, s in (("rule", 0), ("fnn", 0), ("fnn", 1))]
    one = sweep.run_cells(cells, windows, tmp_path / "a", jobs=1)
    two = sweep.run_cells(cells, windows, tmp_path / "b", jobs=2)
    strip = [{k: v for k, v in r.items() if k != "train_s"} for r in one]
    assert strip == [{k: v for k, v in r.items() if k != "train_s"} for r in two]
    assert section_table(sweep.aggregate(one), {}) == section_table(sweep.aggregate(two), {})
    assert [(r["kind"], r["seed"]) for r in two] == [("rule", 0), ("fnn", 0), ("fnn", 1)]
    assert all("error" not in r for r in one) and all(r["accuracy"] >= 0.9 for r in one[1:])


def test_kept_models_are_timed_with_vision_added(tmp_path):
    ws = synthetic(n_groups=4, per_group=12)
    windows = {("syn", ws.window): (ws, ws)}
    rows = sweep.run_cells([sweep.Cell("syn", "surface", "fnn", ws.window, 0)], windows,
                           tmp_path, keep_seed=0)
    assert rows[0]["model_dir"].startswith(str(tmp_path))
    vision = {"plain": {"wall": {"p50": 2.0, "p99": 5.0}, "cpu": {"p50": 1.0, "p99": 3.0}}}
    cost = sweep.time_models(rows, windows, vision)[("syn", "fnn", ws.window)]
    model = cost["model"]["cpu"]
    assert model["n"] == len(ws) and 0 < model["p50"] <= model["p99"]
    assert math.isclose(cost["cpu"]["p50"], 1.0 + model["p50"])
    assert math.isclose(cost["pi4"]["p99"], 4 * (3.0 + model["p99"]))


def test_a_failed_int8_check_keeps_the_float_model_and_says_why(monkeypatch, tmp_path):
    """When the int8 copy fails its check the float model is still written (trained
    once); the verdict carries the agreement reached, from the check's fields."""
    import host.learn.trainers

    def failing_quantise(*a, **k):
        raise QuantisationError("int8 check failed: the agreement is too low",
                                kind="classifier", agreement=0.9718, required=0.99)

    fits = []
    real_fit = host.learn.trainers.fit_estimator
    monkeypatch.setattr(host.learn.trainers, "quantise_model", failing_quantise)
    monkeypatch.setattr(host.learn.trainers, "fit_estimator",
                        lambda *a, **k: fits.append(1) or real_fit(*a, **k))
    ws = synthetic()
    why = sweep.train_row("surface", "fnn", ws, ws, tmp_path / "m", 0)
    assert len(fits) == 1
    assert why == ("int8 check failed: 97.18% argmax agreement with float (< 99 %); "
                   "float kept")
    assert (tmp_path / "m" / "model.onnx").is_file()
    assert not (tmp_path / "m" / "model.int8.onnx").exists()
    doc = json.loads((tmp_path / "m" / "manifest.json").read_text())
    assert doc["variant"] == "float" and doc["measured"]["int8"]["agreement"] == 0.9718


@pytest.mark.parametrize("fields,message,want", [
    ({"mae_change": 0.5, "mae_change_of_range": 0.1}, "int8 check failed: raises the MAE",
     "int8 check failed: raises the MAE by 0.5 (10.00% of the target range, > 1%); float kept"),
    ({}, "int8 check failed: /m/model.int8.onnx gives NaN",
     "int8 check failed: /m/model.int8.onnx gives NaN"),
])
def test_the_int8_verdict_names_the_numbers_or_the_message_once(fields, message, want):
    assert sweep.int8_why(fields, message) == want


def test_a_finished_cell_is_reused_for_the_same_windows_only(monkeypatch, tmp_path):
    ws = synthetic(n_groups=4, per_group=12, classes=("hard", "soft"))
    te = synthetic(n_groups=2, per_group=12, classes=("hard", "soft"), seed=1)
    cell = sweep.Cell("syn", "surface", "rule", ws.window, 0)
    first = sweep.run_cell(cell, ws, te, tmp_path)
    monkeypatch.setattr(sweep, "train_row", lambda *a, **k: (_ for _ in ()).throw(
        AssertionError("trained again")))
    assert sweep.run_cell(cell, ws, te, tmp_path) == first
    other = synthetic(n_groups=2, per_group=12, classes=("hard", "soft"), seed=2)
    with pytest.raises(AssertionError, match="trained again"):
        sweep.run_cell(cell, ws, other, tmp_path)
