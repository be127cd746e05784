"""Grouped K-fold cross-validation of a task's model on training windows."""
from __future__ import annotations

import sys

import numpy as np

from host.data.splits import group_kfold

from host.data.windows import DataError
from host.learn.estimators import (default_uses_imu, fit_estimator, fit_rule, hyperparameters,
                                   rule_probs)
from host.extras import need
from host.learn.inputs import augment_rotations, model_inputs
from host.learn.metrics import class_report, regression_metrics
from host.learn.pressure import bootstrap_mae
from host.learn.tasks import LAYOUT, TrainError, check_int, label_ids

__all__ = ["cross_validate_model", "CI_OVER_TRIALS"]

#: how a regressor's CV interval is made: the held-out windows of a trial share its
#: presses, so whole trials are resampled (:func:`host.learn.pressure.bootstrap_mae`)
CI_OVER_TRIALS = "bootstrap over trials (groups), 2000 resamples, percentile 95 %"


def cross_validate_model(cfg, ws, hp: dict | None = None, uses_imu: bool | None = None,
                         classes: list[str] | None = None, progress: bool = True) -> dict:
    """Grouped K-fold CV (whole trials per fold, :func:`host.data.splits.group_kfold`)
    of the kind ``cfg.model`` (a :class:`host.learn.config.TrainConfig`: its task,
    ``cv`` folds, seed, ``augment``, profile) with hyperparameters ``hp``
    (:func:`hyperparameters`; None: the kind's defaults): pooled held-out metrics plus
    each fold's accuracy (or MAE; a regressor's pooled MAE also gets ``mae_ci95``, its
    95 % interval resampling whole trials). ``augment`` rotated copies are added to
    each fold's training part only."""
    tqdm = need("tqdm").tqdm

    task, model, seed, augment, profile = cfg.task, cfg.model, cfg.seed, cfg.augment, cfg.profile
    k = check_int("cv", cfg.cv, 2)
    if len(ws) < k:
        raise TrainError(f"cv={k} folds need at least {k} windows, the data have {len(ws)}")
    try:
        folds = list(group_kfold(ws, k, seed))
    except DataError as exc:
        raise TrainError(f"cv={k}: {exc}") from None
    layout = LAYOUT[model]
    uses_imu = default_uses_imu(model, ws) if uses_imu is None else uses_imu
    X = model_inputs(ws, layout, uses_imu)
    hp = hyperparameters(model) if hp is None else hp
    regression = task == "pressure"
    if not regression:
        classes = classes or sorted({str(x) for x in ws.labels})
        y = label_ids(ws.labels, classes)
        pooled = np.zeros((len(ws), len(classes)))
    else:
        y = np.asarray(ws.targets, np.float64)
        pooled = np.zeros(len(ws))
    per_fold = []
    for f, (tr, te) in enumerate(tqdm(folds, desc=f"cv {k} folds", unit="fold",
                                      disable=not progress or None, file=sys.stderr,
                                      leave=False)):
        if not regression:
            present = np.unique(y[tr])
            if len(present) < 2:
                raise TrainError(f"cv={k}: fold {f} trains on one class only "
                                 f"({classes[int(present[0])]!r}); use fewer folds or more "
                                 f"trials per class")
        if model == "rule":
            rc = fit_rule(task, ws.subset(tr), classes)
            out = rule_probs(rc, X[te])
        else:
            Xf, yf = X[tr], y[tr]
            if augment:
                a = augment_rotations(ws.subset(tr), augment, profile)
                Xf = model_inputs(a, layout, uses_imu)
                yf = (np.asarray(a.targets, np.float64) if regression
                      else label_ids(a.labels, classes))
            pipe, _ = fit_estimator(task, model, Xf, yf, 0 if regression else len(classes), hp,
                                    seed)
            if regression:
                out = pipe.predict(X[te]).reshape(-1)
            else:
                out = np.zeros((len(te), len(classes)))
                out[:, pipe.steps[-1][1].classes_.astype(int)] = pipe.predict_proba(X[te])
        pooled[te] = out
        if regression:
            per_fold.append(regression_metrics(y[te], out)["mae"])
        else:
            per_fold.append(float((np.argmax(out, 1) == y[te]).mean()))
    if regression:
        res = regression_metrics(y, pooled)
        res["fold_mae"] = [round(x, 6) for x in per_fold]
        res["mae_ci95"] = bootstrap_mae(np.abs(pooled - y), ws.groups, seed=seed)
        res["ci_method"] = CI_OVER_TRIALS
        res["trials"] = int(len(np.unique(ws.groups)))
    else:
        res = class_report(task, ws, y, pooled, classes)
        res["fold_accuracy"] = [round(x, 6) for x in per_fold]
    res.update({"folds": k, "grouped": True,
                "fold_mean": round(float(np.mean(per_fold)), 6),
                "fold_std": round(float(np.std(per_fold)), 6)})
    return res

