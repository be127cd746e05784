"""The recording-identity check: can a simple probe tell recordings of one class apart?

A model that scores well on windows of the recordings it was trained on may have
learnt the recording (its exposure, frame rate, lost pins, the session) rather than
the surface. :func:`identity_check` asks whether that is possible at all: a simple
probe (standardised inputs, a PCA of the model's own inputs, a logistic regression)
reads every window of each recording, the features the model reads plus the
per-window means of the statistics that carry a session (:data:`SESSION_FEATURES`:
lost pins, and where the loader measured them the image's brightness, its contrast
and the interval between frames), and is asked which recording each window came from.

Each recording's windows are cut, in time order, into :data:`N_BLOCKS` contiguous
blocks; block k of every recording is tested by a probe trained on the other blocks,
less the windows within T frames of the tested block (grouped cross-validation over
contiguous blocks, so a window is never tested by a probe that saw its frames). The
score is the balanced accuracy over every window (the mean of the per-recording
accuracies) with its 95 % block-bootstrap interval
(:func:`host.learn.metrics.block_bootstrap`).

Per class, the verdict is:

* ``flagged``: the interval's lower bound exceeds chance (1/k for k recordings) by
  more than ``margin`` (default 0.2): the recordings differ in what the model reads,
  and :func:`warning_line` gives the one-line warning ``host train`` and ``host
  eval`` log;
* ``clear``: the interval's upper bound is within ``margin`` of chance;
* ``inconclusive``: neither, or too few windows; it says what data would settle it;
* ``no verdict``: the class has one recording, so there is no second session to tell
  apart. Then, where every class has one recording, the probe is run on the session
  statistics alone across the classes (``across_classes``): when it tells the
  classes' recordings apart, a model could score by session rather than surface,
  which only a second session of a surface can check.

Windows without contact (``no-touch``) are not checked: they show no surface.
"""
from __future__ import annotations

import numpy as np

from host.data.windows import NO_TOUCH
from host.learn.inputs import model_inputs
from host.learn.metrics import block_bootstrap
from host.learn.tasks import LAYOUT, TrainError

__all__ = ["identity_check", "warning_line", "verdict_lines", "session_features",
           "WARNING", "MARGIN", "N_BLOCKS", "SESSION_FEATURES"]

WARNING = "the model may learn the recording, not the surface"
#: how far above chance the interval's lower bound must be to flag
MARGIN = 0.2
#: contiguous blocks per recording: the folds of the grouped cross-validation
N_BLOCKS = 5
#: a class's windows are thinned evenly to at most this many; the interval's resamples
MAX_WINDOWS, N_BOOT = 3000, 1000
#: fewest windows a block needs
MIN_BLOCK = 5
#: PCA components of the model's inputs the probe reads (fewer with fewer windows)
N_COMPONENTS = 16
#: the per-window session statistics the probe reads: lost pins always, the rest
#: where the loader measured them (host.data.extract.SESSION_STATS)
SESSION_FEATURES = ("lost_fraction", "brightness", "contrast", "interval_s")
METHOD = ("a logistic-regression probe over a PCA of the model's inputs and the "
          "session statistics (lost pins, brightness, contrast, frame interval), "
          f"trained to tell apart the recordings of one class; grouped CV over "
          f"{N_BLOCKS} contiguous blocks of each recording, windows within T frames of "
          "the tested block left out of training; balanced accuracy with a "
          "block-bootstrap 95 % interval")


def _position(ws, idx: np.ndarray) -> np.ndarray:
    fi = getattr(ws, "frame_index", None)
    return (fi if fi is not None and (fi[idx] >= 0).all() else ws.t_index)[idx]


