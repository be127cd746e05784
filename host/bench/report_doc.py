"""The markdown and figures of ``host report`` (:mod:`host.bench.report`): one
table per section (mean ± sd over seeds and the whole per-decision cost), the
regulariser comparison, and an accuracy-vs-T figure with error bars."""
from __future__ import annotations

import math
from pathlib import Path

from host.analysis.figures import pyplot, save_figure
from host.bench.costs import PI4_FACTOR, PI4_SOURCE, machine_line
from host.learn.tasks import DEFAULT_ALPHA, TASK_HIDDEN


def _alpha(a: float) -> str:
    """An L2 weight as the docs write it: 1e-3."""
    return f"{a:.0e}".replace("e-0", "e-").replace("e+0", "e")

__all__ = ["FPS", "pm", "pareto", "section_table", "regulariser_table", "regulariser_verdict",
           "plot_accuracy_vs_t", "render"]

#: the frame rate of the time-to-decision column
FPS = 120
MARKERS = {"rule": "s", "ridge": "D", "fnn": "o", "grid-fnn": "^", "cnn": "P"}


def pm(mean: float, sd: float, n: int, digits: int = 3) -> str:
    """``mean ± sd (n)``, or ``-`` when nothing was scored."""
    if not n or not math.isfinite(mean):
        return "-"
    return f"{mean:.{digits}f} ± {sd:.{digits}f} ({n})"


def _time_to_decision(row: dict, cost: dict | None) -> float:
    return 1000.0 * row["T"] / FPS + (cost["cpu"]["p50"] if cost else 0.0)


def pareto(points: list[tuple[float, float]], lower_better: bool) -> set[int]:
    """Indices of the (time, score) points that no other point beats on both."""
    keep = set()
    for i, (t, s) in enumerate(points):
        better = [(t2 <= t and (s2 < s if lower_better else s2 > s)) or (t2 < t and s2 == s)
                  for j, (t2, s2) in enumerate(points) if j != i]
        if not any(better):
            keep.add(i)
    return keep


def _ms(d: dict | None) -> str:
    if not d or d.get("p50") is None:
        return "-"
    return f"{d['p50']:.3f} / {d['p99']:.3f}"


def section_table(rows: list[dict], timing: dict) -> str:
    """Markdown table of aggregated rows (:func:`host.bench.sweep.aggregate`) of one
    section; ``timing[(kind, T)]`` is the cost of that model (or missing)."""
    ok = [r for r in rows if r["n"]]
    lower = bool(ok) and ok[0]["metric"] == "mae"
    front = pareto([(_time_to_decision(r, timing.get((r["kind"], r["T"]))), r["mean"])
                    for r in ok], lower)
    lines = [f"| kind | T | {'MAE' if lower else 'accuracy'} mean ± sd (seeds) | int8 copy | "
             "vision CPU ms | window + model CPU ms | per decision CPU ms | per decision "
             f"wall ms | Pi 4 est. ms | to a decision @{FPS} fps ms | Pareto |",
             "|---|--:|--:|--:|--:|--:|--:|--:|--:|--:|:-:|"]
    for i, r in enumerate(ok):
        c = timing.get((r["kind"], r["T"]))
        int8 = pm(r["int8_mean"], r["int8_sd"], r["int8_n"])
        if r["int8_errors"]:
            failed = f"failed its check for {r['int8_errors']} of {r['n']} seeds, float kept"
            int8 = failed if not r["int8_n"] else f"{int8}; {failed}"
        lines.append(f"| {r['kind']} | {r['T']} | {pm(r['mean'], r['sd'], r['n'], 4)} | {int8} | "
                     f"{_ms(c and c['vision']['cpu'])} | {_ms(c and c['model']['cpu'])} | "
                     f"{_ms(c and c['cpu'])} | {_ms(c and c['wall'])} | {_ms(c and c['pi4'])} | "
                     f"{_time_to_decision(r, c):.1f} | {'*' if i in front else ''} |")
    for r in rows:
        for e in r["errors"]:
            lines.append(f"| {r['kind']} | {r['T']} | not trained: {e} | | | | | | | | |")
    return "\n".join(lines)


