"""The report's sweep: one cell per (data, kind, T, seed), run in parallel through
joblib, then aggregated over seeds (mean and sd) and timed in a serial pass.

:func:`run_cells` hands the cells to ``joblib.Parallel(n_jobs=jobs)``. It names no
backend, so the backend in force is joblib's default (separate processes) or the
one a caller sets with ``joblib.parallel_config``: the same cells then run on a Dask
or Ray cluster::

    from dask.distributed import Client
    from joblib import parallel_config
    client = Client("tcp://scheduler:8786")          # registers joblib's "dask" backend
    with parallel_config(backend="dask"):
        build_report("docs/accuracy-vs-time.md", "out/report", ["my-data.csv"], jobs=-1)

(Ray: ``from ray.util.joblib import register_ray; register_ray()`` and
``backend="ray"``.) A cell trains and scores; it measures no time. Its row is
written under the sweep's folder and reused by a later run whose windows hash the
same (:func:`fingerprint`); the hash does not cover the training code, so a changed
model needs a fresh folder. The times come
from :func:`time_models`, one model after another in the calling process, so no
cell runs beside a measurement.
"""
from __future__ import annotations

import hashlib
import json
import math
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from host.data.dataset import atomic_write_text
from host.extras import need

__all__ = ["Cell", "train_row", "int8_why", "run_cell", "run_cells", "aggregate", "mean_sd",
           "time_models"]

INT8_FAILED = "int8 check failed: "


def int8_why(fields: dict, message: str) -> str:
    """The int8 check's verdict in a few words, formatted once from its fields
    (:meth:`QuantisationError.fields`, or the manifest's ``int8``): the agreement
    reached and the bar (a classifier), or the MAE change (a regressor). Only a
    verdict with neither falls back to the start of the check's ``message``."""
    from host.learn.tasks import MAX_REGRESSION_CHANGE

    agreement, required = fields.get("agreement"), fields.get("required")
    mae_change, share = fields.get("mae_change"), fields.get("mae_change_of_range")
    if agreement is not None and required is not None:
        why = f"{agreement:.2%} argmax agreement with float (< {required * 100:g} %)"
    elif mae_change is not None:
        why = f"raises the MAE by {mae_change:.4g}" + (
            "" if share is None else
            f" ({share:.2%} of the target range, > {MAX_REGRESSION_CHANGE:.0%})")
    else:
        return INT8_FAILED + message.removeprefix(INT8_FAILED)[:120]
    return f"{INT8_FAILED}{why}; float kept"


def train_row(task, model, tr, te, out, seed, profile: str = "roboskin") -> str | None:
    """Train one model into ``out`` (float, and int8 when it passes its check), its
    features (roughness included) with the sensor ``profile``. Returns why there is
    no int8 model, or None."""
    from host.learn.onnx_io import INT8_NAME
    from host.learn.tasks import QuantisationError
    from host.learn.train import train_model

    if model == "cnn":
        from host.learn.cnn import quantise_cnn, train_cnn
        res = train_cnn(tr, te, seed=seed, out_dir=out, progress=False, epochs=15)
        try:
            quantise_cnn(res["onnx_path"], tr, Path(out) / INT8_NAME, seed=seed)
        except QuantisationError as exc:
            return int8_why(exc.fields(), str(exc))
        return None
    res = train_model(task, model, tr, te, quantise="if-passes" if model != "rule" else False,
                      seed=seed, out_dir=out, progress=False, profile=profile)
    failed = (res.get("int8") or {}).get("failed")
    if not failed:
        return None
    return int8_why(res["int8"], failed)


@dataclass(frozen=True)
class Cell:
    """One training run of the sweep: ``data`` names the section's data."""

    data: str
    task: str
    kind: str
    T: int
    seed: int

    def folder(self, root) -> Path:
        return Path(root) / self.data / f"{self.kind}-T{self.T}-s{self.seed}"


def _score(metrics: dict) -> dict:
    return {"accuracy": metrics.get("accuracy"), "mae": metrics.get("mae")}


def fingerprint(tr, te) -> str:
    """A short hash of a cell's training and test windows."""
    h = hashlib.sha1()
    for ws in (tr, te):
        for a in (ws.vectors, ws.lost, ws.grids, ws.labels, ws.targets, ws.t_index):
            if a is not None:
                h.update(np.ascontiguousarray(a).tobytes() if a.dtype != object
                         else "\n".join(map(str, a)).encode())
    return h.hexdigest()[:16]


def cached_row(cell: Cell, root, key: str, keep: bool) -> dict | None:
    """The row a finished cell left under ``root`` for the same windows, if any."""
    path = cell.folder(root).with_suffix(".json")
    try:
        row = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if row.get("fingerprint") != key or (keep and not row.get("model_dir")):
        return None
    return row