def session_features(ws, with_lost: bool = True) -> np.ndarray:
    """(N, k) per-window means of the session statistics: the share of lost pins
    (with ``with_lost``), then brightness, contrast and the frame interval where the
    windows carry them (``ws.session``)."""
    cols = [ws.lost.reshape(len(ws), -1).mean(axis=1, dtype=np.float64)[:, None]] \
        if with_lost else []
    sess = getattr(ws, "session", None)
    if sess is not None:
        cols.append(np.asarray(sess, np.float64).mean(axis=1))
    return np.hstack(cols) if cols else np.zeros((len(ws), 0))


def _inputs(ws, model: str, uses_imu: bool) -> np.ndarray:
    X = model_inputs(ws, LAYOUT.get(model, "vectors"), uses_imu)
    return np.asarray(X, np.float64).reshape(len(ws), -1)


def _blocks(pos: np.ndarray, n_blocks: int) -> np.ndarray:
    """Block number (0 .. n_blocks-1) of each window, contiguous in time."""
    order = np.argsort(pos, kind="stable")
    blk = np.empty(len(pos), np.int64)
    blk[order] = np.arange(len(pos)) * n_blocks // max(len(pos), 1)
    return blk


def _fit_predict(Xm, Xs, y, train, test, seed):
    """Fit the probe on ``train`` windows, predict ``test`` ones."""
    from sklearn.linear_model import LogisticRegression
    from sklearn.preprocessing import StandardScaler

    parts_tr, parts_te = [], []
    if Xm.shape[1]:
        sc = StandardScaler().fit(Xm[train])
        a = sc.transform(Xm[train])
        k = int(min(N_COMPONENTS, len(a) - 1, Xm.shape[1]))
        # a is centred: its PCA from the (windows x windows) Gram matrix, cheap when
        # the windows are fewer than the inputs
        w, u = np.linalg.eigh(a @ a.T)
        top = np.argsort(w)[::-1][:k]
        comp = a.T @ (u[:, top] / np.sqrt(np.maximum(w[top], 1e-12)))    # (D, k) unit
        a, b = a @ comp, sc.transform(Xm[test]) @ comp
        s = a.std(axis=0) + 1e-9
        parts_tr.append(a / s)
        parts_te.append(b / s)
    if Xs.shape[1]:
        sc = StandardScaler().fit(Xs[train])
        parts_tr.append(sc.transform(Xs[train]))
        parts_te.append(sc.transform(Xs[test]))
    if len(np.unique(y[train])) < 2:
        return np.full(int(test.sum()), int(y[train][0]) if train.any() else -1)
    clf = LogisticRegression(C=1.0, max_iter=1000)
    clf.fit(np.hstack(parts_tr), y[train])
    return clf.predict(np.hstack(parts_te))


def _probe(Xm, Xs, unit: np.ndarray, pos: np.ndarray, T: int, margin: float, seed: int,
           n_boot: int) -> dict:
    """Grouped CV over contiguous blocks of each unit (recording): can the probe tell
    the units apart? The figures and the verdict."""
    ids = sorted(set(unit.tolist()))
    y = np.array([ids.index(u) for u in unit], np.int64)
    blk = np.zeros(len(unit), np.int64)
    for j in range(len(ids)):
        sel = np.flatnonzero(y == j)
        blk[sel] = _blocks(pos[sel], N_BLOCKS)
    pred = np.full(len(unit), -1, np.int64)
    for k in range(N_BLOCKS):
        test = blk == k
        train = ~test
        for j in range(len(ids)):         # leave out windows sharing frames with the test
            sel = y == j
            if not (test & sel).any():
                continue
            tp = pos[test & sel]
            near = sel & (pos > tp.min() - T) & (pos < tp.max() + T) & ~test
            train &= ~near
        if test.any() and train.any():
            pred[test] = _fit_predict(Xm, Xs, y, train, test, seed)
    correct = (pred == y).astype(np.float64)
    order = {u: np.flatnonzero(unit == u)[np.argsort(pos[unit == u], kind="stable")]
             for u in ids}
    rids, sums, counts, _ = block_bootstrap(correct, unit, T, order, n_boot, seed)
    per = {r: float(correct[unit == r].mean()) for r in rids}
    bal = float(np.mean(list(per.values())))
    boot = (sums / counts[None, :]).mean(axis=1)
    lo, hi = (float(x) for x in np.percentile(boot, [2.5, 97.5]))
    chance = 1.0 / len(ids)
    if lo > chance + margin:
        verdict = "flagged"
    elif hi <= chance + margin:
        verdict = "clear"
    else:
        verdict = "inconclusive"
    return {"balanced_accuracy": round(bal, 4),
            "balanced_accuracy_ci95": [round(lo, 4), round(hi, 4)],
            "chance": round(chance, 4), "per_recording": {r: round(v, 4) for r, v in per.items()},
            "n_windows": int(len(unit)), "verdict": verdict, "flagged": verdict == "flagged"}


