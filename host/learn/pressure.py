"""Pressure from all pin vectors, with untracked pins read as missing, not as zero.

The runtime gives a lost (untracked) pin the vector (0, 0) (``device.pi.vision.layout``),
and so do recorded vector sets (``roboskin/vectors2.npy``: about a quarter of the
vectors). A model that reads those zeros as "this pin did not move" learns which pins
a recording happens to lose. Here the first, fixed layer (:class:`TrackedPins`)
fills each untracked pin with what its tracked neighbours in the data say it would
read: a per-pin line ``a + b * s`` in the frame's mean tracked displacement ``s``,
fitted on the training frames where that pin was tracked. It appends, per frame,
the share of pins tracked and ``s``. Its ONNX graph reads the runtime's ``vectors``
window encoding as it is, so ``device.pi.models.regressor.Regressor`` runs the
model unchanged, for any pin count (146 for the hard-plate set, 133 for roboskin).

Models (``kind``):

* ``gbt`` (default): TrackedPins -> scikit-learn's GradientBoostingRegressor with
  its default settings (100 trees of depth 3; fixed, not tuned on the data). The
  installed skl2onnx cannot convert HistGradientBoostingRegressor (it writes
  numpy integers into the tree node attributes), so it is not used;
* ``ridge``: TrackedPins -> standard scaling -> Ridge, alpha chosen by grouped
  K-fold inside the training data only (:func:`nested_alpha`).

    python -m host.learn.pressure --vectors ../shared/data/roboskin/vectors2.npy \
        --pressures ../shared/data/roboskin/pressures2.npy --cv 5 --json

prints the grouped (by trial) K-fold CV MAE with a 95 % bootstrap interval over
trials, beside the MAE of the former model (Ridge alpha 150 on the raw vectors);
``--out DIR`` also writes the model fitted on all trials (ONNX + manifest), checked
against scikit-learn through ONNX Runtime. ``--npz FILE`` writes the set as an
``.npz`` data spec instead (groups = trials), for the command users run::

    host train --task pressure --data hard_plate.npz --cv 5 --json --out DIR

which trains the default pressure model, ``gbt``, and reports the grouped CV MAE
with its interval over trials (``metrics.cv``).
"""
from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from host.learn.tasks import TrainError

__all__ = ["check_pin_count", "KINDS", "tracked_class", "pressure_pipeline", "nested_alpha", "fit_pressure",
           "cross_validate_pressure", "bootstrap_mae", "checked_onnx", "export_pressure",
           "hard_plate", "hard_plate_npz",
           "main"]


def check_pin_count(ws, profile, where: str = "the data") -> None:
    """Refuse, in one line, windows whose marker count is not the sensor profile's
    pin count (e.g. 133-marker data with a 130-pin profile): the leg refuses such a
    model, so training should not make it. ``profile``: a built-in name, a ``.toml``
    path or a profile record (with ``n_pins``)."""
    if isinstance(profile, dict):
        n, name = int(profile["n_pins"]), profile.get("name", "?")
    else:
        from device.profile import load_pipeline_profile
        prof = load_pipeline_profile(profile if profile is not None else "roboskin")
        n, name = prof.n_pins, profile
    if ws.n_pins != n:
        raise TrainError(f"{where} has {ws.n_pins} markers a frame but the profile {name} "
                         f"has n_pins={n}: give the profile the data was recorded with "
                         f"(--profile), or record the data with this one")

KINDS = ("gbt", "ridge", "ridge150-raw")
#: the alphas :func:`nested_alpha` chooses from
ALPHAS = tuple(float(a) for a in np.logspace(-1, 4, 11))
#: ONNX Runtime against scikit-learn: largest difference allowed, as a share of the
#: target range (float32 graph against float64 sklearn)
PARITY_OF_RANGE = 1e-4


def tracked_class():
    """:class:`TrackedPins`, defined on first use (sklearn/skl2onnx are host-only)."""
    from host.learn.layers import defined_once
    return defined_once("TrackedPins", _define_tracked)