def regulariser_table(rows: list[dict]) -> str:
    """Markdown table: accuracy mean ± sd of each fnn regulariser per data set."""
    names = {"fnn": f"L2 penalty alpha = {_alpha(DEFAULT_ALPHA['fnn'])} (shipped)",
             "fnn-dropout": "dropout 0.2 (paper)"}
    data = sorted({r["data"] for r in rows})
    lines = ["| fnn regulariser | " + " | ".join(data) + " |",
             "|---|" + "--:|" * len(data)]
    for kind, name in names.items():
        cells = []
        for d in data:
            r = next((r for r in rows if r["kind"] == kind and r["data"] == d), None)
            cells.append("-" if r is None else pm(r["mean"], r["sd"], r["n"], 4))
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def regulariser_verdict(rows: list[dict]) -> str:
    """One sentence per data set: dropout's mean accuracy minus L2's, and whether
    the difference exceeds the larger of the two sds."""
    out = []
    for d in sorted({r["data"] for r in rows}):
        l2 = next((r for r in rows if r["data"] == d and r["kind"] == "fnn" and r["n"]), None)
        do = next((r for r in rows if r["data"] == d and r["kind"] == "fnn-dropout" and r["n"]),
                  None)
        if l2 is None or do is None:
            continue
        diff = do["mean"] - l2["mean"]
        within = abs(diff) <= max(l2["sd"], do["sd"])
        out.append(f"{d}: dropout {'-' if diff < 0 else '+'}{abs(diff):.4f} against L2 "
                   f"({'within' if within else 'beyond'} one sd).")
    return " ".join(out)


