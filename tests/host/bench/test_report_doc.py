"""host/bench/report_doc.py: mean ± sd cells, the Pareto front, the tables, the
figure and the header's machine line and Pi 4 scaling."""
from __future__ import annotations

import math

from host.bench import report_doc


def agg(kind, T, mean, sd=0.01, n=3, errors=(), metric="accuracy"):
    return {"data": "d", "task": "texture", "kind": kind, "T": T, "seeds": n, "n": n,
            "mean": mean, "sd": sd, "metric": metric, "errors": list(errors),
            "int8_mean": math.nan, "int8_sd": math.nan, "int8_n": 0, "int8_errors": 0,
            "n_train": 100, "n_test": 40, "train_s": 1.0}


def cost(p50):
    t = {"p50": p50, "p99": 2 * p50}
    return {"vision": {"cpu": t, "wall": t}, "model": {"cpu": t, "wall": t}, "cpu": t,
            "wall": t, "pi4": {"p50": 4 * p50, "p99": 8 * p50}}


def test_pm_formats_mean_sd_and_seeds():
    assert report_doc.pm(0.91234, 0.0123, 3, 4) == "0.9123 ± 0.0123 (3)"
    assert report_doc.pm(math.nan, math.nan, 0) == "-"


def test_the_table_marks_the_front_and_lists_untrained_cells():
    rows = [agg("fnn", 1, 0.90), agg("fnn", 10, 0.95), agg("grid-fnn", 10, 0.80),
            agg("cnn", 5, math.nan, n=0, errors=["too few windows"])]
    text = report_doc.section_table(rows, {("fnn", 1): cost(1.0), ("fnn", 10): cost(1.0)})
    lines = text.splitlines()
    assert "0.9000 ± 0.0100 (3)" in lines[2] and lines[2].endswith("* |")
    assert lines[3].endswith("* |")               # slower but more accurate
    assert lines[4].endswith("|  |")              # slower and worse than fnn T=1
    assert "| 1.000 / 2.000 | 4.000 / 8.000 | 9.3 |" in lines[2]  # 1000/120 + 1 ms
    assert "| cnn | 5 | not trained: too few windows" in text
    assert report_doc.pareto([(1, 0.9), (2, 0.95), (2, 0.8)], False) == {0, 1}
    assert report_doc.pareto([(1, 0.3), (2, 0.1), (2, 0.5)], True) == {0, 1}


def test_the_regulariser_table_and_verdict_compare_dropout_with_l2():
    rows = [dict(agg("fnn", 10, 0.85, sd=0.02), data="lego"),
            dict(agg("fnn-dropout", 10, 0.90, sd=0.01), data="lego")]
    text = report_doc.regulariser_table(rows)
    assert "| L2 penalty alpha = 1e-3 (shipped) | 0.8500 ± 0.0200 (3) |" in text
    assert "| dropout 0.2 (paper) | 0.9000 ± 0.0100 (3) |" in text
    assert report_doc.regulariser_verdict(rows) == \
        "lego: dropout +0.0500 against L2 (beyond one sd)."


def test_the_figure_draws_error_bars(tmp_path):
    out = report_doc.plot_accuracy_vs_t([agg("fnn", 1, 0.9), agg("fnn", 2, 0.95)],
                                        tmp_path / "img" / "a.png", "t")
    assert out.is_file() and out.stat().st_size > 1000


def test_the_header_names_the_machine_the_scaling_and_the_cluster_backends():
    doc = {"command": "host report --jobs 2", "jobs": 2, "cnn": False,
           "machine": {"cpu": "Test CPU", "cores": 2, "load": [1.0, 2.0, 3.0],
                       "system": "Linux", "python": "3.11"},
           "vision": {"plain": cost(1.5)["cpu"] and {"cpu": {"p50": 1.5, "p99": 3.0},
                                                     "wall": {"p50": 2.0, "p99": 9.0}},
                      "crop": {"cpu": {"p50": 1.6, "p99": 3.1}, "wall": {"p50": 2.1, "p99": 9.1}},
                      "frames": 100, "clips": ["smooth.avi"]},
           "sections": [], "aggregate": [], "timing": [], "regulariser_T": 10}
    text = report_doc.render(doc)
    assert "Test CPU, 2 cores, load average 1.00, 2.00, 3.00" in text
    assert "multiplies this machine's CPU times by 4" in text
    assert "thread CPU time 1.500 / 3.000 ms" in text
    assert 'parallel_config(backend="dask")' in text and "--jobs 2" in text
