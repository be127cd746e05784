"""The simulated accuracy benchmarks: :func:`sim_benchmarks` builds the simulated data
sets the accuracy figures are measured on (randomised scenes, unseen seeds and surface
parameters beyond the training range for the test trials) and measures all four
tasks with the shipped model settings (:data:`BENCH_MODELS`)."""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from host.bench.scenes import BENCH_FPS, SURFACE_RANGES, simulate_scenes
from host.data.dataset import atomic_write_text
from host.data.load import load_spec
from host.learn.evaluate import evaluate_model
from host.learn.onnx_io import FLOAT_NAME, INT8_NAME, json_default
from host.learn.tasks import TrainError, check_int
from host.learn.train import train_model

__all__ = ["BENCH_TRIALS", "BENCH_TARGETS", "BENCH_MODELS", "sim_benchmarks"]


BENCH_TRIALS = {
    "full": {"surface": (24, 8), "texture": (16, 6), "slip": (30, 10), "pressure": (30, 10)},
    "quick": {"surface": (8, 3), "texture": (6, 3), "slip": (10, 4), "pressure": (10, 4)},
}
BENCH_TARGETS = {"surface_accuracy": 0.99, "lego_vs_smooth_accuracy": 0.99,
                 "concrete_vs_smooth_accuracy": 0.99, "slip_f1": 0.95,
                 "slip_median_latency_frames": 3.0, "pressure_mae_of_range": 0.05}
#: the benchmark's model per task (the MLPs are regularised harder than the
#: defaults: the test surfaces lie beyond the training range; surface and texture
#: add 3 rotated copies of each training window, so the drag direction is no clue).
#: Texture uses the fnn (frame-to-frame layer + IMU): the grid FNN reached 50 %
#: (Lego) and 75 % (concrete) on sliding windows in the same benchmark.
BENCH_MODELS = {"surface": ("fnn", {"alpha": 0.1, "augment": 3}),
                "texture": ("fnn", {"alpha": 0.01, "augment": 3}),
                "slip": ("fnn", {"alpha": 0.01}), "pressure": ("ridge", {})}


def _trial_scene(ws) -> np.ndarray:
    """The scene kind of each window's trial (``bench-lego`` -> ``lego``)."""
    names = {int(t["group"]): str(t.get("scene") or "").removeprefix("bench-")
             for t in ws.source.get("trials", [])}
    return np.array([names.get(int(g), "") for g in ws.groups], object)


def _subset_accuracy(model_dir, ws, mask, variant=None) -> dict | None:
    if not mask.any():
        return None
    ev = evaluate_model(model_dir, ws.subset(np.flatnonzero(mask)), variant=variant)
    return {"n": ev["n_windows"], "accuracy": ev["metrics"]["accuracy"],
            "macro_f1": ev["metrics"]["macro_f1"], "confusion": ev["metrics"]["confusion"]}