def _thin(idx: np.ndarray, most: int, rng) -> np.ndarray:
    if len(idx) <= most:                    # an even thinning keeps the time order
        return idx
    return idx[np.sort(rng.choice(len(idx), most, replace=False))]


def identity_check(ws, task: str, model: str, hp: dict | None = None,
                   uses_imu: bool = False, seed: int = 0, margin: float = MARGIN) -> dict:
    """Run the check on the windows ``ws`` for a model of kind ``model`` (its input
    layout; ``hp`` is accepted for the callers' sake, the probe is the same for every
    kind). Returns a JSON-able dict: ``classes`` (per class: ``mode`` ``recordings``
    or ``one recording``, ``recordings``, ``verdict``, ``flagged``, the figures, and
    ``settle`` saying what data would settle an inconclusive or absent verdict),
    ``across_classes`` (where every class has one recording), ``verdict`` (flagged,
    clear, inconclusive or no verdict), ``flagged``, ``warning`` (None when not
    flagged), ``margin``, ``method``."""
    if not (0.0 <= margin < 1.0):
        raise TrainError(f"identity check: margin must be in [0, 1), got margin={margin!r}")
    out = {"flagged": False, "warning": None, "margin": margin, "classes": {},
           "verdict": "no verdict", "method": METHOD}
    if model == "rule" or task == "pressure" or ws.labels is None:
        out["skipped"] = ("a rule learns no recording" if model == "rule"
                          else "regression: recordings are not classes")
        return out
    T = ws.window
    labels = ws.labels.astype(str)
    rec = ws.recording_ids().astype(str)
    rng = np.random.default_rng(seed)
    classes = sorted(set(labels.tolist()) - {NO_TOUCH})
    need = N_BLOCKS * MIN_BLOCK
    Xm = Xs = None
    for c in classes:
        idx = _thin(np.flatnonzero(labels == c), MAX_WINDOWS, rng)
        ids = sorted(set(rec[idx].tolist()))
        entry = {"mode": "recordings" if len(ids) >= 2 else "one recording", "recordings": ids}
        out["classes"][c] = entry
        if len(ids) < 2:
            entry.update(verdict="no verdict", flagged=False,
                         settle=f"one recording of {c}: no second session to tell apart; "
                                f"record a second session of {c} to check")
            entry["skipped"] = entry["settle"]       # not run (the older readers' key)
            continue
        few = {r: int((rec[idx] == r).sum()) for r in ids if (rec[idx] == r).sum() < need}
        if few:
            entry.update(verdict="inconclusive", flagged=False, n_windows=int(len(idx)),
                         settle=f"too few contact windows in {few} (each recording needs "
                                f"{need}, {N_BLOCKS} blocks of {MIN_BLOCK}): record longer")
            entry["skipped"] = entry["settle"]
            continue
        if Xm is None:
            Xm, Xs = _inputs(ws, model, uses_imu), session_features(ws)
        entry.update(_probe(Xm[idx], Xs[idx], rec[idx], _position(ws, idx), T, margin, seed,
                            N_BOOT))
        if entry["verdict"] == "inconclusive":
            entry["settle"] = entry["inconclusive"] = (
                f"the interval spans chance + {margin}: longer recordings of {c} (more "
                f"windows) narrow it")
    _across(out, ws, classes, margin, seed, rng)
    verdicts = [e["verdict"] for e in out["classes"].values()]
    out["verdict"] = next((v for v in ("flagged", "inconclusive", "clear") if v in verdicts),
                          "no verdict")
    if "flagged" in verdicts:
        which = [c for c, e in out["classes"].items() if e.get("flagged")]
        out["flagged"] = True
        out["warning"] = (f"{WARNING}: a simple probe tells apart the recordings of class(es) "
                          f"{which} far above chance (record more sessions, or test on a "
                          f"separate recording)")
    return out


