"""host/bench/sim.py: the pipeline benchmark scores pins with the analysis code."""
from __future__ import annotations


def test_the_benchmark_scores_pins_with_the_one_recall_precision():
    from host.analysis import recall
    from host.bench import sim

    assert sim.recall_precision is recall.recall_precision
