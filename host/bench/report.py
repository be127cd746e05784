"""``host report``: what accuracy costs in time.

For each task it crosses model kind x float/int8 x window T, trains on the same
training windows and measures on the same held-out windows: accuracy (or MAE),
per-decision compute latency (p50, p99, one thread), model size, and the decision
delay T/fps at 30 and 120 fps. It writes one markdown table and one Pareto plot
(PNG) per task.
"""
from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

from host.analysis.figures import pyplot, save_figure
from host.bench.scenes import simulate_scenes
from host.data.dataset import atomic_write_text
from host.data.load import load_specs
from host.data.splits import split_grouped, split_time
from host.learn.evaluate import evaluate_model
from host.learn.onnx_io import INT8_NAME
from host.learn.tasks import MAX_REGRESSION_CHANGE, TASK_MODELS, QuantisationError, TrainError
from host.learn.train import train_model

WINDOWS = (1, 2, 3, 5, 10)
FPS = (30, 120)


def _have_torch() -> bool:
    try:
        import torch  # noqa: F401
        return True
    except ImportError:
        return False


def models_for(task: str) -> list[str]:
    models = list(TASK_MODELS[task])
    if task != "pressure" and _have_torch():
        models.append("cnn")
    return models


INT8_FAILED = "int8 check failed: "


def _int8_why(fields: dict, message: str) -> str:
    """The int8 check's verdict in a few words, formatted once from its fields
    (:meth:`QuantisationError.fields`, or the manifest's ``int8``): the agreement
    reached and the bar (a classifier), or the MAE change (a regressor). Only a
    verdict with neither falls back to the start of the check's ``message``."""
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


def train_row(task, model, tr, te, out, seed) -> str | None:
    """Train one row's model into ``out`` (float, and int8 when it passes its
    check). Returns why there is no int8 model, or None."""
    if model == "cnn":
        from host.learn.cnn import quantise_cnn, train_cnn
        res = train_cnn(tr, te, seed=seed, out_dir=out, progress=False, epochs=15)
        try:
            quantise_cnn(res["onnx_path"], tr, Path(out) / INT8_NAME, seed=seed)
        except QuantisationError as exc:
            return _int8_why(exc.fields(), str(exc))
        return None
    res = train_model(task, model, tr, te, quantise="if-passes" if model != "rule" else False,
                      seed=seed, out_dir=out, progress=False)
    failed = (res.get("int8") or {}).get("failed")
    if not failed:
        return None
    return _int8_why(res["int8"], failed)


def run_task(task: str, train_specs, test_specs=None, windows=WINDOWS, seed: int = 0,
             split: str = "grouped", contact_only: bool = False, label: str = "",
             progress: bool = True) -> list[dict]:
    """Rows of the report for one task and data source."""
    rows = []
    cache: dict = {}
    for T in windows:
        ws = load_specs(train_specs, task=task, window=T, contact_only=contact_only,
                        progress=False, cache=cache)
        if test_specs:
            tr, te = ws, load_specs(test_specs, task=task, window=T, contact_only=contact_only,
                                    progress=False, cache=cache, min_classes=1)
        else:
            idx = (split_time(ws, 0.7, gap=T) if split == "time"
                   else split_grouped(ws, 0.3, seed))
            tr, te = ws.subset(idx[0]), ws.subset(idx[1])
        for model in models_for(task):
            with tempfile.TemporaryDirectory() as d:
                t0 = time.perf_counter()
                try:
                    int8_failed = train_row(task, model, tr, te, d, seed)
                except (TrainError, ValueError) as exc:
                    rows.append({"task": task, "data": label, "model": model, "T": T,
                                 "error": str(exc)[:200]})
                    continue
                train_s = time.perf_counter() - t0
                for variant in ("float", "int8"):
                    if variant == "int8" and int8_failed:
                        rows.append({"task": task, "data": label, "model": model,
                                     "variant": "int8", "T": T, "error": int8_failed})
                        continue
                    if variant == "int8" and not (Path(d) / INT8_NAME).exists():
                        continue
                    r = evaluate_model(d, te, variant=variant)
                    m = r["metrics"]
                    rows.append({
                        "task": task, "data": label, "model": model, "variant": variant,
                        "T": T, "accuracy": m.get("accuracy"), "macro_f1": m.get("macro_f1"),
                        "mae": m.get("mae"), "latency_p50_ms": r["latency_ms"]["p50"],
                        "latency_p99_ms": r["latency_ms"]["p99"],
                        "size_bytes": r["model_bytes"], "train_s": round(train_s, 2),
                        "n_train": len(tr), "n_test": len(te),
                        **{f"delay_{f}fps_ms": 1000.0 * T / f for f in FPS}})
                if progress:
                    print(f"  {label} {task} T={T} {model}: done", flush=True)
    return rows


