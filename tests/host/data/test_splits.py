"""host/data/splits.py: grouped and time splits and group k-fold never leak a trial."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from host.data.load import load_spec
from host.data.splits import (group_kfold, missing_classes, split_grouped, split_holdout,
                               split_time)
from host.data.windows import DataError, WindowSet


def synthetic(trial_lens, T, stride=1, labels=("a", "b")):
    """A WindowSet with only the bookkeeping arrays filled in."""
    g, t, L = [], [], []
    for k, n in enumerate(trial_lens):
        ends = np.arange(T - 1, n, stride)
        g += [k] * len(ends)
        t += list(ends)
        L += [n] * len(ends)
    N = len(g)
    lab = np.array([labels[x % len(labels)] for x in g], object)
    return WindowSet(task="surface", window=T, vectors=np.zeros((N, T, 1, 2), np.float32),
                     lost=np.zeros((N, T, 1), bool), imu=None, grids=None, frames=None,
                     contact=np.ones(N, bool), labels=lab, targets=None,
                     groups=np.array(g, np.int64), t_index=np.array(t, np.int64),
                     trial_len=np.array(L, np.int64), classes=sorted(set(labels)))


@settings(max_examples=80, deadline=None)
@given(st.lists(st.integers(30, 300), min_size=1, max_size=4), st.integers(1, 10),
       st.integers(1, 3), st.floats(0.3, 0.9), st.integers(0, 15))
def test_time_split_never_overlaps_and_keeps_the_gap(assert_time_split_ok, lens, T, stride, frac,
                                                     gap):
    ws = synthetic(lens, T, stride)
    b = np.floor(frac * ws.trial_len)
    n_train = int((ws.t_index < b).sum())
    n_test = int((ws.t_index - T + 1 >= b + gap).sum())
    if n_train == 0 or n_test == 0:                 # trials too short: a clear error
        with pytest.raises(DataError, match="too short"):
            split_time(ws, frac, gap)
        return
    tr, te = split_time(ws, frac, gap)
    assert (len(tr), len(te)) == (n_train, n_test)
    assert_time_split_ok(ws, tr, te, gap)
    for i in tr:      # train windows lie in the first frac of their trial
        assert ws.t_index[i] < np.floor(frac * ws.trial_len[i])


def test_time_split_default_gap_is_T(assert_time_split_ok):
    ws = synthetic([100, 80], 5)
    tr, te = split_time(ws)
    assert_time_split_ok(ws, tr, te, 5)
    first_test = ws.t_index[te] - 4
    assert first_test[ws.groups[te] == 0].min() == 70 + 5


@settings(max_examples=60, deadline=None)
@given(st.integers(2, 30), st.floats(0.1, 0.6), st.integers(0, 1000))
def test_grouped_split_never_shares_a_trial(n_trials, frac, seed):
    ws = synthetic([20 + 3 * k for k in range(n_trials)], 3)
    tr, te = split_grouped(ws, frac, seed)
    assert len(tr) and len(te) and len(tr) + len(te) == len(ws)
    assert not set(ws.groups[tr]) & set(ws.groups[te])


def test_grouped_split_spreads_labels_and_kfold_covers_each_trial_once():
    ws = synthetic([30] * 10, 3)               # 5 trials of 'a', 5 of 'b'
    tr, te = split_grouped(ws, 0.4, seed=3)
    assert set(ws.labels[te]) == {"a", "b"} and set(ws.labels[tr]) == {"a", "b"}
    seen = []
    for tr, te in group_kfold(ws, 5):
        assert not set(ws.groups[tr]) & set(ws.groups[te])
        assert len(tr) + len(te) == len(ws)
        seen += sorted(set(ws.groups[te]))
    assert sorted(seen) == list(range(10))


def test_grouped_split_on_a_simulated_dataset(sim_ds, cache, assert_time_split_ok):
    ws = load_spec(str(sim_ds), "surface", 3, progress=False, cache=cache)
    tr, te = split_grouped(ws, 0.34, seed=0)
    assert not set(ws.groups[tr]) & set(ws.groups[te])
    tr, te = split_time(ws)
    assert_time_split_ok(ws, tr, te, 3)


def test_too_few_groups_for_k_folds():
    ws = synthetic([30, 30, 30], 3)
    with pytest.raises(DataError, match="too few groups for 5 folds.*3 trials"):
        group_kfold(ws, 5)
    with pytest.raises(DataError, match="at least 2 groups"):
        split_grouped(synthetic([30], 3), 0.3)
    with pytest.raises(DataError, match="no time order"):
        split_time(_untimed(ws))


def _untimed(ws):
    ws = ws.subset(np.arange(len(ws)))
    ws.t_index[:] = -1
    return ws


def test_split_holdout_keeps_whole_trials_when_every_class_survives():
    ws = synthetic([40] * 8, 3)                 # 4 trials per class
    tr, te, how = split_holdout(ws, 0.3, seed=0)
    assert how.startswith("grouped split")
    assert set(ws.groups[tr]).isdisjoint(ws.groups[te])
    assert set(ws.labels[tr]) == set(ws.labels[te]) == {"a", "b"}


@pytest.mark.parametrize("n_trials", [1, 2, 3])
def test_split_holdout_falls_back_to_time_within_each_trial_and_says_why(n_trials):
    """One recording per class (the paper's data): a whole-trial split would lose a
    class, so each trial's last 30 % is held out after a gap of T frames."""
    T = 4
    ws = synthetic([60] * n_trials, T, labels=("a", "b", "c")[:n_trials])
    tr, te, how = split_holdout(ws, 0.3, seed=0)
    assert how.startswith("time split within each trial")
    assert "gap of 4 frames" in how
    assert set(ws.labels[tr]) == set(ws.labels[te]) == set(ws.labels)
    for g in np.unique(ws.groups):
        last_train = ws.t_index[tr][ws.groups[tr] == g].max()
        first_test = (ws.t_index[te][ws.groups[te] == g] - T + 1).min()
        assert first_test - last_train >= T         # the gap: no frame shared, T apart
        assert first_test >= int(0.7 * 60)


def test_split_holdout_names_a_class_no_split_can_keep():
    ws = synthetic([6, 60], 5, labels=("rare", "common"))   # 2 windows of "rare"
    with pytest.raises(DataError, match=r"no held-out split keeps every class.*\[.rare.\]"):
        split_holdout(ws, 0.3, seed=0)


def test_missing_classes_lists_absent_ones():
    ws = synthetic([10, 10], 2)
    assert missing_classes(ws, np.flatnonzero(ws.groups == 0), ["a", "b", "z"]) == ["b", "z"]


def test_split_holdout_leaves_whole_recordings_out_never_a_part_of_one():
    """8 trials that are parts of 4 recordings (two per class): whole recordings go
    to one side, so no recording's windows are trained and tested on."""
    from host.data.splits import LEAVE_RECORDINGS_OUT, holdout_protocol
    ws = synthetic([40] * 8, 3)                 # trial k has label a (even) or b (odd)
    ws.recordings = np.array([f"rec{g % 4}" for g in ws.groups], object)  # 0,2: a; 1,3: b
    for seed in range(6):
        tr, te, how = split_holdout(ws, 0.3, seed=seed)
        assert holdout_protocol(how) == LEAVE_RECORDINGS_OUT and "recordings held out" in how
        assert set(ws.recordings[tr]).isdisjoint(ws.recordings[te])
        assert set(ws.labels[tr]) == set(ws.labels[te]) == {"a", "b"}
        assert len(tr) + len(te) == len(ws)


def test_split_holdout_holds_out_whole_recordings_of_a_class_that_has_two():
    """The recording is the unit (issue 33): class a has two recordings, class b one
    (cut into two trials). One recording of a is held out whole; b's one recording is
    split in time, and the account says both, b's part "optimistic"."""
    from host.data.splits import MIXED, held_out_recordings, holdout_protocol
    ws = synthetic([40] * 4, 3)
    ws.recordings = np.array(["a1", "b1", "a2", "b1"], object)[ws.groups]
    for seed in range(4):
        tr, te, how = split_holdout(ws, 0.3, seed=seed)
        assert holdout_protocol(how) == MIXED and "1 of 3 recordings held out whole" in how
        assert "['b'] have one recording each" in how and "optimistic" in how
        held = held_out_recordings(ws.subset(tr), ws.subset(te))
        assert set(held["inside"]) == {"b1"} and len(held["whole"]) == 1
        (whole,) = held["whole"]
        assert whole in ("a1", "a2") and whole not in set(ws.recordings[tr])
        assert held["whole"][whole] == int((ws.recordings == whole).sum())
        # b1's test windows are its later frames, after a gap of T
        b_tr, b_te = (ws.t_index[i][ws.recordings[i] == "b1"] for i in (tr, te))
        assert (b_te - 3 + 1).min() - b_tr.max() >= 3


def test_split_holdout_with_one_recording_of_every_class_says_optimistic():
    """Every class has one recording: the split is by time within the recordings,
    and says so: 'same recordings: optimistic'."""
    from host.data.splits import LATER_FRAMES, held_out_recordings, holdout_protocol
    ws = synthetic([40] * 4, 3)
    ws.recordings = np.array(["a1", "b1", "a1", "b1"], object)[ws.groups]
    tr, te, how = split_holdout(ws, 0.3, seed=0)
    assert holdout_protocol(how) == LATER_FRAMES and "same recordings: optimistic" in how
    assert "['a', 'b'] have only one recording" in how
    held = held_out_recordings(ws.subset(tr), ws.subset(te))
    assert held["whole"] == {} and set(held["inside"]) == {"a1", "b1"}