def _frame_stats(v: np.ndarray):
    """(rows, M, 2) float32 -> tracked (rows, M) float32 0/1, s (rows,) mean tracked |v|."""
    mag = np.sqrt((v * v).sum(axis=2, dtype=np.float32))
    t = (mag > 0).astype(np.float32)
    n = t.sum(axis=1)
    s = (mag * t).sum(axis=1) / np.maximum(n, np.float32(1.0))
    return t, s.astype(np.float32)


def _define_tracked():
    from sklearn.base import BaseEstimator, TransformerMixin

    class TrackedPins(TransformerMixin, BaseEstimator):
        """Fill untracked pins (vector exactly (0, 0)) from the frame's tracked ones.

        Input: the ``vectors`` window encoding, (N, T*M*2 [+ extra]); columns past
        T*M*2 (the IMU) are passed through. Per frame, ``s`` is the mean |v| over the
        tracked pins (0 when none is). ``fit`` fits, for each pin and component, the
        line ``a + b * s`` over the training frames where the pin was tracked (the
        mean when it has fewer than 3 such frames or ``s`` does not vary there; 0
        when it never was). ``transform`` keeps tracked vectors, puts the line's
        value on untracked ones, and appends per frame the tracked share and ``s``:
        (N, T*M*2 + 2T [+ extra]). float32 throughout, as the ONNX graph."""

        def __init__(self, T: int = 1, n_pins: int = 133):
            self.T = T
            self.n_pins = n_pins

        def _split(self, X):
            X = np.asarray(X, np.float32)
            w = int(self.T) * int(self.n_pins) * 2
            if X.ndim != 2 or X.shape[1] < w:
                raise TrainError(f"TrackedPins(T={self.T}, n_pins={self.n_pins}) needs at "
                                 f"least {w} input columns, got shape {X.shape}")
            return X[:, :w].reshape(-1, int(self.n_pins), 2), X[:, w:]

        def fit(self, X, y=None):
            v, rest = self._split(X)
            t, s = _frame_stats(v)
            M = int(self.n_pins)
            a = np.zeros((M, 2), np.float64)
            b = np.zeros((M, 2), np.float64)
            for m in range(M):
                ok = t[:, m] > 0
                if not ok.any():
                    continue
                if ok.sum() >= 3 and s[ok].std() > 0:
                    coef = np.polyfit(s[ok].astype(np.float64), v[ok, m].astype(np.float64), 1)
                    b[m], a[m] = coef[0], coef[1]
                else:
                    a[m] = v[ok, m].mean(axis=0)
            self.a_, self.b_ = a.astype(np.float32), b.astype(np.float32)
            self.n_features_in_ = int(np.asarray(X).shape[1])
            self.n_features_out_ = self.n_features_in_ + 2 * int(self.T)
            return self

        def transform(self, X):
            v, rest = self._split(X)
            if np.asarray(X).shape[1] != self.n_features_in_:
                raise TrainError(f"TrackedPins was fitted on {self.n_features_in_} columns, "
                                 f"got {np.asarray(X).shape[1]}")
            t, s = _frame_stats(v)
            fill = self.a_[None] + self.b_[None] * s[:, None, None]
            out = v + fill * (np.float32(1.0) - t)[:, :, None]
            N, T = len(X), int(self.T)
            share = (t.sum(axis=1) / np.float32(self.n_pins)).astype(np.float32)
            return np.concatenate([out.reshape(N, -1), rest, share.reshape(N, T),
                                   s.reshape(N, T)], axis=1).astype(np.float32)

    _register_tracked(TrackedPins)
    return TrackedPins


def _register_tracked(cls) -> None:
    from skl2onnx import update_registered_converter
    from skl2onnx.common.data_types import FloatTensorType

    def shape(operator):
        operator.outputs[0].type = FloatTensorType([None, operator.raw_operator.n_features_out_])

    update_registered_converter(cls, "TacfootTrackedPins", shape, _tracked_to_onnx)


