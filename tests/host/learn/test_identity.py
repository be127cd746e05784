"""host/learn/identity.py: the recording-identity check flags recordings a model can
tell apart, and not recordings drawn from one distribution."""
from __future__ import annotations

import numpy as np

from host.learn.estimators import hyperparameters
from host.learn.identity import WARNING, identity_check
from tests.windows import synthetic

HP = hyperparameters("fnn", (8, 8), 1e-3, 25)


def _one_class_two_recordings(offset: float, seed: int = 0):
    """120 windows each of two recordings of class 'a' (and 40 windows of 'b');
    the second recording's displacements shifted by ``offset`` px."""
    ws = synthetic(n_groups=3, per_group=120, classes=("a", "a", "b"), imu=False, seed=seed)
    ws.recordings = np.array(["r0", "r1", "r2"], object)[ws.groups]
    ws.vectors[ws.groups == 1] += np.float32(offset)
    return ws


def test_two_recordings_that_differ_by_an_offset_are_flagged():
    res = identity_check(_one_class_two_recordings(1.0), "surface", "fnn", HP)
    a = res["classes"]["a"]
    assert a["mode"] == "recordings" and a["recordings"] == ["r0", "r1"]
    assert a["balanced_accuracy_ci95"][0] > 0.5 + res["margin"] and a["flagged"]
    assert res["flagged"] and res["warning"].startswith(WARNING)
    assert res["classes"]["b"]["mode"] == "halves"


def test_recordings_drawn_from_one_distribution_are_not_flagged():
    res = identity_check(_one_class_two_recordings(0.0), "surface", "fnn", HP)
    a = res["classes"]["a"]
    assert a["balanced_accuracy_ci95"][0] <= 0.5 + res["margin"]
    assert not a["flagged"] and not res["flagged"] and res["warning"] is None
    lo, hi = a["balanced_accuracy_ci95"]
    assert lo <= a["balanced_accuracy"] <= hi and a["n_windows"] > 0


def test_a_drifting_single_recording_is_flagged_through_its_halves():
    """One recording whose second half is brighter (shifted): its halves, T frames
    apart, are told apart; a rule is not checked."""
    ws = _one_class_two_recordings(0.0)
    ws.recordings[:] = "one"
    ws.labels[:] = "a"
    ws.t_index = np.arange(len(ws)) + ws.window - 1
    ws.vectors[len(ws) // 2:] += np.float32(1.0)
    res = identity_check(ws, "surface", "fnn", HP)
    assert res["classes"]["a"]["mode"] == "halves" and res["flagged"]
    assert "skipped" in identity_check(ws, "surface", "rule")


def test_too_few_test_windows_are_inconclusive_not_flagged():
    """Recordings that differ, but with fewer than 2T test windows each: the check
    says inconclusive rather than flag on a handful of windows."""
    ws = synthetic(n_groups=3, per_group=30, classes=("a", "a", "b"), imu=False, Tn=3)
    ws.recordings = np.array(["r0", "r1", "r2"], object)[ws.groups]
    ws.vectors[ws.groups == 1] += np.float32(1.0)
    a = identity_check(ws, "surface", "fnn", HP)["classes"]["a"]
    assert a["n_windows"] < 12 and "inconclusive" in a and not a["flagged"]
