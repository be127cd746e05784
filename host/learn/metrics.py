"""Metrics of classifiers and regressors, one schema for every model kind
(``host train``, the CNN and ``host eval``), the slip detection latency, and the
95 % intervals of accuracy and MAE.

Intervals (:func:`add_intervals`, :func:`block_bootstrap`): neighbouring windows
share frames and lighting, so they are not independent, and an i.i.d. bootstrap
would give intervals that are too narrow. The windows of each recording are put in
time order and resampled in blocks of consecutive windows (circular block
bootstrap, stratified by recording: every resample keeps each recording's window
count). Block length per recording: ``max(T, ceil(sqrt(n)))`` windows for ``n``
windows of T frames (at least one window length, so a block spans the frames the
windows share; growing with n, so slow drifts stay inside blocks). Windows without a
time order (an ``.npz``) are resampled one at a time. ``B = 1000`` resamples, a
fixed seed, percentile interval. The metrics dicts gain ``accuracy_ci95`` (or
``mae_ci95``), ``n_windows``, ``block_windows``, ``ci_method`` and
``by_recording``: per recording its value, interval and window count.
"""
from __future__ import annotations

import numpy as np

from host.learn.tasks import TrainError, label_ids

__all__ = ["classification_metrics", "label_metrics", "regression_metrics", "slip_latency",
           "class_report", "block_bootstrap", "add_intervals", "block_length", "N_BOOT"]

#: bootstrap resamples of every interval
N_BOOT = 1000
CI_METHOD = "circular block bootstrap within each recording, 1000 resamples"


def block_length(n: int, T: int) -> int:
    """Windows per bootstrap block for ``n`` time-ordered windows of ``T`` frames:
    ``max(T, ceil(sqrt(n)))``, at most ``n``."""
    return int(max(1, min(n, max(int(T), int(np.ceil(np.sqrt(max(n, 0))))))))


def _order(ws, rows: np.ndarray) -> np.ndarray | None:
    """``rows`` sorted by time in their recording, or None without a time order."""
    fi = ws.frame_index if getattr(ws, "frame_index", None) is not None else ws.t_index
    if (fi[rows] < 0).any():
        return None
    return rows[np.lexsort((ws.t_index[rows], fi[rows]))]


