"""The recording-identity check: can the model kind tell recordings of one class apart?

A model that scores well on windows of the recordings it was trained on may have
learnt the recording (its exposure, frame rate, lost pins, the session) rather than
the surface. :func:`identity_check` trains the same model kind, on the same inputs
(its MLP stopped after at most 100 epochs, for speed),
to tell apart the recordings of one class (where a class has two or more), or the
two halves of its one recording (split at the middle frame, with a gap of T frames
between the halves). Within each recording (or half), the earlier 70 % of windows
train and the windows after a gap of T frames test. The score is the balanced
accuracy on the test windows (the mean of the per-recording accuracies) with its
95 % block-bootstrap interval (:func:`host.learn.metrics.block_bootstrap`).

When the interval's lower bound exceeds chance (1/k for k recordings) by more than
``margin`` (default 0.2) for any class whose every recording (or half) has at least
2T test windows (fewer: ``inconclusive``, not flagged), the check is ``flagged`` and its
``warning`` reads :data:`WARNING`: ``host train`` puts it in its result and the
manifest, and the model card shows it. Windows without contact (``no-touch``) are
not checked: they show no surface.
"""
from __future__ import annotations

import numpy as np

from host.data.windows import NO_TOUCH
from host.learn.estimators import fit_estimator, hyperparameters
from host.learn.inputs import model_inputs
from host.learn.metrics import block_bootstrap
from host.learn.tasks import LAYOUT, TrainError

__all__ = ["identity_check", "WARNING", "MARGIN"]

WARNING = "the model may learn the recording, not the surface"
#: how far above chance the interval's lower bound must be to flag
MARGIN = 0.2
#: fewest windows a recording (or half) needs on each side of its time split
MIN_WINDOWS = 5
#: most training epochs of the check's MLP (the model's own setting when lower)
MAX_EPOCHS = 100
#: a class's windows are thinned evenly to at most this many; the interval's resamples
MAX_WINDOWS, N_BOOT = 3000, 1000


def _position(ws, idx: np.ndarray) -> np.ndarray:
    fi = getattr(ws, "frame_index", None)
    return (fi if fi is not None and (fi[idx] >= 0).all() else ws.t_index)[idx]


def _time_split(pos: np.ndarray, T: int, frac: float = 0.7):
    """(train, test) masks: the earlier ``frac`` of the frame span and the windows
    that start T frames or more after it."""
    lo, hi = pos.min() - T + 1, pos.max() + 1
    b = lo + int(np.floor(frac * (hi - lo)))
    return pos < b, pos - T + 1 >= b + T


def _pseudo_recordings(ws, idx: np.ndarray, T: int) -> tuple[np.ndarray, np.ndarray, str]:
    """(windows, pseudo-recording id per window, mode) for one class's windows."""
    rec = ws.recording_ids()[idx].astype(str)
    if len(np.unique(rec)) >= 2:
        return idx, rec, "recordings"
    pos = _position(ws, idx)
    mid = (pos.min() - T + 1 + pos.max() + 1) // 2
    first = pos < mid
    second = pos - T + 1 >= mid + T                # T frames between the halves
    keep = first | second
    return (idx[keep], np.where(first[keep], f"{rec[0]} first half",
                                f"{rec[0]} second half").astype(object), "halves")