def run_cell(cell: Cell, tr, te, root=None, keep: bool = False,
             profile: str = "roboskin") -> dict:
    """Train ``cell`` on windows ``tr``, score it on ``te``. With ``root`` its row is
    kept beside the model folder and reused by a later run on the same windows; with
    ``keep`` the model folder stays under ``root`` (for :func:`time_models`). Kinds: those of
    :mod:`host.learn.train`, ``cnn``, and ``fnn-dropout``
    (:mod:`host.bench.regularise`). A failure is a row with ``error``."""
    from host.bench.regularise import REGULARISERS, fit_fnn_variant
    from host.learn.evaluate import evaluate_model
    from host.learn.onnx_io import INT8_NAME
    from host.learn.tasks import TrainError

    key = fingerprint(tr, te)
    if root is not None:
        hit = cached_row(cell, root, key, keep)
        if hit is not None:
            return hit
    row = {**asdict(cell), "n_train": int(len(tr)), "n_test": int(len(te)), "fingerprint": key}
    t0 = time.perf_counter()
    try:
        if cell.kind in REGULARISERS:
            row.update(fit_fnn_variant(cell.kind, tr, te, cell.seed))
            row["train_s"] = round(time.perf_counter() - t0, 2)
            return _store(row, cell, root)
        with tempfile.TemporaryDirectory() as tmp:
            folder = cell.folder(root) if keep and root is not None else Path(tmp) / "m"
            int8_failed = train_row(cell.task, cell.kind, tr, te, folder, cell.seed, profile)
            row["train_s"] = round(time.perf_counter() - t0, 2)
            row.update(_score(evaluate_model(folder, te, variant="float")["metrics"]))
            if int8_failed:
                row["int8_error"] = int8_failed
            elif (folder / INT8_NAME).exists():
                q = _score(evaluate_model(folder, te, variant="int8")["metrics"])
                row["int8_accuracy"], row["int8_mae"] = q["accuracy"], q["mae"]
            if keep and root is not None:
                row["model_dir"] = str(folder)
    except (TrainError, ValueError) as exc:
        row["error"] = str(exc)[:200]
    return _store(row, cell, root)


def _store(row: dict, cell: Cell, root) -> dict:
    if root is not None:
        path = cell.folder(root).with_suffix(".json")
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(path, json.dumps(row, default=float))
    return row


def run_cells(cells, windows: dict, root, jobs: int = 1, keep_seed: int | None = None,
              verbose: int = 0, progress: bool = False,
              profiles: dict | None = None) -> list[dict]:
    """Run every cell through joblib (``jobs`` workers, the backend in force; see the
    module doc). ``windows[(data, T)]`` is the (train, test) WindowSet pair of a
    cell; models of seed ``keep_seed`` are kept under ``root`` for timing;
    ``profiles[data]`` is the sensor profile of a cell's data (default roboskin).
    ``progress``: a tqdm bar over the cells as they finish."""
    from joblib import Parallel, delayed
    tqdm = need("tqdm").tqdm

    cells = list(cells)
    profiles = profiles or {}
    tasks = (delayed(run_cell)(c, *windows[(c.data, c.T)], root, c.seed == keep_seed,
                               profiles.get(c.data, "roboskin"))
             for c in cells)
    rows = Parallel(n_jobs=jobs, verbose=verbose, return_as="generator")(tasks)
    return list(tqdm(rows, total=len(cells), desc="host report: cells", unit="cell",
                     disable=not progress or None))


def mean_sd(values) -> tuple[float, float, int]:
    """(mean, sample sd, n) of the finite values; sd is 0 for one value and
    (nan, nan, 0) for none."""
    a = np.asarray([v for v in values if v is not None and math.isfinite(v)], np.float64)
    if not len(a):
        return math.nan, math.nan, 0
    return float(a.mean()), float(a.std(ddof=1)) if len(a) > 1 else 0.0, int(len(a))


def aggregate(rows: list[dict]) -> list[dict]:
    """One row per (data, task, kind, T): the score's mean, sd and number of seeds
    over the cells that trained (``accuracy`` or ``mae``, and the int8 copy's), and
    the errors of those that did not. Ordered by data, kind (first seen), T."""
    groups: dict = {}
    for r in rows:
        groups.setdefault((r["data"], r["task"], r["kind"], r["T"]), []).append(r)
    out = []
    for (data, task, kind, T), rs in groups.items():
        ok = [r for r in rs if "error" not in r]
        agg = {"data": data, "task": task, "kind": kind, "T": T, "seeds": len(rs),
               "errors": sorted({r["error"] for r in rs if "error" in r})}
        metric = "mae" if any(r.get("mae") is not None for r in ok) else "accuracy"
        agg["metric"] = metric
        agg["mean"], agg["sd"], agg["n"] = mean_sd(r.get(metric) for r in ok)
        q = [r.get(f"int8_{metric}") for r in ok if r.get(f"int8_{metric}") is not None]
        agg["int8_mean"], agg["int8_sd"], agg["int8_n"] = mean_sd(q)
        agg["int8_errors"] = len([r for r in ok if r.get("int8_error")])
        agg["n_train"] = ok[0]["n_train"] if ok else None
        agg["n_test"] = ok[0]["n_test"] if ok else None
        agg["train_s"] = float(np.median([r["train_s"] for r in ok])) if ok else None
        out.append(agg)
    return out


def time_models(rows: list[dict], windows: dict, vision: dict) -> dict:
    """Per-decision cost of each kept model (rows with ``model_dir``), one after
    another in this process: the window encoding and the model on its test windows
    (:func:`host.bench.costs.model_cost`, one thread) plus the vision pipeline per
    frame (``vision["plain"]``, or ``vision["crop"]`` for a model that reads the
    dome crop). Returns {(data, kind, T): cost}."""
    from host.bench.costs import decision_cost, model_cost

    out = {}
    for r in rows:
        if not r.get("model_dir"):
            continue
        m = model_cost(r["model_dir"], windows[(r["data"], r["T"])][1])
        v = vision["crop" if m["input_layout"] == "frames" else "plain"]
        out[(r["data"], r["kind"], r["T"])] = {"vision": v, "model": m,
                                               **decision_cost(v, m)}
    return out
