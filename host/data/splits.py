"""Splits that never leak: whole trials to one side (:func:`split_grouped`,
:func:`group_kfold`) or, within each trial, earlier frames to train and later ones to
test with a gap (:func:`split_time`). Each returns index arrays into a WindowSet.
:func:`split_holdout` picks between the two so that no class is lost, and says which
protocol it used (:data:`LEAVE_RECORDINGS_OUT`, :data:`LATER_FRAMES` or
:data:`MIXED`): the recording is the unit, so whole *recordings*
(:meth:`WindowSet.recording_ids`) are held out of each class that has two or more of
them; a class with one recording is tested on the later frames of it, which is
optimistic, since the test windows share the training windows' session.
:func:`held_out_recordings` says, per recording, which of the two its test windows
are."""
from __future__ import annotations

from typing import Iterator

import numpy as np

from host.data.windows import DataError, WindowSet


def _group_labels(ws: WindowSet, uniq: np.ndarray, inv: np.ndarray) -> np.ndarray:
    """The most common label of each group ('' for regression)."""
    if ws.labels is None:
        return np.array([""] * len(uniq), object)
    out = []
    lab = ws.labels.astype(str)
    for g in range(len(uniq)):
        names, counts = np.unique(lab[inv == g], return_counts=True)
        out.append(names[np.argmax(counts)])
    return np.array(out, object)


#: the held-out protocols of :func:`split_holdout` (a model's ``metrics.test.protocol``)
LEAVE_RECORDINGS_OUT = "leave-recordings-out"
LATER_FRAMES = "later-frames-same-recordings (optimistic)"
MIXED = ("leave-recordings-out where a class has two or more recordings, else "
         "later-frames-same-recordings (optimistic)")


