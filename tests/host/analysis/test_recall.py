"""Pin recall and precision (host/analysis/recall.py)."""

from __future__ import annotations

import numpy as np

from host.analysis.recall import pin_hits, recall_precision


def test_hits_within_the_gate():
    truth = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0], [30.0, 0.0]])
    found = np.array([[0.5, 0.0], [10.0, 1.9], [50.0, 0.0]])
    truth_hit, found_hit, err = pin_hits(found, truth, gate_px=2.0)
    assert truth_hit.tolist() == [True, True, False, False]
    assert found_hit.tolist() == [True, True, False]
    np.testing.assert_allclose(err, [0.5, 1.9, 20.0])
    r, p = recall_precision(found, truth, gate_px=2.0)
    assert r == 0.5 and abs(p - 2 / 3) < 1e-12
    r, p = recall_precision(found, truth, gate_px=15.0)       # 20 px away: not yet
    assert r == 0.75 and abs(p - 2 / 3) < 1e-12
    assert recall_precision(found, truth, gate_px=25.0) == (1.0, 1.0)


def test_empty_sets_give_finite_zeros():
    truth = np.zeros((3, 2))
    truth_hit, found_hit, err = pin_hits(np.zeros((0, 2)), truth)
    assert truth_hit.tolist() == [False] * 3 and found_hit.size == 0 and err.size == 0
    _, found_hit, err = pin_hits(truth, np.zeros((0, 2)))
    assert found_hit.tolist() == [False] * 3 and np.isinf(err).all()
    assert recall_precision(np.zeros((0, 2)), truth) == (0.0, 0.0)
    assert recall_precision(truth, []) == (0.0, 0.0)