def block_bootstrap(values: np.ndarray, recordings: np.ndarray, T: int, ordered=None,
                    n_boot: int = N_BOOT, seed: int = 0, block: int | None = None
                    ) -> tuple[list[str], np.ndarray, np.ndarray, list[int]]:
    """Circular block bootstrap of per-window ``values`` within each recording.

    ``recordings``: (N,) recording id per window; ``ordered``: a dict id -> window
    indices in time order (None: the order given, one window per block, i.e. an
    i.i.d. bootstrap when a recording has no order). ``block``: windows per block
    (None: :func:`block_length`). Returns (ids, sums (n_boot, R) of each resampled
    recording's values, counts (R,), block lengths (R,))."""
    values = np.asarray(values, np.float64)
    rec = np.asarray(recordings).astype(str)
    ids = sorted(set(rec.tolist()))
    rng = np.random.default_rng(seed)
    sums = np.zeros((n_boot, len(ids)))
    counts = np.zeros(len(ids), np.int64)
    blocks = []
    for j, r in enumerate(ids):
        idx = (ordered or {}).get(r)
        if idx is None:
            idx, L = np.flatnonzero(rec == r), 1
        else:
            L = block_length(len(idx), T) if block is None else int(min(block, len(idx)))
        v = values[idx]
        n = len(v)
        nb = -(-n // L)
        starts = rng.integers(0, n, size=(n_boot, nb))
        take = (starts[:, :, None] + np.arange(L)[None, None, :]).reshape(n_boot, -1)[:, :n] % n
        sums[:, j] = v[take].sum(axis=1)
        counts[j] = n
        blocks.append(int(L))
    return ids, sums, counts, blocks


def _ci(x: np.ndarray) -> list[float]:
    lo, hi = np.percentile(x, [2.5, 97.5]) if len(x) else (0.0, 0.0)
    return [round(float(lo), 6), round(float(hi), 6)]


def add_intervals(m: dict, ws, values, key: str = "accuracy", n_boot: int = N_BOOT,
                  seed: int = 0) -> dict:
    """Add to the metrics dict ``m`` the 95 % interval of ``key`` (the mean of the
    per-window ``values``: 1/0 correct for accuracy, absolute errors for MAE), the
    window count and the same per recording (see the module doc). Returns ``m``."""
    values = np.asarray(values, np.float64)
    n = len(values)
    m["n_windows"] = int(n)
    if n == 0:
        m[f"{key}_ci95"] = None
        m["by_recording"] = {}
        return m
    rec = ws.recording_ids() if hasattr(ws, "recording_ids") else np.zeros(n, object)
    rec = np.asarray(rec).astype(str)
    ordered = {}
    for r in set(rec.tolist()):
        o = _order(ws, np.flatnonzero(rec == r))
        if o is not None:
            ordered[r] = o
    ids, sums, counts, blocks = block_bootstrap(values, rec, ws.window, ordered, n_boot, seed)
    m[f"{key}_ci95"] = _ci(sums.sum(axis=1) / n)
    m["block_windows"] = int(max(blocks))
    m["ci_method"] = CI_METHOD
    by = {}
    for j, r in enumerate(ids):
        sel = rec == r
        entry = {key: round(float(values[sel].mean()), 6),
                 f"{key}_ci95": _ci(sums[:, j] / counts[j]), "n_windows": int(counts[j]),
                 "block_windows": blocks[j]}
        if getattr(ws, "labels", None) is not None:
            names, c = np.unique(ws.labels[sel].astype(str), return_counts=True)
            entry["labels"] = {str(a): int(b) for a, b in zip(names, c)}
        by[r] = entry
    m["by_recording"] = by
    return m


def classification_metrics(true_ids: np.ndarray, pred_ids: np.ndarray, classes: list[str],
                           true_labels=None) -> dict:
    """Accuracy, macro F1, per-class precision / recall / F1 and the confusion
    matrix (rows: true class, columns: predicted) over ``classes``; true labels
    the model never saw (id -1) count as errors and get their own row."""
    true_ids = np.asarray(true_ids, np.int64)
    pred_ids = np.asarray(pred_ids, np.int64)
    n = len(true_ids)
    C = len(classes)
    rows = list(classes)
    unknown = []
    if true_labels is not None and (true_ids < 0).any():
        unknown = sorted({str(x) for x, t in zip(true_labels, true_ids) if t < 0})
        rows += unknown
    conf = np.zeros((len(rows), C), np.int64)
    for t, p, lab in zip(true_ids, pred_ids,
                         true_labels if true_labels is not None else [None] * n):
        r = t if t >= 0 else (C + unknown.index(str(lab)) if lab is not None else None)
        if r is not None and 0 <= p < C:
            conf[r, p] += 1
    per = {}
    for i, c in enumerate(classes):
        tp = int(conf[i, i])
        fp = int(conf[:, i].sum() - tp)
        fn = int(conf[i].sum() - tp)
        prec = tp / (tp + fp) if tp + fp else 0.0
        rec = tp / (tp + fn) if tp + fn else 0.0
        f1 = 2 * prec * rec / (prec + rec) if prec + rec else 0.0
        per[c] = {"precision": round(prec, 6), "recall": round(rec, 6), "f1": round(f1, 6),
                  "support": int(conf[i].sum())}
    present = [c for c in classes if per[c]["support"] > 0]
    macro = float(np.mean([per[c]["f1"] for c in present])) if present else 0.0
    acc = float((true_ids == pred_ids).mean()) if n else 0.0
    return {"n": int(n), "accuracy": round(acc, 6), "macro_f1": round(macro, 6),
            "per_class": per, "confusion": {"labels": rows, "predicted": list(classes),
                                            "matrix": conf.tolist()}}


def label_metrics(true_labels, pred_ids, classes: list[str]) -> dict:
    """:func:`classification_metrics` of predicted class ids against true labels
    (strings; a label not in ``classes`` gets its own confusion row)."""
    labels = [str(x) for x in true_labels]
    return classification_metrics(label_ids(labels, classes), pred_ids, classes, labels)


def regression_metrics(y: np.ndarray, pred: np.ndarray) -> dict:
    """MAE, RMSE, the target range and MAE as a share of it."""
    y = np.asarray(y, np.float64)
    pred = np.asarray(pred, np.float64)
    err = pred - y
    rng = float(y.max() - y.min()) if len(y) else 0.0
    mae = float(np.abs(err).mean()) if len(y) else 0.0
    return {"n": int(len(y)), "mae": round(mae, 6),
            "rmse": round(float(np.sqrt((err ** 2).mean())) if len(y) else 0.0, 6),
            "target_range": round(rng, 6),
            "mae_of_range": round(mae / rng, 6) if rng > 0 else None,
            "mae_predict_mean": round(float(np.abs(y - y.mean()).mean()) if len(y) else 0.0, 6)}


def slip_latency(ws, slip_pred, slip_label: str = "slip") -> dict:
    """Detection latency of slip onsets, in frames.

    An onset is a window whose label is ``slip_label`` while the window ending one
    frame earlier in the same trial is not. It is detected at the first window of
    its slip run (same trial, consecutive frames, slip label) that ``slip_pred``
    marks as slip; the latency is that window's last frame minus the onset frame
    (0: the decision made on the onset frame itself). A run with no such window is
    missed. Windows without a time order (``t_index`` -1) are skipped.
    """
    slip_pred = np.asarray(slip_pred, bool)
    if ws.labels is None:
        raise TrainError("slip_latency needs labelled windows (task slip)")
    is_slip = np.array([str(x) == slip_label for x in ws.labels])
    lat, missed = [], 0
    for g in np.unique(ws.groups):
        idx = np.flatnonzero((ws.groups == g) & (ws.t_index >= 0))
        if len(idx) < 2:
            continue
        idx = idx[np.argsort(ws.t_index[idx], kind="stable")]
        t = ws.t_index[idx]
        s = is_slip[idx]
        p = slip_pred[idx]
        for k in range(1, len(idx)):
            if not (s[k] and not s[k - 1] and t[k] == t[k - 1] + 1):
                continue
            j, found = k, None
            while j < len(idx) and s[j] and (j == k or t[j] == t[j - 1] + 1):
                if p[j]:
                    found = int(t[j] - t[k])
                    break
                j += 1
            if found is None:
                missed += 1
            else:
                lat.append(found)
    a = np.asarray(lat, np.float64)
    return {"onsets": len(lat) + missed, "detected": len(lat), "missed": missed,
            "median_frames": float(np.median(a)) if len(a) else None,
            "p90_frames": float(np.percentile(a, 90)) if len(a) else None,
            "max_frames": int(a.max()) if len(a) else None,
            "latencies_frames": [int(x) for x in lat]}


def class_report(task: str, ws, true_ids, probs, classes) -> dict:
    pred = np.argmax(probs, axis=1) if len(probs) else np.zeros(0, np.int64)
    m = classification_metrics(true_ids, pred, classes, ws.labels)
    add_intervals(m, ws, np.asarray(true_ids) == pred)
    if task == "slip" and "slip" in classes:
        m["slip_f1"] = m["per_class"]["slip"]["f1"]
        m["latency"] = slip_latency(ws, pred == classes.index("slip"))
    return m