def _tracked_to_onnx(scope, operator, container):
    """ONNX for :class:`TrackedPins`: the same float32 numbers as its transform."""
    from host.learn.layers import OnnxGraph

    op = operator.raw_operator
    T, M = int(op.T), int(op.n_pins)
    w = T * M * 2
    g = OnnxGraph(scope, container)
    const, fconst, node = g.ints, g.floats, g.node

    x = operator.inputs[0].full_name
    v = node("Reshape", [node("Slice", [x, const([0]), const([w]), const([1])]),
                         const([-1, M, 2])])                                  # (NT, M, 2)
    mag = node("Sqrt", [node("ReduceSumSquare", [v], axes=[2], keepdims=1)])  # (NT, M, 1)
    t = node("Cast", [node("Greater", [mag, fconst([0.0], [])])], to=1)      # float 0/1
    n = node("ReduceSum", [t, const([1])], keepdims=1)                        # (NT, 1, 1)
    s = node("Div", [node("ReduceSum", [node("Mul", [mag, t]), const([1])], keepdims=1),
                     node("Max", [n, fconst([1.0], [])])])                    # (NT, 1, 1)
    fill = node("Add", [fconst(op.a_, [1, M, 2]), node("Mul", [fconst(op.b_, [1, M, 2]), s])])
    out = node("Add", [v, node("Mul", [fill, node("Sub", [fconst([1.0], []), t])])])
    parts = [node("Reshape", [out, const([-1, w])])]
    if op.n_features_in_ > w:
        parts.append(node("Slice", [x, const([w]), const([op.n_features_in_]), const([1])]))
    parts += [node("Reshape", [node("Div", [n, fconst([float(M)], [])]), const([-1, T])]),
              node("Reshape", [s, const([-1, T])])]
    container.add_node("Concat", parts, operator.outputs[0].full_name, axis=1,
                       name=scope.get_unique_operator_name("Concat"))


def pressure_pipeline(kind: str, T: int, n_pins: int, alpha: float = 150.0, seed: int = 0):
    """An unfitted pipeline of ``kind`` (:data:`KINDS`) over ``vectors`` windows."""
    from sklearn.ensemble import GradientBoostingRegressor
    from sklearn.linear_model import Ridge
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    if kind == "gbt":
        return make_pipeline(tracked_class()(T, n_pins),
                             GradientBoostingRegressor(random_state=seed))
    if kind == "ridge":
        return make_pipeline(tracked_class()(T, n_pins), StandardScaler(), Ridge(alpha=alpha))
    if kind == "ridge150-raw":          # the former model: untracked pins read as zero
        return make_pipeline(StandardScaler(), Ridge(alpha=150.0))
    raise TrainError(f"kind must be one of {list(KINDS)}, got kind={kind!r}")


def _folds(groups: np.ndarray, k: int, seed: int):
    """K folds of whole groups, shuffled by ``seed``: [(train idx, test idx)]."""
    ids = np.unique(groups)
    if len(ids) < k:
        raise TrainError(f"cv={k} folds need at least {k} groups (trials), got {len(ids)}")
    order = np.random.default_rng(seed).permutation(ids)
    fold_of = {g: i % k for i, g in enumerate(order)}
    f = np.array([fold_of[g] for g in groups])
    return [(np.flatnonzero(f != i), np.flatnonzero(f == i)) for i in range(k)]


def nested_alpha(X, y, groups, T: int, n_pins: int, k: int = 4, seed: int = 0) -> float:
    """The Ridge alpha (of :data:`ALPHAS`) with the lowest grouped ``k``-fold MAE
    on this (training) data alone."""
    best, best_mae = ALPHAS[0], np.inf
    folds = _folds(groups, min(k, len(np.unique(groups))), seed + 1)
    for a in ALPHAS:
        err = 0.0
        for tr, te in folds:
            p = pressure_pipeline("ridge", T, n_pins, a).fit(X[tr], y[tr]).predict(X[te])
            err += float(np.abs(p - y[te]).sum())
        if err < best_mae:
            best, best_mae = a, err
    return best


