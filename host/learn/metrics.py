"""Metrics of classifiers and regressors, one schema for every model kind
(``host train``, the CNN and ``host eval``), and the slip detection latency."""
from __future__ import annotations

import numpy as np

from host.learn.tasks import TrainError, label_ids

__all__ = ["classification_metrics", "label_metrics", "regression_metrics", "slip_latency",
           "class_report"]


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
    if task == "slip" and "slip" in classes:
        m["slip_f1"] = m["per_class"]["slip"]["f1"]
        m["latency"] = slip_latency(ws, pred == classes.index("slip"))
    return m