def sim_benchmarks(out_dir, quick: bool = False, T: int = 3, seed: int = 0,
                   progress: bool = True) -> dict:
    """The simulated accuracy figures (:data:`BENCH_TARGETS`), measured end to end.

    For each task it simulates training trials (surface parameters in the
    training range, seeds of one stream) and test trials (unseen seeds, surface
    parameters drawn from a wider range that reaches beyond the training range;
    :data:`SURFACE_RANGES`), cuts windows of T frames with the Pi's pipeline,
    trains, exports, quantises (int8, checked against float) and evaluates the
    shipped (int8) model on the test windows through the Pi's loader:

    * surface: 4-class FNN (vectors + IMU) on hard / soft / wet / no-touch steps;
    * texture: grid FNN, Lego vs smooth and concrete vs smooth, each a model of
      {texture, smooth, no-touch}; accuracy on all test windows, on contact
      windows, and on contact windows while the foot slides (a texture is only felt
      while sliding; in the stick phase Lego and smooth are the same surface);
    * slip: FNN slip detector on randomised ``slip-onset`` scenes; slip F1 and the
      detection latency in frames from each true onset;
    * pressure: Ridge on all vectors of press scenes; MAE as a share of the range.

    Data and models go under ``out_dir`` (data folders are reused when present);
    the result is also written to ``out_dir/benchmarks.json``.
    """
    T = check_int("T", T, 1)
    seed = check_int("seed", seed, 0)
    counts = BENCH_TRIALS["quick" if quick else "full"]
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    res: dict = {"T": T, "quick": bool(quick), "seed": seed, "fps": BENCH_FPS,
                 "trials": counts, "targets": BENCH_TARGETS,
                 "surface_ranges": {k: {kk: vv for kk, vv in v.items()}
                                    for k, v in SURFACE_RANGES.items()},
                 "command": f"python -c \"from host.bench.benchmarks import sim_benchmarks; "
                            f"sim_benchmarks('{out}', quick={bool(quick)}, T={T})\""}
    figures: dict = {}
    cache: dict = {}
    t_all = time.perf_counter()

    def data(task, kinds):
        n_tr, n_te = counts[task]
        t0 = time.perf_counter()
        tr = simulate_scenes(out / f"{task}-train", kinds, n_tr, 10 * seed + 1, False, progress)
        te = simulate_scenes(out / f"{task}-test", kinds, n_te, 10 * seed + 2, True, progress)
        sim_s = time.perf_counter() - t0
        return tr, te, sim_s

    def load(path, task, **kw):
        return load_spec(str(path), task, T, progress=False, cache=cache, **kw)

    def train(task, ws_tr, ws_te, name, model=None, **kw):
        m, hp = BENCH_MODELS[task]
        m = model or m
        args = dict(seed=seed, out_dir=out / "models" / name, progress=progress, **dict(hp, **kw))
        # a failed int8 check is reported, and the float model measured
        r = train_model(task, m, ws_tr, ws_te, quantise="if-passes", **args)
        return r, out / "models" / name

    def summary(r, ev):
        return {"model": r["model"], "uses_imu": r["uses_imu"], "fit": r.get("fit"),
                "train_s": r["train_s"], "variant": ev["variant"],
                "int8_check": {k: r["int8"][k] for k in ("agreement", "max_prob_diff",
                                                          "max_abs_diff", "mae_change",
                                                          "saturation", "failed")
                               if k in r["int8"]},
                "float_bytes": r["files"][FLOAT_NAME]["size_bytes"],
                "int8_bytes": r["files"].get(INT8_NAME, {}).get("size_bytes"),
                "latency_ms": ev["latency_ms"], "encode_ms": ev["encode_ms"]}

    def float_eval(mdir, ws):
        """The float model's evaluation (the same as the default without int8)."""
        return evaluate_model(mdir, ws, variant="float")

    def one_model(task, kinds):
        """Simulate, load, train and evaluate (default and float) one task's model."""
        tr, te, sim_s = data(task, kinds)
        t0 = time.perf_counter()
        ws_tr, ws_te = load(tr, task), load(te, task)
        load_s = time.perf_counter() - t0
        r, mdir = train(task, ws_tr, ws_te, task)
        ev = evaluate_model(mdir, ws_te)
        common = dict(windows={"train": len(ws_tr), "test": len(ws_te)},
                      sim_s=round(sim_s, 1), load_s=round(load_s, 1))
        return r, mdir, ws_te, ev, common

    # -- surface -------------------------------------------------------------
    r, mdir, ws_te, ev, common = one_model("surface", ["hard", "soft", "wet", "no-touch"])
    evf = float_eval(mdir, ws_te)
    res["surface"] = dict(summary(r, ev), accuracy_int8=ev["metrics"]["accuracy"],
                          accuracy_float=evf["metrics"]["accuracy"],
                          per_class=ev["metrics"]["per_class"],
                          confusion=ev["metrics"]["confusion"], **common)
    figures["surface_accuracy"] = ev["metrics"]["accuracy"]

    # -- texture -------------------------------------------------------------
    tr, te, sim_s = data("texture", ["smooth", "lego", "concrete"])
    t0 = time.perf_counter()
    tx_tr, tx_te = load(tr, "texture"), load(te, "texture")
    sl_te = load(te, "slip", min_classes=1)
    load_s = time.perf_counter() - t0
    if not (np.array_equal(sl_te.groups, tx_te.groups)
            and np.array_equal(sl_te.t_index, tx_te.t_index)):
        raise TrainError("texture and slip windows of the same trials differ")   # never
    sliding = sl_te.labels.astype(str) == "slip"
    kind_tr, kind_te = _trial_scene(tx_tr), _trial_scene(tx_te)
    res["texture"] = {"sim_s": round(sim_s, 1), "load_s": round(load_s, 1)}
    for other in ("lego", "concrete"):
        name = f"{other}-vs-smooth"
        a = tx_tr.subset(np.isin(kind_tr, [other, "smooth"]))
        keep_te = np.isin(kind_te, [other, "smooth"])
        b = tx_te.subset(keep_te)
        contact = b.contact
        slide = sliding[keep_te] & contact
        r, mdir = train("texture", a, b, name)
        ev = evaluate_model(mdir, b)
        evf = float_eval(mdir, b)
        entry = dict(summary(r, ev), accuracy_all_int8=ev["metrics"]["accuracy"],
                     accuracy_all_float=evf["metrics"]["accuracy"],
                     contact=_subset_accuracy(mdir, b, contact),
                     sliding=_subset_accuracy(mdir, b, slide),
                     windows={"train": len(a), "test": len(b), "test_contact": int(contact.sum()),
                              "test_sliding": int(slide.sum())})
        res["texture"][name] = entry
        figures[f"{other}_vs_smooth_accuracy"] = (entry["sliding"] or {}).get("accuracy")
        figures[f"{other}_vs_smooth_accuracy_contact"] = (entry["contact"] or {}).get("accuracy")
        figures[f"{other}_vs_smooth_accuracy_all"] = entry["accuracy_all_int8"]

    # -- slip ------------------------------------------------------------------
    r, mdir, ws_te, ev, common = one_model("slip", ["slip"])
    res["slip"] = dict(summary(r, ev), slip_f1=ev["metrics"]["slip_f1"],
                       accuracy=ev["metrics"]["accuracy"], latency=ev["metrics"]["latency"],
                       confusion=ev["metrics"]["confusion"], **common)
    res["slip"]["latency"].pop("latencies_frames", None)
    figures["slip_f1"] = ev["metrics"]["slip_f1"]
    figures["slip_median_latency_frames"] = ev["metrics"]["latency"]["median_frames"]

    # -- pressure --------------------------------------------------------------
    r, mdir, ws_te, ev, common = one_model("pressure", ["press-hard", "press-soft"])
    evf = float_eval(mdir, ws_te)
    res["pressure"] = dict(summary(r, ev), int8=ev["metrics"], float=evf["metrics"], **common)
    figures["pressure_mae_of_range"] = ev["metrics"]["mae_of_range"]
    figures["pressure_mae_n"] = ev["metrics"]["mae"]

    def ok(key, value):
        if value is None:
            return False
        want = BENCH_TARGETS[key]
        return value <= want if key in ("slip_median_latency_frames",
                                        "pressure_mae_of_range") else value >= want

    res["figures"] = figures
    res["met"] = {k: ok(k, figures.get(k)) for k in BENCH_TARGETS}
    res["total_s"] = round(time.perf_counter() - t_all, 1)
    atomic_write_text(out / "benchmarks.json", json.dumps(res, indent=1, default=json_default))
    return res