def fit_pressure(kind: str, X, y, groups, T: int, n_pins: int, seed: int = 0):
    """(fitted pipeline, info) for ``kind``; ridge picks its alpha on ``X`` alone."""
    info = {"model": kind}
    alpha = 150.0
    if kind == "ridge":
        alpha = nested_alpha(X, y, groups, T, n_pins, seed=seed)
        info["alpha"] = alpha
    return pressure_pipeline(kind, T, n_pins, alpha, seed).fit(X, y), info


def _check_xy(X, y, groups):
    X = np.asarray(X, np.float32)
    y = np.asarray(y, np.float64).reshape(-1)
    groups = np.asarray(groups).reshape(-1)
    if X.ndim != 2 or not (len(X) == len(y) == len(groups)):
        raise TrainError(f"X {X.shape}, y {y.shape} and groups {groups.shape} must have one "
                         f"row per window")
    if not np.isfinite(y).all():
        raise TrainError(f"targets y: {int((~np.isfinite(y)).sum())} are NaN or inf")
    return np.nan_to_num(X, nan=0.0, posinf=0.0, neginf=0.0), y, groups


def bootstrap_mae(abs_err, groups, n_boot: int = 2000, seed: int = 0) -> list[float]:
    """95 % interval of the MAE, resampling whole groups (trials) with replacement."""
    abs_err, groups = np.asarray(abs_err, np.float64), np.asarray(groups)
    ids, inv = np.unique(groups, return_inverse=True)
    tot = np.bincount(inv, abs_err, len(ids))
    cnt = np.bincount(inv, None, len(ids))
    pick = np.random.default_rng(seed).integers(0, len(ids), (int(n_boot), len(ids)))
    maes = tot[pick].sum(axis=1) / cnt[pick].sum(axis=1)
    return [round(float(q), 3) for q in np.percentile(maes, [2.5, 97.5])]


def cross_validate_pressure(X, y, groups, kind: str = "gbt", T: int = 1,
                            n_pins: int | None = None, k: int = 5, seed: int = 0) -> dict:
    """Grouped ``k``-fold CV (whole trials per fold): pooled MAE, its 95 % bootstrap
    interval over trials, each fold's MAE, and the MAE of predicting the training
    mean. Ridge's alpha is chosen inside each training part."""
    X, y, groups = _check_xy(X, y, groups)
    n_pins = n_pins or X.shape[1] // (2 * T)
    pred, base = np.zeros_like(y), np.zeros_like(y)
    fold_mae, alphas = [], []
    for tr, te in _folds(groups, k, seed):
        pipe, info = fit_pressure(kind, X[tr], y[tr], groups[tr], T, n_pins, seed)
        pred[te] = pipe.predict(X[te])
        base[te] = y[tr].mean()
        fold_mae.append(round(float(np.abs(pred[te] - y[te]).mean()), 3))
        if "alpha" in info:
            alphas.append(info["alpha"])
    err = np.abs(pred - y)
    res = {"kind": kind, "mae": round(float(err.mean()), 3),
           "mae_ci95": bootstrap_mae(err, groups, seed=seed),
           "mae_predict_mean": round(float(np.abs(base - y).mean()), 3),
           "fold_mae": fold_mae, "folds": k, "grouped": True,
           "trials": int(len(np.unique(groups))), "n": int(len(y))}
    if alphas:
        res["fold_alpha"] = alphas
    return res


def checked_onnx(pipe, X, y):
    """(ONNX model, parity record) of the fitted pipeline ``pipe``, after checking
    that ONNX Runtime gives its predictions on ``X`` within ``PARITY_OF_RANGE`` of
    the range of the targets ``y`` (TrainError otherwise)."""
    from host.learn.onnx_io import run_onnx, session, sklearn_to_onnx

    X = np.asarray(X, np.float32)
    y = np.asarray(y, np.float64).reshape(-1)
    model = sklearn_to_onnx(pipe, X.shape[1])
    got = run_onnx(session(model.SerializeToString()), X).reshape(-1)
    want = pipe.predict(X)
    rng = float(y.max() - y.min()) or 1.0
    diff = float(np.abs(got - want).max()) if len(X) else 0.0
    parity = {"max_abs_diff": diff, "of_range": diff / rng, "n": int(len(X))}
    if not diff <= PARITY_OF_RANGE * rng:
        raise TrainError(f"the ONNX pressure model differs from scikit-learn by {diff:g} "
                         f"(more than {PARITY_OF_RANGE:g} of the target range {rng:g})")
    return model, parity


