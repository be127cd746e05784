"""Rebuild the shipped default models in ``models/`` (``make models``).

    python -m host.bench.shipped --out models [--work out/models-data] [--only surface,slip]
    python -m host.bench.shipped --out models --regraph texture

``--regraph NAME`` trains nothing: it rewrites the fixed first layer's graph of the
fnn in ``models/NAME`` with the current converter (:func:`regraph`), so a faster graph
reaches a shipped model without changing its weights or its figures.

With ``--real-data DIR`` the texture model is trained on the real roboskin
recordings (the first 70 % of concrete.avi, smooth.avi and lego_train.avi, contact
windows only; their rest is its held-out test). The other models, and texture
without real data, are trained on simulated trials of the roboskin sensor (surface
parameters drawn from the training ranges of :data:`host.bench.scenes.SURFACE_RANGES`,
fixed seeds), exported to ONNX with the scaler folded in, quantised to int8 and
checked against float, and written as ``models/<name>/`` (the manifest, a model
spec (:mod:`device.pi.models.spec`); model.onnx, model.int8.onnx; README.md, the
model card, and train.toml, the config: :mod:`host.learn.card`). The surface model must pass the int8 check; for the
others a failed check ships the float model alone (the texture FNN's first layer
reads frame-to-frame changes of ~0.1 px, finer than its int8 input step). The model settings are the simulated benchmark's
(:data:`host.bench.benchmarks.BENCH_MODELS`), so the figures in docs/accuracy-vs-time.md and
``host.bench.benchmarks.sim_benchmarks`` describe these models.

=========  ======================  =========================================
folder     task / model            classes or target
=========  ======================  =========================================
surface    surface, int8 FNN       hard, no-touch, slippery, soft
texture    texture, FNN            concrete, lego, no-touch, smooth
slip       slip, FNN               no-slip, slip
pressure   pressure, Ridge         normal load (N)
localiser  (host.localiser.train)        133 pin positions, roboskin
=========  ======================  =========================================

The simulated data go under ``--work`` (default ``out/models-data``) and are reused
when a later run asks for the same trials. Same seeds, same models: the training is
deterministic on one machine (ONNX files may differ in the last bits across
machines with other BLAS builds).
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

from device.pi.models.artefact import sha256_file
from device.pi.models.manifest import read_spec, write_variant_specs
from host.bench.benchmarks import BENCH_MODELS
from host.bench.scenes import simulate_scenes
from host.data.load import load_spec
from host.learn.card import measure_cost, write_model_docs
from host.learn.onnx_io import FLOAT_NAME, INT8_NAME, replace_graphs, session
from host.learn.tasks import (DEFAULT_ALPHA, DEFAULT_EPOCHS, DEFAULT_MODEL, DEFAULT_WINDOW,
                              TASK_HIDDEN, TASK_RATES, TrainError)
from host.learn.train import train_model

__all__ = ["DEFAULTS", "build_model", "build_defaults", "regraph", "main"]

#: name -> (task, simulated kinds, trials per kind, T)
DEFAULTS = {
    "surface": ("surface", ["hard", "soft", "wet", "no-touch"], 24, 3),
    "texture": ("texture", ["smooth", "lego", "concrete"], 16, 3),
    "slip": ("slip", ["slip"], 30, 3),
    "pressure": ("pressure", ["press-hard", "press-soft"], 30, 3),
}
#: these must ship as int8 (the surface FNN is shipped int8); the others fall
#: back to float when their int8 copy fails the >= 99 % agreement check
MUST_INT8 = ("surface",)
#: largest shipped model folder
MAX_BYTES = 1 << 20


def build_model(name: str, out_root, work, seed: int = 0, progress: bool = True,
                trials: int | None = None) -> dict:
    """Train one default model into ``out_root/name`` (replaced only when the new
    one is complete). Returns a summary: metrics, int8 check, bytes."""
    if name not in DEFAULTS:
        raise TrainError(f"unknown default model {name!r}; choose from {sorted(DEFAULTS)}")
    task, kinds, n, T = DEFAULTS[name]
    n = trials or n
    t0 = time.perf_counter()
    # the same folder and seeds as the training part of host.bench.benchmarks.sim_benchmarks
    data = simulate_scenes(Path(work) / f"{task}-train", kinds, n, 10 * seed + 1, False,
                           progress)
    ws = load_spec(str(data), task, T, progress=progress)
    model, hp = BENCH_MODELS[task]
    out_root = Path(out_root)
    tmp = out_root / f".{name}.building"
    shutil.rmtree(tmp, ignore_errors=True)
    res = train_model(task, model, ws, quantise=True if name in MUST_INT8 else "if-passes",
                      seed=seed, out_dir=tmp, progress=progress, **hp)
    # the runtime loads the float model when the int8 copy failed its check
    int8_failed = (res.get("int8") or {}).get("failed")
    mark_trained_on(tmp, {"data": "simulated", "recordings": [],
                          "split": res.get("holdout"), "scenes": kinds, "trials_per_kind": n,
                          "real_accuracy": None},
                    shipped_config(name, task, model, T, seed, trials_per_kind=n, **hp))
    size = _check_size(tmp, name)
    _install(tmp, out_root / name)
    test = res["metrics"].get("test", {})
    return {"name": name, "task": task, "model": model, "T": T, "trials_per_kind": n,
            "windows": len(ws), "bytes": size, "seconds": round(time.perf_counter() - t0, 1),
            "test": {k: test.get(k) for k in ("accuracy", "macro_f1", "slip_f1", "mae",
                                              "mae_of_range", "n") if k in test},
            "int8": ({"failed": int8_failed} if int8_failed else
                     {k: res["int8"].get(k) for k in ("agreement", "max_prob_diff",
                                                       "mae_change", "passed")
                      if k in (res.get("int8") or {})})}


#: the real recordings the texture model trains on, when they are at hand:
#: clip (under roboskin/) -> label. Lego's later frames are kept back by the data's
#: authors; lego_train.avi is its first 70 %.
REAL_TEXTURE = {"concrete.avi": "concrete", "smooth.avi": "smooth", "lego_train.avi": "lego"}
#: share of each real clip (its start) the texture model trains on; the rest, after
#: a gap of T frames, is its held-out test
REAL_TRAIN_FRAC = 0.7


def real_texture_specs(real_data, work, T: int) -> tuple[Path, Path]:
    """(train CSV, held-out CSV) over the real clips: the first ``REAL_TRAIN_FRAC`` of
    each clip, and its rest from T frames after that."""
    import cv2

    root = Path(real_data).resolve() / "roboskin"
    work = Path(work)
    work.mkdir(parents=True, exist_ok=True)
    train, test = ["path,label,start_frame,end_frame"], ["path,label,start_frame,end_frame"]
    for clip, label in REAL_TEXTURE.items():
        path = root / clip
        if not path.is_file():
            raise TrainError(f"real texture data: {path} is missing")
        cap = cv2.VideoCapture(str(path))
        n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        cap.release()
        cut = int(REAL_TRAIN_FRAC * n)
        train.append(f"{path},{label},0,{cut}")
        test.append(f"{path},{label},{cut + T},")
    a, b = work / "real-texture-train.csv", work / "real-texture-test.csv"
    a.write_text("\n".join(train) + "\n")
    b.write_text("\n".join(test) + "\n")
    return a, b


def build_real_texture(out_root, work, real_data, seed: int = 0,
                       progress: bool = True) -> dict:
    """``models/texture`` from the real recordings (:data:`REAL_TEXTURE`): trained on
    the first 70 % of each clip, contact windows only, tested on the rest."""
    # host train's texture defaults (tasks.DEFAULT_MODEL, DEFAULT_WINDOW, TASK_HIDDEN),
    # whose hidden layers keep the model (float + int8) under MAX_BYTES
    model, T = DEFAULT_MODEL["texture"], DEFAULT_WINDOW["texture"]
    tr, te = real_texture_specs(real_data, work, T)
    ws = load_spec(str(tr), "texture", T, contact_only=True, progress=progress)
    wt = load_spec(str(te), "texture", T, contact_only=True, progress=progress)
    out_root = Path(out_root)
    tmp = out_root / ".texture.building"
    shutil.rmtree(tmp, ignore_errors=True)
    t0 = time.perf_counter()
    res = train_model("texture", model, ws, wt, quantise="if-passes", seed=seed, out_dir=tmp,
                      progress=progress)
    root = Path(real_data).resolve()
    trained_on = {"data": "real",
                  "recordings": [{"path": f"roboskin/{c}",
                                  "sha256": sha256_file(root / "roboskin" / c),
                                  "frames": f"0..{REAL_TRAIN_FRAC:.0%}"} for c in REAL_TEXTURE],
                  "split": f"the rest of each recording after a gap of {T} frames, "
                           f"contact windows only",
                  "real_accuracy": res["metrics"]["test"].get("accuracy")}
    mark_trained_on(tmp, trained_on,
                    shipped_config("texture", "texture", model, T, seed,
                                   real_data=str(Path(real_data)),
                                   train_fraction=REAL_TRAIN_FRAC, contact_only=True,
                                   hidden=TASK_HIDDEN["texture"], alpha=DEFAULT_ALPHA[model],
                                   epochs=DEFAULT_EPOCHS, augment=0,
                                   rates=TASK_RATES.get("texture", ())))
    size = _check_size(tmp, "texture")
    _install(tmp, out_root / "texture")
    write_model_docs(out_root / "texture", measure=False)   # the card named after its folder
    test = res["metrics"]["test"]
    return {"name": "texture", "task": "texture", "model": model, "T": T, "data": "real",
            "clips": sorted(REAL_TEXTURE), "windows": len(ws), "test_windows": len(wt),
            "bytes": size,
            "seconds": round(time.perf_counter() - t0, 1),
            "test": {k: test.get(k) for k in ("accuracy", "macro_f1", "n")},
            "int8": {k: (res.get("int8") or {}).get(k) for k in ("agreement", "failed")},
            "ignored_pins": res.get("ignored_pins")}


def regraph(folder, seed: int = 0) -> dict:
    """Rewrite the fixed first layer (``TemporalFeatures``) of the fnn in ``folder``
    (model.onnx and, when there, model.int8.onnx) with the graph its converter writes
    now, without training again: weights, metrics and the training record are kept.
    The files are replaced only when, for each of them, the new graph names the same
    class as the old one on random windows with probabilities within 1e-4 (none is
    written unless all pass); sha256 and sizes are recorded again. Returns {file: (bytes before, bytes after)}."""
    import numpy as np
    import onnx

    from host.learn.layers import replace_temporal_graph

    folder = Path(folder)
    spec, _ = read_spec(folder)
    params = spec.training.get("temporal")
    if not params:
        raise TrainError(f"{folder}: the manifest records no temporal layer to rewrite")
    if spec.features is not None:
        raise TrainError(f"{folder}: its window features run outside the graph (features "
                         f"version {spec.features.get('version')!r}): no layer to rewrite")
    names = [n for n in (FLOAT_NAME, INT8_NAME) if (folder / n).is_file()]
    X = np.random.default_rng(seed).normal(0, 3, (256, spec.n_inputs))
    X = X.astype(np.float32)
    new_bytes = {}
    for name in names:                  # every file is checked before any is written
        old = onnx.load(str(folder / name))
        new = replace_temporal_graph(old, params, seed)
        feed = {spec.input_name: X}
        try:
            a, b = session(old).run(None, feed), session(new).run(None, feed)
        except Exception as exc:       # ONNX Runtime's own exception types
            raise TrainError(f"{folder / name}: the rewritten graph does not run: "
                             + " ".join(str(exc).split())) from None
        if not (np.array_equal(a[0], b[0]) and np.allclose(a[1], b[1], atol=1e-4)):
            raise TrainError(f"{folder / name}: the rewritten graph gives other outputs")
        new_bytes[name] = new.SerializeToString()
    return replace_graphs(folder, spec, new_bytes)


def shipped_config(name: str, task: str, model: str, T: int, seed: int, **more) -> dict:
    """The config (the spec's ``config``, written as train.toml) of a shipped model:
    the command that rebuilds it and its settings."""
    real = more.get("real_data")
    cmd = (f"python -m host.bench.shipped --only {name} --seed {seed}"
           + (f" --real-data {real}" if real else ""))
    return {"module": "host.bench.shipped", "command": cmd, "name": name, "task": task,
            "model": model, "T": T, "seed": seed, "profile": "roboskin",
            **{k: (list(v) if isinstance(v, tuple) else v) for k, v in more.items()}}


def mark_trained_on(folder: Path, trained_on: dict, config: dict | None = None) -> None:
    """Record in the spec of ``folder`` what the model was trained on (``measured``): ``data`` (real or simulated), ``recordings`` (path, sha256,
    frames), ``split`` and, where real data exist, its accuracy on real frames; and
    ``config``, the settings that rebuild it; time its cost per decision, write its
    manifests once, then the model card and train.toml."""
    spec, _ = read_spec(folder)
    spec.measured.trained_on = dict(trained_on)
    if config is not None:
        spec.config = dict(config)
    spec.measured.cost_per_decision = measure_cost(folder, spec)
    write_variant_specs(folder, spec)          # the manifests written once, from the spec
    write_model_docs(folder, measure=False)


def _check_size(tmp: Path, name: str) -> int:
    size = sum(p.stat().st_size for p in tmp.iterdir() if p.is_file())
    if size > MAX_BYTES:
        shutil.rmtree(tmp, ignore_errors=True)
        raise TrainError(f"default model {name}: {size} bytes, over the {MAX_BYTES} limit")
    return size


def _install(tmp: Path, final: Path) -> None:
    old = final.parent / f".{final.name}.old"
    shutil.rmtree(old, ignore_errors=True)
    if final.exists():
        final.rename(old)
    tmp.rename(final)
    shutil.rmtree(old, ignore_errors=True)


def build_defaults(out_root="models", work="out/models-data", names=None, seed: int = 0,
                   progress: bool = True, real_data=None) -> list[dict]:
    """The default models; with ``real_data`` (the folder holding roboskin/), texture
    trains on the real recordings instead of simulated trials."""
    out_root = Path(out_root)
    out_root.mkdir(parents=True, exist_ok=True)
    return [build_real_texture(out_root, work, real_data, seed, progress)
            if n == "texture" and real_data is not None else
            build_model(n, out_root, work, seed=seed, progress=progress)
            for n in (names or list(DEFAULTS))]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m host.bench.shipped", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default="models", help="models folder (default: models)")
    p.add_argument("--work", default="out/models-data", help="simulated training data")
    p.add_argument("--only", help="comma-separated subset of " + ",".join(DEFAULTS))
    p.add_argument("--real-data", help="folder holding roboskin/: texture trains on the real "
                                       "recordings (concrete, smooth, lego_train)")
    p.add_argument("--regraph", metavar="NAME",
                   help="rewrite the first layer's graph of the fnn in OUT/NAME with the "
                        "current converter, without training again")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    names = [n.strip() for n in args.only.split(",")] if args.only else None
    if args.regraph:
        try:
            sizes = regraph(Path(args.out) / args.regraph, seed=args.seed)
        except (TrainError, OSError, ValueError, KeyError) as exc:
            print(f"host.bench.shipped: error: {args.regraph}: {exc}", file=sys.stderr)
            return 2
        for name, (before, after) in sizes.items():
            print(f"{args.regraph}/{name}: {before} -> {after} bytes")
        return 0
    try:
        rows = build_defaults(args.out, args.work, names, seed=args.seed,
                              progress=not args.quiet, real_data=args.real_data)
    except TrainError as exc:
        print(f"host.bench.shipped: error: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(rows, indent=1))
    else:
        for r in rows:
            print(f"{r['name']:9s} {r['model']:8s} T={r['T']} {r['bytes'] / 1024:7.1f} KiB "
                  f"test {r['test']} int8 {r['int8']} ({r['seconds']} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