def identity_check(ws, task: str, model: str, hp: dict | None = None,
                   uses_imu: bool = False, seed: int = 0, margin: float = MARGIN) -> dict:
    """Run the check on the windows ``ws`` with the model kind ``model`` (its
    hyperparameters ``hp``, default :func:`hyperparameters`). Returns a JSON-able
    dict: ``classes`` (per class: the recordings or halves, ``mode``,
    ``balanced_accuracy``, ``balanced_accuracy_ci95``, ``chance``, ``n_windows``,
    ``flagged``; or ``skipped`` and why), ``flagged``, ``warning`` (None when not
    flagged), ``margin``."""
    if not (0.0 <= margin < 1.0):
        raise TrainError(f"identity check: margin must be in [0, 1), got margin={margin!r}")
    out = {"flagged": False, "warning": None, "margin": margin, "classes": {},
           "method": ("same model kind trained to tell apart the recordings of one class "
                      "(or the two halves of its one recording, T frames apart); earlier "
                      "70 % of each trains, later windows after a gap of T frames test; "
                      "balanced accuracy with a block-bootstrap 95 % interval")}
    if model == "rule" or task == "pressure" or ws.labels is None:
        out["skipped"] = ("a rule learns no recording" if model == "rule"
                          else "regression: recordings are not classes")
        return out
    T = ws.window
    hp = dict(hyperparameters(model) if hp is None else hp)
    if hp.get("epochs"):
        hp["epochs"] = min(int(hp["epochs"]), MAX_EPOCHS)
    labels = ws.labels.astype(str)
    rng = np.random.default_rng(seed)
    for c in sorted(set(labels.tolist()) - {NO_TOUCH}):
        idx = np.flatnonzero(labels == c)
        if len(idx) > MAX_WINDOWS:              # an even thinning keeps the time order
            idx = idx[np.sort(rng.choice(len(idx), MAX_WINDOWS, replace=False))]
        idx, pseudo, mode = _pseudo_recordings(ws, idx, T)
        ids = sorted(set(pseudo.tolist()))
        train, test = np.zeros(len(idx), bool), np.zeros(len(idx), bool)
        for r in ids:
            sel = np.flatnonzero(pseudo == r)
            a, b = _time_split(_position(ws, idx[sel]), T)
            train[sel[a]], test[sel[b]] = True, True
        short = [r for r in ids if min((train & (pseudo == r)).sum(),
                                       (test & (pseudo == r)).sum()) < MIN_WINDOWS]
        entry = {"mode": mode, "recordings": ids}
        if len(ids) < 2 or short:
            entry["skipped"] = (f"too few windows (fewer than {MIN_WINDOWS} to train or test "
                                f"in {short or ids})")
            out["classes"][c] = entry
            continue
        X = model_inputs(ws.subset(idx), LAYOUT[model], uses_imu)
        y = np.array([ids.index(r) for r in pseudo], np.int64)
        pipe, _ = fit_estimator(task, model, X[train], y[train], len(ids), hp, seed)
        pred = np.asarray(pipe.predict(X[test])).reshape(-1).astype(np.int64)
        correct = (pred == y[test]).astype(np.float64)
        te_idx = np.flatnonzero(test)
        order = {r: np.flatnonzero(pseudo[te_idx] == r)[
            np.argsort(_position(ws, idx[te_idx[pseudo[te_idx] == r]]), kind="stable")]
            for r in ids}
        rids, sums, counts, _ = block_bootstrap(correct, pseudo[te_idx], T, order, N_BOOT,
                                                seed)
        per = {r: float(correct[pseudo[te_idx] == r].mean()) for r in rids}
        bal = float(np.mean(list(per.values())))
        boot = (sums / counts[None, :]).mean(axis=1)
        lo, hi = np.percentile(boot, [2.5, 97.5])
        chance = 1.0 / len(ids)
        few = int(counts.min()) < 2 * T          # under two window lengths of test
        flagged = bool(lo > chance + margin) and not few
        entry.update({"balanced_accuracy": round(bal, 4),
                      "balanced_accuracy_ci95": [round(float(lo), 4), round(float(hi), 4)],
                      "chance": round(chance, 4), "per_recording": {
                          r: round(v, 4) for r, v in per.items()},
                      "n_windows": int(len(te_idx)), "n_train_windows": int(train.sum()),
                      "flagged": flagged})
        if few:
            entry["inconclusive"] = (f"a recording has {int(counts.min())} test windows, "
                                     f"under 2T = {2 * T}: not flagged")
        out["classes"][c] = entry
        out["flagged"] |= flagged
    if out["flagged"]:
        which = [c for c, e in out["classes"].items() if e.get("flagged")]
        out["warning"] = (f"{WARNING}: the {model} tells apart the recordings of class(es) "
                          f"{which} far above chance")
    return out