def export_pressure(X, y, groups, out_dir, kind: str = "gbt", shape: tuple = (1, None),
                    seed: int = 0, extra: dict | None = None):
    """Fit ``kind`` on all windows and write ONNX + manifest (kind ``pressure``,
    ``input_layout`` vectors, ``shape`` = (T, pins), pins None: from X) to
    ``out_dir``, after checking that ONNX Runtime
    gives scikit-learn's predictions within ``PARITY_OF_RANGE`` of the target
    range (TrainError otherwise). Returns (folder, pipeline, parity record)."""
    from host.learn.onnx_io import write_model

    X, y, groups = _check_xy(X, y, groups)
    T, n_pins = shape
    n_pins = n_pins or X.shape[1] // (2 * T)
    pipe, info = fit_pressure(kind, X, y, groups, T, n_pins, seed)
    model, parity = checked_onnx(pipe, X, y)
    # the runtime clips inputs to this range: 0 (an untracked pin) stays inside it
    lo = np.minimum(X.min(axis=0), 0.0)
    hi = np.maximum(X.max(axis=0), 0.0)
    doc = {"model": kind, "task": "pressure", "T": int(T), "input_layout": "vectors",
           "uses_imu": False, "n_pins": int(n_pins), "output": "variable",
           "output_kind": "value", "variant": "float", "untracked_pins": "filled (TrackedPins)"
           if kind != "ridge150-raw" else "read as zero",
           "target_mean": float(y.mean()), "target_range": [float(y.min()), float(y.max())],
           "input_clip": [lo.tolist(), hi.tolist()], "onnx_parity": parity, **info,
           **(extra or {})}
    out = write_model(model, out_dir, kind="pressure", n_features=X.shape[1], extra=doc)
    from host.learn.card import write_model_docs
    write_model_docs(out)                  # README.md (the model card) and train.toml
    return out, pipe, parity


def pressing_set(vectors_path, pressures_path):
    """(vectors, loads) of a pressing set, checked: vectors (trials, depths, M, 2) and
    loads (trials, 2, depths); a TrainError naming the file otherwise."""
    v = np.load(vectors_path, allow_pickle=False)
    p = np.load(pressures_path, allow_pickle=False)
    if v.ndim != 4 or v.shape[-1] != 2:
        raise TrainError(f"{vectors_path}: vectors must be (trials, depths, M, 2), got {v.shape}")
    if p.shape != (v.shape[0], 2, v.shape[1]):
        raise TrainError(f"{pressures_path}: loads must be ({v.shape[0]}, 2, {v.shape[1]}), "
                         f"got {p.shape}")
    return v, p


def hard_plate(vectors_path, pressures_path):
    """(X, y, groups, n_pins) from a pressing set: vectors (trials, depths, M, 2) and
    loads (trials, 2, depths) with row 1 the load cell; one window (T=1) per press."""
    from device.pi.models.window import encode_vectors

    v, p = pressing_set(vectors_path, pressures_path)
    n_trials, n_depths, M = v.shape[:3]
    X = encode_vectors(v.reshape(n_trials * n_depths, 1, M, 2))
    y = p[:, 1, :].reshape(-1).astype(np.float64)
    return X, y, np.repeat(np.arange(n_trials), n_depths), int(M)