def split_grouped(ws: WindowSet, test_frac: float = 0.3, seed: int = 0, keys=None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(train_idx, test_idx): whole trials (or whole ``keys``, e.g. recording ids) to
    one side, about ``test_frac`` of them to test, spread over their majority labels."""
    if not (isinstance(test_frac, (int, float)) and 0.0 < test_frac < 1.0):
        raise DataError(f"test_frac must be between 0 and 1, got test_frac={test_frac!r}")
    uniq, inv = np.unique(ws.groups if keys is None else np.asarray(keys).astype(str),
                          return_inverse=True)
    n = len(uniq)
    if n < 2:
        raise DataError(f"split_grouped needs at least 2 groups (trials), the data have {n}; "
                        f"use split_time to split within a trial")
    rng = np.random.default_rng(seed)
    order = rng.permutation(n)
    glab = _group_labels(ws, uniq, inv)
    order = order[np.argsort(glab[order].astype(str), kind="stable")]
    pos = np.arange(n)
    u = rng.random()             # systematic sampling: test_frac of each label's trials
    pick = np.floor((pos + 1) * test_frac + u) > np.floor(pos * test_frac + u)
    test_groups = order[pick]
    if len(test_groups) == 0:
        test_groups = order[:1]
    if len(test_groups) == n:
        test_groups = order[1:]
    is_test = np.isin(inv, test_groups)
    return np.flatnonzero(~is_test), np.flatnonzero(is_test)


def split_time(ws: WindowSet, train_frac: float = 0.7, gap: int | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
    """(train_idx, test_idx) within each trial: windows that end in the first
    ``train_frac`` of its frames to train, windows that start at least ``gap`` frames
    (default T) after that to test. No window overlaps both sides."""
    if not (isinstance(train_frac, (int, float)) and 0.0 < train_frac < 1.0):
        raise DataError(f"train_frac must be between 0 and 1, got train_frac={train_frac!r}")
    T = ws.window
    gap = T if gap is None else gap
    if isinstance(gap, bool) or not isinstance(gap, (int, np.integer)) or gap < 0:
        raise DataError(f"gap must be a whole number of frames >= 0, got gap={gap!r}")
    if (ws.t_index < 0).any():
        raise DataError("split_time: some windows have no time order (from an .npz); "
                        "use split_grouped")
    boundary = np.floor(train_frac * ws.trial_len).astype(np.int64)
    first = ws.t_index - T + 1
    train = ws.t_index < boundary
    test = first >= boundary + gap
    if not train.any() or not test.any():
        raise DataError(f"split_time: train_frac={train_frac} with gap={gap} leaves "
                        f"{int(train.sum())} train and {int(test.sum())} test windows; "
                        f"the trials are too short for T={T}")
    return np.flatnonzero(train), np.flatnonzero(test)


def missing_classes(ws: WindowSet, idx: np.ndarray, classes) -> list[str]:
    """The ``classes`` that no window ``idx`` of ``ws`` carries."""
    have = set() if ws.labels is None else {str(x) for x in ws.labels[idx]}
    return sorted(str(c) for c in classes if str(c) not in have)


def recordings_per_class(ws: WindowSet) -> dict[str, int]:
    """How many recordings carry windows of each class."""
    if ws.labels is None:
        return {}
    rec = ws.recording_ids().astype(str)
    lab = ws.labels.astype(str)
    return {c: int(len(np.unique(rec[lab == c]))) for c in sorted(set(lab.tolist()))}


def _pick_recordings(ws: WindowSet, rec: np.ndarray, frac: float, seed: int) -> np.ndarray:
    """Test windows: of each class's recordings (by their most common label other than
    no-touch), ``frac`` rounded, at least one and never all."""
    from host.data.windows import NO_TOUCH
    rng = np.random.default_rng(seed)
    lab = ws.labels.astype(str) if ws.labels is not None else np.full(len(ws), "", object)
    ids = np.unique(rec)
    major = {}
    for r in ids:
        names, counts = np.unique(lab[rec == r], return_counts=True)
        keep = names != NO_TOUCH
        if keep.any():
            names, counts = names[keep], counts[keep]
        major[r] = names[np.argmax(counts)]
    test = []
    for c in sorted(set(major.values())):
        mine = rng.permutation([r for r in ids if major[r] == c])
        if len(mine) >= 2:
            test += list(mine[:min(len(mine) - 1, max(1, int(round(frac * len(mine)))))])
    return np.flatnonzero(np.isin(rec, test))


def holdout_protocol(how: str) -> str:
    """The protocol (:data:`LEAVE_RECORDINGS_OUT`, :data:`LATER_FRAMES`, :data:`MIXED`,
    ``given`` or ``none``) that a :func:`split_holdout` account ``how`` names."""
    if how.startswith("grouped split"):
        return LEAVE_RECORDINGS_OUT
    if how.startswith("time split"):
        return LATER_FRAMES
    if how.startswith("mixed split"):
        return MIXED
    return how.split(":", 1)[0]


def held_out_recordings(ws_train: WindowSet, ws_test: WindowSet) -> dict:
    """Which recordings the test windows ``ws_test`` come from, and how: ``whole``,
    the recordings held out whole ({recording: test windows}), and ``inside``, the
    recordings split inside (the later frames tested: optimistic). Recordings are
    compared by id (:meth:`WindowSet.recording_ids`), so the two sets must name them."""
    seen = set(ws_train.recording_ids().astype(str).tolist())
    rid, n = np.unique(ws_test.recording_ids().astype(str), return_counts=True)
    out: dict = {"whole": {}, "inside": {}}
    for r, k in zip(rid.tolist(), n.tolist()):
        out["inside" if r in seen else "whole"][r] = int(k)
    return out


def _mixed_split(ws: WindowSet, rec: np.ndarray, few: list[str], test_frac: float,
                 grouped_frac: float, seed: int):
    """(train_idx, test_idx): whole recordings of each class that has two or more
    (:func:`_pick_recordings`), and the later frames (:func:`split_time`) of the one
    recording of each class in ``few``; None when no such split exists."""
    lab = ws.labels.astype(str)
    alone = np.unique(rec[np.isin(lab, few)])            # the recordings of those classes
    inside = np.flatnonzero(np.isin(rec, alone))
    try:
        tr_in, te_in = split_time(ws.subset(inside), 1.0 - test_frac)
    except DataError:
        return None
    te_whole = _pick_recordings(ws.subset(np.flatnonzero(~np.isin(rec, alone))),
                                rec[~np.isin(rec, alone)], grouped_frac, seed)
    rest = np.flatnonzero(~np.isin(rec, alone))
    te = np.sort(np.concatenate([inside[te_in], rest[te_whole]]))
    tr = np.sort(np.concatenate([inside[tr_in], np.setdiff1d(rest, rest[te_whole])]))
    return tr, te


def split_holdout(ws: WindowSet, test_frac: float = 0.3, seed: int = 0, tries: int = 32,
                  grouped_frac: float = 0.25) -> tuple[np.ndarray, np.ndarray, str]:
    """(train_idx, test_idx, how): a held-out split that keeps every class on both
    sides.

    Where every class has two or more recordings, whole recordings go to one side
    (:func:`split_grouped` on the recording ids, holding out ``grouped_frac`` of
    them; up to ``tries`` seeds from ``seed``) when that keeps every class in train
    and test: ``how`` starts with "grouped split" and names :data:`LEAVE_RECORDINGS_OUT`.
    Where some classes have two or more recordings and others one, the first lose
    whole recordings to the test side and the one recording of each of the others is
    split in time as below: ``how`` starts with "mixed split" and names :data:`MIXED`.
    Otherwise, as with one recording per class, each trial is split in time (:func:`split_time`): its
    first ``1 - test_frac`` to train, its last ``test_frac`` to test, with a gap of T
    frames; ``how`` starts with "time split within each trial", names
    :data:`LATER_FRAMES` and says "same recordings: optimistic". ``how`` says why (:func:`holdout_protocol` reads the protocol back).
    A DataError names the classes that no split keeps.
    """
    classes = [] if ws.labels is None else sorted({str(x) for x in ws.labels})
    rec = ws.recording_ids().astype(str)
    n_rec = len(np.unique(rec))
    per_class = recordings_per_class(ws)
    few = sorted(c for c, n in per_class.items() if n < 2)
    why = f"{n_rec} recording(s)"
    if few and len(few) < len(per_class):
        for k in range(tries):                 # the recording is the unit where it can be
            got = _mixed_split(ws, rec, few, test_frac, grouped_frac, seed + k)
            if got is None:
                break
            tr, te = got
            if not missing_classes(ws, tr, classes) + missing_classes(ws, te, classes):
                whole = sorted(set(rec[te]) - set(rec[tr]))
                return tr, te, (f"mixed split ({MIXED}): {len(whole)} of {n_rec} recordings "
                                f"held out whole; class(es) {few} have one recording each, "
                                f"split inside it in time (last {test_frac:.0%} after a gap "
                                f"of {ws.window} frames): optimistic for them")
    if few:
        why = (f"class(es) {few} have only one recording each "
               f"({', '.join(f'{c}: {per_class[c]}' for c in few[:5])})")
    elif n_rec >= 2:
        lost: list = []
        for k in range(tries):
            if ws.labels is None:           # regression: a share of all recordings
                tr, te = split_grouped(ws, grouped_frac, seed + k,
                                       keys=None if ws.recordings is None else rec)
            else:
                te = _pick_recordings(ws, rec, grouped_frac, seed + k)
                tr = np.setdiff1d(np.arange(len(ws)), te)
            lost = missing_classes(ws, tr, classes) + missing_classes(ws, te, classes)
            if not lost:
                return tr, te, (f"grouped split ({LEAVE_RECORDINGS_OUT}): "
                                f"{len(np.unique(rec[te]))} of {n_rec} recordings held out "
                                f"whole")
        why = (f"no split of whole recordings keeps every class on both sides "
               f"(e.g. {sorted(set(lost))} would be lost)")
    try:
        tr, te = split_time(ws, 1.0 - test_frac)
    except DataError as exc:
        raise DataError(f"no held-out split: {why}, and {exc}") from None
    lost_tr, lost_te = missing_classes(ws, tr, classes), missing_classes(ws, te, classes)
    if lost_tr or lost_te:
        raise DataError(f"no held-out split keeps every class: {why}, and the time split "
                        f"leaves class(es) {sorted(set(lost_tr + lost_te))} without "
                        f"{'training' if lost_tr else 'test'} windows (too few frames for "
                        f"T={ws.window}); record more of them or give --test")
    return tr, te, (f"time split within each trial ({LATER_FRAMES}): last {test_frac:.0%} "
                    f"held out after a gap of {ws.window} frames, because {why}; same recordings: "
                    f"optimistic (the test windows share the training windows' session: "
                    f"give --test with another recording for a fair score)")


def group_kfold(ws: WindowSet, k: int, seed: int = 0
                ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """K folds of whole trials: yields (train_idx, test_idx) ``k`` times. Each trial
    is in exactly one test fold; folds are balanced by window count."""
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 2:
        raise DataError(f"k must be a whole number >= 2, got k={k!r}")
    uniq, inv = np.unique(ws.groups, return_inverse=True)
    if len(uniq) < k:
        raise DataError(f"too few groups for {k} folds: the data have {len(uniq)} trials "
                        f"(groups); use k <= {len(uniq)} or more trials")
    sizes = np.bincount(inv, minlength=len(uniq))
    rng = np.random.default_rng(seed)
    order = rng.permutation(len(uniq))
    order = order[np.argsort(-sizes[order], kind="stable")]
    fold_of = np.empty(len(uniq), np.int64)
    load = np.zeros(k, np.int64)
    for i, g in enumerate(order):
        f = i if i < k else int(np.argmin(load))   # every fold gets a trial first
        fold_of[g] = f
        load[f] += sizes[g]
    win_fold = fold_of[inv]

    def gen():
        for f in range(k):
            yield np.flatnonzero(win_fold != f), np.flatnonzero(win_fold == f)

    return gen()