def plot_accuracy_vs_t(rows: list[dict], out: Path, title: str) -> Path:
    """Score against T, one line per kind, error bars of one sd over the seeds."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 4.0))
    ok = [r for r in rows if r["n"]]
    for kind in dict.fromkeys(r["kind"] for r in ok):
        rs = sorted((r for r in ok if r["kind"] == kind), key=lambda r: r["T"])
        ax.errorbar([r["T"] for r in rs], [r["mean"] for r in rs], yerr=[r["sd"] for r in rs],
                    marker=MARKERS.get(kind, "o"), capsize=3, label=kind)
    lower = bool(ok) and ok[0]["metric"] == "mae"
    ax.set_xlabel("window T [frames]")
    ax.set_ylabel("held-out MAE" if lower else "held-out accuracy")
    ax.set_title(title, fontsize=10)
    if ok:
        ax.legend(fontsize=8)
        ax.set_xticks(sorted({r["T"] for r in ok}))
    ax.grid(alpha=0.3)
    return save_figure(fig, out)


def _header(doc: dict) -> list[str]:
    v = doc.get("vision")
    real_grid = next((s for s in doc["sections"] if s["real"]), None)
    sim_grid = next((s for s in doc["sections"] if not s["real"]), None)
    grid = []
    if real_grid:
        grid.append(f"the real sections train every kind at T = "
                    f"{', '.join(map(str, real_grid['windows']))} with seeds "
                    f"{', '.join(map(str, real_grid['seeds']))}")
    if sim_grid:
        grid.append(f"the simulated sections use a reduced grid, T = "
                    f"{', '.join(map(str, sim_grid['windows']))} with seeds "
                    f"{', '.join(map(str, sim_grid['seeds']))}, to keep the run affordable")
    vis = ("The vision pipeline was not timed (no real frames at hand); the per-decision "
           "cost below is the window encoding and the model only." if not v else
           f"The vision pipeline (`device.pi.vision.encoder.FrameEncoder`: dome, threshold, "
           f"glare removal, centroids, tracking, contact grid, layout mapping) is timed "
           f"per frame on {v['frames']} real frames of {', '.join(v['clips'])} (profile "
           f"`{Path(str(v.get('profile', 'roboskin'))).name}`), one thread: "
           f"thread CPU time {_ms(v['plain']['cpu'])} ms (p50 / p99), wall clock "
           f"{_ms(v['plain']['wall'])} ms; with the CNN's dome crop "
           f"{_ms(v['crop']['cpu'])} ms CPU, {_ms(v['crop']['wall'])} ms wall.")
    return [
        "# What accuracy costs in time", "",
        f"Generated by `{doc['command']}`.", "",
        machine_line(doc["machine"]), "",
        "**What a decision costs.** " + vis + " A row's per-decision cost is that vision "
        "time plus the window encoding and the model (ONNX Runtime, one thread, float "
        "model, on the section's test windows), timed after the sweep, one model after "
        "another, with no cell running. Each time is given as p50 / p99 in ms; a decision's "
        "p50 is the sum of the medians, its p99 the sum of the p99s (an upper bound). The "
        "CPU columns are the thread's CPU time, which other programs on a shared machine "
        "inflate far less than the wall clock (the load average above says how busy it "
        "was); the wall column is what a caller waited here. The time to a decision is "
        f"the window's length T/fps at {FPS} fps plus the per-decision CPU p50. `*` marks "
        "the Pareto front (no other row of the section is both "
        "quicker to a decision and better).", "",
        f"**Raspberry Pi 4 estimate.** The Pi 4 column multiplies this machine's CPU times by "
        f"{PI4_FACTOR:g}: a Pi 4 core is taken to be about {PI4_FACTOR:g}x slower than one "
        f"core here; {PI4_SOURCE}.", "",
        "**Seeds.** Scores are the mean ± sample sd over the seeds (the number in brackets "
        "counts the seeds that trained); " + "; ".join(grid) + ". The times are those of "
        "the first seed's model. Every kind trains with its default settings; the int8 "
        "copy is kept only where it passes the >= 99 % argmax agreement check. "
        + ("" if doc.get("cnn") else "The CNN (PyTorch) is left out of this run to keep it "
           "affordable; `--cnn` adds it. ")
        + "The simulated sections use the vision time measured on the real frames.", "",
        f"**Running the sweep.** Each (data, kind, T, seed) is one cell of a joblib sweep "
        f"(`host.bench.sweep`), run here with `--jobs {doc['jobs']}`. `host report --jobs N` "
        "runs N worker processes; the same cells run on a Dask or Ray cluster through "
        "joblib's backends:", "",
        "```python",
        "from dask.distributed import Client",
        "from joblib import parallel_config",
        "from host.bench.report import build_report",
        "",
        "Client(\"tcp://scheduler:8786\")         # registers joblib's \"dask\" backend",
        "with parallel_config(backend=\"dask\"):   # Ray: ray.util.joblib.register_ray(), \"ray\"",
        "    build_report(\"docs/accuracy-vs-time.md\", \"out/report\",",
        "                 [\"out/specs/lego-vs-smooth.csv\"], profile=\"roboskin\", jobs=-1)",
        "```", "",
        "The cells only train and score; the timing pass runs in the calling process "
        "after they finish, so the cluster's load does not reach the times.", ""]


REGULARISER_TEXT = (
    "The paper's FNN uses dropout 0.2; the fnn here ships with an L2 penalty "
    f"(scikit-learn's MLP, alpha = {_alpha(DEFAULT_ALPHA['fnn'])}). The two variants below share "
    "the inputs, the lost-pin mask, the frame-to-frame first layer, the scaling, the "
    f"hidden layers {TASK_HIDDEN['texture']}, Adam and the early stopping "
    "(`host.bench.regularise`); only the regulariser differs. Same data, split and seeds "
    "as the sections above, T = {T}.")


def render(doc: dict, table=section_table, reg_table=regulariser_table) -> str:
    parts = _header(doc)
    timing = {}
    for t in doc["timing"]:
        timing.setdefault(t["data"], {})[(t["kind"], t["T"])] = t
    for s in doc["sections"]:
        rows = [a for a in doc["aggregate"] if a["data"] == s["key"] and a["T"] in s["windows"]
                and a["kind"] in s["kinds"]]
        parts += [f"## {s['title']}", "", s["trained_on"]]
        if s.get("split"):
            parts[-1] += f" Split: {s['split']}."
        n = next((a for a in rows if a["n"]), None)
        if n:
            parts[-1] += f" {n['n_train']} training and {n['n_test']} test windows at T = {n['T']}."
        parts += ["", table(rows, timing.get(s["key"], {})), "",
                  f"![{s['title']}](img/{s['figure']})", ""]
    reg = [a for a in doc["aggregate"] if a["T"] == doc.get("regulariser_T")
           and a["kind"] in ("fnn", "fnn-dropout")
           and any(s["key"] == a["data"] and s["real"] for s in doc["sections"])]
    if any(a["kind"] != "fnn" for a in reg):
        parts += ["## The fnn's regulariser: L2 or dropout 0.2 (real clips)", "",
                  REGULARISER_TEXT.format(T=doc["regulariser_T"]), "", reg_table(reg), "",
                  regulariser_verdict(reg), ""]
    return "\n".join(parts)