def hard_plate_npz(vectors_path, pressures_path, out_path) -> dict:
    """Write a pressing set as an ``.npz`` data spec for ``host train --task pressure``
    (:mod:`host.data.spec_npz`): ``vectors`` (N, 1, M, 2), ``targets`` (N,) the
    load-cell reading, ``groups`` (N,) the trial and ``lost`` (N, 1, M) the pins at
    exactly (0, 0). Returns a summary (path, windows, trials, pins)."""
    from pathlib import Path

    v, p = pressing_set(vectors_path, pressures_path)
    n_trials, n_depths, M = v.shape[:3]
    vec = v.reshape(n_trials * n_depths, 1, M, 2).astype(np.float32)
    out = Path(out_path)
    out = out if out.suffix == ".npz" else out.with_name(out.name + ".npz")
    np.savez_compressed(out, vectors=vec, targets=p[:, 1, :].reshape(-1).astype(np.float64),
                        groups=np.repeat(np.arange(n_trials), n_depths),
                        lost=(vec == 0).all(axis=3))
    return {"path": str(out), "windows": int(len(vec)), "trials": int(n_trials),
            "n_pins": int(M)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m host.learn.pressure",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--vectors", required=True, help="(trials, depths, M, 2) .npy")
    ap.add_argument("--pressures", required=True, help="(trials, 2, depths) .npy, row 1 the load")
    ap.add_argument("--model", choices=KINDS, default="gbt")
    ap.add_argument("--cv", type=int, default=5, help="grouped folds (default 5)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-baseline", action="store_true",
                    help="skip the former model's figure (ridge150-raw)")
    ap.add_argument("--out", help="also write the model fitted on all trials here")
    ap.add_argument("--profile", default="roboskin",
                    help="the sensor profile the model's spec carries (name or .toml; "
                         "default roboskin)")
    ap.add_argument("--npz", help="only write the set as an .npz data spec for "
                                   "host train --task pressure (no CV)")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    try:
        if a.npz:
            res = hard_plate_npz(a.vectors, a.pressures, a.npz)
            print(json.dumps(res) if a.json else f"wrote {res['path']}: {res['windows']} "
                  f"windows of {res['trials']} trials, {res['n_pins']} pins")
            return 0
        X, y, groups, M = hard_plate(a.vectors, a.pressures)
        res = {"data": {"vectors": a.vectors, "pressures": a.pressures, "n_pins": M,
                        "windows": int(len(y))},
               "cv": cross_validate_pressure(X, y, groups, a.model, 1, M, a.cv, a.seed)}
        if not a.no_baseline and a.model != "ridge150-raw":
            res["baseline"] = cross_validate_pressure(X, y, groups, "ridge150-raw", 1, M,
                                                      a.cv, a.seed)
        if a.out:
            from device.pi.models.artefact import sha256_file
            recs = [{"path": str(f), "sha256": sha256_file(f), "frames": int(len(y))}
                    for f in (a.vectors, a.pressures)]
            spec = {"metrics": {"cv": res["cv"]}, "profile": a.profile,
                    "trained_on": {"data": "real", "recordings": recs,
                                   "split": f"grouped {a.cv}-fold CV over pressing trials "
                                            f"(metrics.cv); the model is fitted on all"},
                    "config": {"module": "host.learn.pressure", "vectors": str(a.vectors),
                               "pressures": str(a.pressures), "model": a.model,
                               "cv": a.cv, "seed": a.seed, "profile": a.profile}}
            out, _, parity = export_pressure(X, y, groups, a.out, a.model, (1, M), a.seed,
                                             spec)
            res["model"] = {"out": str(out), "onnx_parity": parity}
    except (TrainError, OSError, ValueError) as exc:
        msg = " ".join(str(exc).split())
        print(f"host.learn.pressure: error: {msg[:300]}", file=sys.stderr)
        return 2
    if a.json:
        print(json.dumps(res, indent=1))
    else:
        for key in ("cv", "baseline"):
            if key in res:
                r = res[key]
                print(f"{r['kind']:13s} grouped {r['folds']}-fold CV MAE {r['mae']:.1f} "
                      f"(95 % {r['mae_ci95'][0]:.1f}..{r['mae_ci95'][1]:.1f}), "
                      f"predict-mean {r['mae_predict_mean']:.1f}, {r['trials']} trials")
        if "model" in res:
            print(f"wrote {res['model']['out']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