def _score(r):
    return r["mae"] if r.get("mae") is not None else r.get("accuracy")


def pareto(rows: list[dict], lower_better: bool) -> set[int]:
    """Indices of rows no other row beats on both score and total delay."""
    pts = [(r["delay_120fps_ms"] + r["latency_p50_ms"], _score(r)) for r in rows]
    keep = set()
    for i, (t, s) in enumerate(pts):
        dominated = any((t2 <= t and (s2 < s if lower_better else s2 > s)) or
                        (t2 < t and s2 == s) for j, (t2, s2) in enumerate(pts) if j != i)
        if not dominated:
            keep.add(i)
    return keep


def plot_pareto(rows: list[dict], out: Path, title: str) -> Path:
    plt = pyplot()

    ok = [r for r in rows if "error" not in r]
    lower = ok and ok[0].get("mae") is not None
    front = pareto(ok, lower)
    fig, ax = plt.subplots(figsize=(7.5, 4.8))
    markers = {"rule": "s", "ridge": "D", "fnn": "o", "grid-fnn": "^", "cnn": "P"}
    for i, r in enumerate(ok):
        x = r["delay_120fps_ms"] + r["latency_p50_ms"]
        ax.scatter(x, _score(r), marker=markers.get(r["model"], "o"), s=50,
                   c=[plt.cm.viridis(min(r["T"], 10) / 10)],
                   edgecolors="r" if i in front else "none",
                   alpha=0.55 if r["variant"] == "float" else 0.95)
    fr = sorted((ok[i] for i in front), key=lambda r: r["delay_120fps_ms"] + r["latency_p50_ms"])
    ax.plot([r["delay_120fps_ms"] + r["latency_p50_ms"] for r in fr], [_score(r) for r in fr],
            "r--", lw=1, label="Pareto front")
    for m, mk in markers.items():
        if any(r["model"] == m for r in ok):
            ax.scatter([], [], marker=mk, c="gray", label=m)
    ax.set_xlabel("time to a decision at 120 fps: T/fps + compute p50 [ms]")
    ax.set_ylabel("MAE (lower is better)" if lower else "held-out accuracy")
    ax.set_title(title)
    ax.legend(fontsize=8)
    sm = plt.cm.ScalarMappable(cmap="viridis", norm=plt.Normalize(0, 10))
    fig.colorbar(sm, ax=ax, label="window T [frames]")
    return save_figure(fig, out)


def table(rows: list[dict]) -> str:
    ok = [r for r in rows if "error" not in r]
    lower = ok and ok[0].get("mae") is not None
    front = pareto(ok, lower)
    head = ("| model | variant | T | " + ("MAE" if lower else "accuracy") +
            " | compute p50 ms | p99 ms | size KB | delay @30 fps ms | delay @120 fps ms | "
            "Pareto |")
    lines = [head, "|---|---|--:|--:|--:|--:|--:|--:|--:|:-:|"]
    for i, r in enumerate(ok):
        lines.append(f"| {r['model']} | {r['variant']} | {r['T']} | {_score(r):.4f} | "
                     f"{r['latency_p50_ms']:.3f} | {r['latency_p99_ms']:.3f} | "
                     f"{r['size_bytes'] / 1024:.1f} | {r['delay_30fps_ms']:.1f} | "
                     f"{r['delay_120fps_ms']:.1f} | {'*' if i in front else ''} |")
    for r in rows:
        if "error" in r:
            why = r["error"] if r.get("variant") else f"not trained: {r['error']}"
            lines.append(f"| {r['model']} | {r.get('variant', '-')} | {r['T']} | {why} "
                         f"| | | | | | |")
    return "\n".join(lines)