def _across(out, ws, classes, margin, seed, rng) -> None:
    """Where every class has one recording: the session statistics alone (not lost
    pins, which contact moves) across the classes' recordings."""
    labels, rec, T = ws.labels.astype(str), ws.recording_ids().astype(str), ws.window
    if len(classes) < 2 or any(e["mode"] != "one recording" for e in out["classes"].values()):
        return
    idx = np.concatenate([_thin(np.flatnonzero(labels == c), MAX_WINDOWS, rng)
                          for c in classes])
    Xs = session_features(ws, with_lost=False)
    if not Xs.shape[1]:
        out["across_classes"] = {"skipped": "these windows carry no session statistics"}
        return
    if min(int((rec[idx] == r).sum()) for r in set(rec[idx])) < N_BLOCKS * MIN_BLOCK:
        out["across_classes"] = {"skipped": "too few windows"}
        return
    res = _probe(np.zeros((len(idx), 0)), Xs[idx], rec[idx], _position(ws, idx), T, margin,
                 seed, N_BOOT)
    res["told_apart"] = res.pop("verdict") == "flagged"
    res.pop("flagged")
    res["note"] = ("the classes' recordings differ in brightness, contrast or frame "
                   "interval: a model could score by session; only a second session of a "
                   "surface can check" if res["told_apart"] else
                   "the session statistics alone do not tell the classes' recordings apart")
    out["across_classes"] = res


def verdict_lines(check: dict) -> list[str]:
    """One line per class of a check: its verdict and figures, or why there is none,
    and what data would settle it; then the across-classes comparison."""
    if check.get("skipped"):
        return [f"skipped: {check['skipped']}"]
    lines = []
    for c, e in sorted((check.get("classes") or {}).items()):
        verdict = e.get("verdict") or ("flagged" if e.get("flagged") else "not run"
                                       if "skipped" in e else "inconclusive"
                                       if e.get("inconclusive") else "not flagged")
        head = f"{c} ({e.get('mode', '?')}): {verdict}"
        if "balanced_accuracy" in e:
            ci = e.get("balanced_accuracy_ci95") or [float("nan")] * 2
            head += (f", balanced accuracy {e['balanced_accuracy']:.2f} [{ci[0]:.2f}, "
                     f"{ci[1]:.2f}] on {e['n_windows']} windows, chance {e['chance']:.2f}")
        why = e.get("settle") or e.get("skipped") or e.get("inconclusive")
        if why:
            head += f"; {why}"
        lines.append(head)
    a = check.get("across_classes")
    if a:
        if "skipped" in a:
            lines.append(f"across classes: not run, {a['skipped']}")
        else:
            ci = a["balanced_accuracy_ci95"]
            lines.append(f"across classes, session statistics alone: balanced accuracy "
                         f"{a['balanced_accuracy']:.2f} [{ci[0]:.2f}, {ci[1]:.2f}], chance "
                         f"{a['chance']:.2f}: {a['note']}")
    return lines


def warning_line(check: dict | None) -> str | None:
    """The one-line warning ``host train`` and ``host eval`` log (``logging``
    WARNING) when a check flagged, else None."""
    if not check or not check.get("flagged"):
        return None
    return (f"recording-identity check: {check.get('warning') or WARNING} "
            f"(host eval --identity shows the figures)")
