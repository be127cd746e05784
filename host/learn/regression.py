"""Ridge regressors from all pin vectors (pressure, depth, shear), with grouped or
shuffled cross-validation, exported to ONNX for ``device.pi.models.regressor``."""
from __future__ import annotations

import numpy as np

from device.pi.vision.features import vector_features


def clean(X: np.ndarray) -> np.ndarray:
    """float32 with NaN/inf replaced by 0: a lost pin carries no displacement."""
    return np.nan_to_num(np.asarray(X, dtype=np.float32), nan=0.0, posinf=0.0, neginf=0.0)


def ridge_pipeline(alpha: float = 150.0):
    from sklearn.linear_model import Ridge
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler
    return make_pipeline(StandardScaler(), Ridge(alpha=alpha))


def cross_validate(X, y, groups=None, alpha: float = 150.0, k: int = 5, seed: int = 0) -> dict:
    """MAE of Ridge under K-fold CV (grouped by ``groups`` when given, else
    shuffled), against the MAE of predicting the training mean."""
    from sklearn.model_selection import GroupKFold, KFold

    X, y = clean(X), np.asarray(y, dtype=np.float64)
    if X.shape[0] != y.shape[0]:
        raise ValueError(f"X has {X.shape[0]} rows but y has {y.shape[0]}")
    if not np.isfinite(y).all():
        raise ValueError("targets y contain NaN or inf")
    n_groups = len(np.unique(groups)) if groups is not None else X.shape[0]
    if n_groups < k:
        raise ValueError(f"--cv {k} needs at least {k} groups, got {n_groups}")
    if groups is not None:
        splits = GroupKFold(n_splits=k).split(X, y, groups)
    else:
        splits = KFold(n_splits=k, shuffle=True, random_state=seed).split(X)
    pred = np.zeros_like(y)
    base = np.zeros_like(y)
    for tr, te in splits:
        pred[te] = ridge_pipeline(alpha).fit(X[tr], y[tr]).predict(X[te])
        base[te] = y[tr].mean()
    mae = float(np.abs(pred - y).mean())
    mae_mean = float(np.abs(base - y).mean())
    return {"mae": mae, "mae_predict_mean": mae_mean,
            "ratio": mae_mean / mae if mae > 0 else float("inf"), "folds": k,
            "grouped": groups is not None, "alpha": alpha, "n": int(len(y))}


def export_regressor(X, y, out_dir, kind: str = "pressure", alpha: float = 150.0,
                     extra: dict | None = None):
    """Fit on all of X, y and write ONNX + manifest (scaler folded in)."""
    from host.learn.onnx_io import sklearn_to_onnx, write_model

    X, y = clean(X), np.asarray(y, dtype=np.float64)
    pipe = ridge_pipeline(alpha).fit(X, y)
    info = {"T": 1, "alpha": alpha, "target_mean": float(y.mean()),     # one frame per row
            "target_range": [float(y.min()), float(y.max())],
            "input_clip": [X.min(axis=0).tolist(), X.max(axis=0).tolist()]}
    info.update(extra or {})
    return write_model(sklearn_to_onnx(pipe, X.shape[1]), out_dir, kind=kind,
                       n_features=X.shape[1], extra=info), pipe


def vectors_npz_features(vectors: np.ndarray) -> np.ndarray:
    """(N, M, 2) vectors (NaN = lost) -> (N, 3M) regressor inputs, as on the Pi."""
    v = np.asarray(vectors, dtype=np.float32)
    lost = ~np.isfinite(v).all(axis=-1)
    return np.stack([vector_features(v[i], lost[i]) for i in range(v.shape[0])])