def write_report(sections: list[tuple[str, str, list[dict]]], out: Path | str,
                 command: str) -> Path:
    """sections: (title, png name, rows). Writes the markdown and the PNGs beside it."""
    out = Path(out)
    img_dir = out.parent / "img"
    parts = ["# What accuracy costs in time", "",
             f"Generated by `{command}`. Every row is trained on the same training windows "
             "and measured on the same held-out windows; compute latency is ONNX Runtime, "
             "one thread, per decision; the decision delay is the window's length T/fps. "
             "`*` marks the Pareto front (no other row is both faster to a decision at "
             "120 fps and more accurate).", "",
             "The simulated sections train every kind with its default settings on a few "
             "trials per surface (`host.bench.report.REPORT_TRIALS`), so that the whole cross "
             "runs in one go; they compare kinds, variants and window lengths with each "
             "other. The shipped models and the accuracy targets use more trials and "
             "tuned settings: see the simulated accuracy table in "
             "[BENCHMARKS.md](BENCHMARKS.md). A row whose int8 copy fails the >= 99 % "
             "argmax agreement check keeps its float model and lists the agreement "
             "reached.", ""]
    for title, png, rows in sections:
        p = plot_pareto(rows, img_dir / png, title)
        parts += [f"## {title}", "", table(rows), "", f"![{title}](img/{p.name})", ""]
    atomic_write_text(out, "\n".join(parts))
    atomic_write_text(out.with_suffix(".json"), json.dumps(
        [{"title": t, "rows": r} for t, _, r in sections], indent=1, default=float))
    return out


#: the simulated scene kinds behind each task (host.bench.scenes.simulate_scenes)
TASK_KINDS = {"surface": ("hard", "soft", "wet", "no-touch"),
              "texture": ("lego", "concrete", "smooth"),
              "slip": ("slip",), "pressure": ("press-hard", "press-soft")}
#: (train, test) trials per kind
REPORT_TRIALS = {"full": {"surface": (8, 3), "texture": (6, 2), "slip": (10, 3),
                          "pressure": (8, 3)},
                 "quick": {"surface": (3, 1), "texture": (2, 1), "slip": (3, 1),
                           "pressure": (3, 1)}}


def real_manifest(data_dir, work: Path) -> Path:
    """Concrete vs smooth from the real roboskin clips, as a CSV manifest."""
    root = Path(data_dir) / "roboskin"
    work.mkdir(parents=True, exist_ok=True)
    path = work / "concrete-vs-smooth.csv"
    path.write_text("path,label\n"
                    f"{(root / 'smooth.avi').resolve()},smooth\n"
                    f"{(root / 'concrete.avi').resolve()},concrete\n")
    return path


def build_report(out, work, data_dir=None, windows=WINDOWS, quick: bool = False,
                 tasks=tuple(TASK_KINDS), seed: int = 0, progress: bool = True,
                 command: str = "host report") -> Path:
    work = Path(work)
    counts = REPORT_TRIALS["quick" if quick else "full"]
    sections = []
    for task in tasks:
        n_tr, n_te = counts[task]
        tr = simulate_scenes(work / f"{task}-train", TASK_KINDS[task], n_tr, 10 * seed + 1,
                             False, progress)
        te = simulate_scenes(work / f"{task}-test", TASK_KINDS[task], n_te, 10 * seed + 2,
                             True, progress)
        rows = run_task(task, [str(tr)], [str(te)], windows, seed, label="sim",
                        progress=progress)
        sections.append((f"{task} (simulated, unseen seeds and surfaces)", f"pareto-{task}.png",
                         rows))
    if data_dir is not None:
        man = real_manifest(data_dir, work)
        rows = run_task("texture", [str(man)], None, windows, seed, split="time",
                        contact_only=True, label="real", progress=progress)
        sections.append(("concrete vs smooth (real roboskin clips, first 70% / last 30%, "
                         "contact windows)", "pareto-real-texture.png", rows))
    return write_report(sections, out, command)
