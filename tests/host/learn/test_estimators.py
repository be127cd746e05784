"""host/learn/estimators.py: early stopping on the training loss."""
from __future__ import annotations

from host.learn.estimators import Plateau


def test_plateau_stops_after_patience_epochs_without_improvement():
    p = Plateau(tol=0.01, patience=3)
    assert [p.reached(x) for x in (1.0, 0.5, 0.495, 0.494, 0.493)] == [False] * 4 + [True]
    p = Plateau(tol=0.01, patience=2)
    assert not p.reached(1.0) and not p.reached(1.0)
    assert not p.reached(0.5)              # an improvement resets the count
    assert not p.reached(0.5) and p.reached(0.5)
