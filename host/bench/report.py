"""``host report``: what accuracy costs in time.

Sections: one real section per data spec the caller gives (a CSV manifest or a
dataset folder, as ``host train --data`` takes; each trained on the first 70 % of
each recording, tested on its last 30 % after a gap of T frames, contact windows
only, features with the caller's sensor profile), the fnn's regulariser on those
tasks (L2 against the paper's dropout 0.2, :mod:`host.bench.regularise`) and the
simulated tasks. The report names no recording of its own: the authors' clips come
in through the default specs of :mod:`host.bench.specs`. Every spec and the profile
are checked before the long work starts. Every (data, kind, T, seed) is one cell of a joblib sweep
(:mod:`host.bench.sweep`); the tables give the held-out score's mean and sd over
the seeds, and the whole per-decision cost: the vision pipeline per frame on real
frames (:mod:`host.bench.costs`), the window encoding and the model, timed one
after another on one thread, with the estimated Raspberry Pi 4 figure beside it.
Each section has an accuracy-vs-T figure with error bars.
"""
from __future__ import annotations

import json
from pathlib import Path

from host.bench import costs
from host.bench.regularise import REGULARISERS
from host.bench.report_doc import plot_accuracy_vs_t, render
from host.bench.scenes import simulate_scenes
from host.bench.specs import check_profile, check_specs, recording_frames, spec_name
from host.bench.sweep import Cell, aggregate, run_cells, time_models
from host.data.dataset import atomic_write_text
from host.data.load import load_specs
from host.data.splits import split_holdout
from host.learn.tasks import OPTIONAL_MODELS, TASK_MODELS
from host.extras import need

__all__ = ["REAL_WINDOWS", "SEEDS", "SIM_WINDOWS", "SIM_SEEDS", "TASK_KINDS",
           "REPORT_TRIALS", "REGULARISER_T", "models_for", "Section",
           "real_sections", "sim_sections", "split_text", "prepare", "sweep_cells", "build_report",
           "write_report"]

REAL_WINDOWS = tuple(range(1, 11))
SEEDS = (0, 1, 2)
#: the simulated sections' reduced grid
SIM_WINDOWS = (1, 3, 10)
SIM_SEEDS = (0, 1)
#: T of the regulariser comparison (the longest window of the real grid)
REGULARISER_T = REAL_WINDOWS[-1]
#: the simulated scene kinds behind each task (host.bench.scenes.simulate_scenes)
TASK_KINDS = {"surface": ("hard", "soft", "wet", "no-touch"),
              "texture": ("lego", "concrete", "smooth"),
              "slip": ("slip",), "pressure": ("press-hard", "press-soft")}
#: (train, test) trials per kind
REPORT_TRIALS = {"full": {"surface": (8, 3), "texture": (6, 2), "slip": (10, 3),
                          "pressure": (8, 3)},
                 "quick": {"surface": (3, 1), "texture": (2, 1), "slip": (3, 1),
                           "pressure": (3, 1)}}


def _have_torch() -> bool:
    try:
        import torch  # noqa: F401
        return True
    except ImportError:
        return False


def models_for(task: str, cnn: bool = True) -> list[str]:
    models = [m for m in TASK_MODELS[task] if m not in OPTIONAL_MODELS]
    if cnn and "cnn" in TASK_MODELS[task] and _have_torch():
        models.append("cnn")
    return models


class Section:
    """One section of the report: its data, kinds, window lengths and seeds, and a
    sentence saying what was trained and tested on."""

    def __init__(self, key, title, task, kinds, windows, seeds, trained_on, real,
                 train_specs, test_specs=None, profile: str = "roboskin", recordings=()):
        self.key, self.title, self.task = key, title, task
        self.kinds, self.windows, self.seeds = list(kinds), tuple(windows), tuple(seeds)
        self.trained_on, self.real = trained_on, real
        self.train_specs, self.test_specs = list(train_specs), test_specs
        self.profile, self.recordings = profile, list(recordings)
        self.how = ""


def _names(items) -> str:
    items = [f"`{x}`" for x in dict.fromkeys(items)]
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " and " + items[-1]


def real_sections(specs, windows=REAL_WINDOWS, seeds=SEEDS, cnn: bool = False, kinds=None,
                  profile: str = "roboskin", task: str = "texture") -> list[Section]:
    """One section per data spec (a CSV manifest or a dataset folder), its features
    computed with ``profile``. Every file is checked first (a DataError names the
    first missing one)."""
    found = check_specs(specs, task)
    out, keys = [], set()
    for spec, recs in found.items():
        key = spec_name(spec)
        while key in keys:
            key += "-2"
        keys.add(key)
        labels = [r.label for r in recs if r.label]
        title = (" vs ".join(dict.fromkeys(labels)) or task) + f" (real, {Path(spec).name})"
        trained = (f"Real frames of `{Path(spec).name}`, profile `{Path(str(profile)).name}`. "
                   f"Trained on the first 70 % of {_names(r.name for r in recs)}, tested on "
                   f"the last 30 % of each after a gap of at least T frames (the time split "
                   f"of `host.data.splits.split_holdout`), contact windows only; the fnn "
                   f"ignores pins that a training recording keeps losing (T >= 2, as `host "
                   f"train` does); the grid-fnn, which reads the contact grid, has no such "
                   f"mask. Later frames of the same recordings are an optimistic test: a "
                   f"separate recording is the honest one.")
        out.append(Section(key, title, task, kinds or models_for(task, cnn), windows, seeds,
                           trained, True, [spec], profile=profile, recordings=recs))
    return out


def sim_sections(work: Path, quick: bool, tasks, windows=SIM_WINDOWS, seeds=SIM_SEEDS,
                 progress: bool = True, cnn: bool = True) -> list[Section]:
    counts = REPORT_TRIALS["quick" if quick else "full"]
    out = []
    for task in tasks:
        n_tr, n_te = counts[task]
        tr = simulate_scenes(work / f"{task}-train", TASK_KINDS[task], n_tr, 1, False, progress)
        te = simulate_scenes(work / f"{task}-test", TASK_KINDS[task], n_te, 2, True, progress)
        trained = (f"Simulated. Trained on {n_tr} simulated trial(s) per kind "
                   f"({', '.join(TASK_KINDS[task])}), tested on {n_te} trial(s) per kind with "
                   f"unseen simulator seeds and surface parameters beyond the training "
                   f"ranges; default settings per kind.")
        out.append(Section(f"sim-{task}", f"{task} (simulated)", task, models_for(task, cnn),
                           windows, seeds, trained, False, [str(tr)], [str(te)]))
    return out


def split_text(how: str, T: int) -> str:
    """``split_holdout``'s account of a split, for every T of a section."""
    return how.replace(f"a gap of {T} frames", "a gap of T frames")


def prepare(sections: list[Section], regularise: bool = True, progress: bool = False) -> dict:
    """{(section key, T): (train, test) WindowSets}, each clip's frames encoded once."""
    tqdm = need("tqdm").tqdm

    windows = {}
    todo = [(s, T) for s in sections
            for T in sorted(set(s.windows) | ({REGULARISER_T} if s.real and regularise else set()))]
    caches: dict = {}
    for s, T in tqdm(todo, desc="host report: windows", unit="set", disable=not progress or None):
        cache = caches.setdefault(s.key, {})
        ws = load_specs(s.train_specs, task=s.task, window=T, contact_only=s.real,
                        profile=s.profile, progress=False, cache=cache)
        if s.test_specs:
            te = load_specs(s.test_specs, task=s.task, window=T, profile=s.profile,
                            progress=False, cache=cache, min_classes=1)
            windows[(s.key, T)] = (ws, te)
            continue
        tr_idx, te_idx, how = split_holdout(ws, 0.3, 0)
        windows[(s.key, T)] = (ws.subset(tr_idx), ws.subset(te_idx))
        if T == min(s.windows):
            s.how = split_text(how, T)
    return windows


#: the order the sweep takes window lengths in, so that a coarse grid finishes first
T_ORDER = (1, 10, 5, 3, 2, 7, 4, 8, 6, 9)


def sweep_cells(sections: list[Section], regularise: bool = True) -> list[Cell]:
    """Every (section, kind, T, seed), coarse T first (:data:`T_ORDER`), and with
    ``regularise`` the fnn's dropout variant at :data:`REGULARISER_T` on the real
    sections."""
    def rank(T):
        return T_ORDER.index(T) if T in T_ORDER else len(T_ORDER) + T

    cells = [Cell(s.key, s.task, k, T, seed) for s in sections
             for T in sorted(s.windows, key=rank) for k in s.kinds for seed in s.seeds]
    if regularise:
        for s in sections:
            if s.real:
                kinds = (["fnn"] if REGULARISER_T not in s.windows else []) + list(REGULARISERS)
                cells += [Cell(s.key, s.task, k, REGULARISER_T, seed) for k in kinds
                          for seed in s.seeds]
    cells.sort(key=lambda c: rank(c.T))
    return cells


def vision_costs(sections: list[Section], profile: str = "roboskin") -> dict | None:
    """The vision pipeline per frame (``profile``) on every recording of the real
    sections (a fresh encoder per recording), without and with the CNN's dome crop;
    None without real frames."""
    recs = list(dict.fromkeys(r for s in sections if s.real for r in s.recordings))
    frames = [f for f in (recording_frames(r) for r in recs) if len(f)]
    if not frames:
        return None
    return {"plain": costs.vision_cost(frames, profile),
            "crop": costs.vision_cost(frames, profile, crop_px=32),
            "frames": sum(len(f) for f in frames),
            "clips": list(dict.fromkeys(r.name for r in recs)), "profile": str(profile)}


def build_report(out, work, specs=None, quick: bool = False, tasks=tuple(TASK_KINDS),
                 progress: bool = True, command: str = "host report", jobs: int = 1,
                 real_windows=REAL_WINDOWS, seeds=SEEDS, sim_windows=SIM_WINDOWS,
                 sim_seeds=SIM_SEEDS, cnn: bool = False, regularise: bool = True,
                 real_kinds=None, profile: str = "roboskin", task: str = "texture") -> Path:
    """Run the sweep (``jobs`` joblib workers) and write the report ``out`` (markdown,
    a JSON twin and the figures under ``img/`` beside it). ``specs``: the real data
    specs (CSV manifests or dataset folders), one section each, features with
    ``profile``; they and the profile are checked before anything is simulated or
    trained (a DataError names the first missing file)."""
    work = Path(work)
    sections = []
    if specs:
        profile = check_profile(profile)
        sections += real_sections(specs, real_windows, seeds, cnn, real_kinds, profile, task)
    sections += sim_sections(work, quick, tasks, sim_windows, sim_seeds, progress, cnn)
    regularise = regularise and _have_torch()
    windows = prepare(sections, regularise, progress)
    cells = sweep_cells(sections, regularise)
    if progress:
        print(f"host report: {len(cells)} cells, {jobs} job(s)", flush=True)
    rows = run_cells(cells, windows, work / "models", jobs,
                     keep_seed=min(min(s.seeds) for s in sections) if sections else None,
                     progress=progress, profiles={s.key: s.profile for s in sections})
    # the times: one measurement after another, after every cell has finished
    machine = costs.machine()
    vision = vision_costs(sections, profile)
    timing = time_models(rows, windows, vision) if vision else {}
    doc = {"command": command, "machine": machine, "vision": vision, "jobs": jobs, "cnn": cnn,
           "regulariser_T": REGULARISER_T, "profile": str(profile),
           "sections": [{"key": s.key, "title": s.title, "task": s.task, "kinds": s.kinds,
                         "trained_on":
                         s.trained_on, "split": s.how, "windows": list(s.windows),
                         "seeds": list(s.seeds), "real": s.real,
                         "specs": [str(x) for x in s.train_specs] if s.real else []}
                        for s in sections],
           "cells": rows, "aggregate": aggregate(rows),
           "timing": [{"data": k[0], "kind": k[1], "T": k[2], **v} for k, v in timing.items()]}
    return write_report(doc, out)


def write_report(doc: dict, out) -> Path:
    """The markdown ``out``, its JSON twin and one accuracy-vs-T figure per section
    under ``img/`` beside it."""
    out = Path(out)
    img = out.parent / "img"
    kinds = {s["key"]: s["kinds"] for s in doc["sections"]}
    doc["aggregate"] = sorted(doc["aggregate"], key=lambda a: (
        a["data"], kinds.get(a["data"], []).index(a["kind"])
        if a["kind"] in kinds.get(a["data"], []) else len(kinds.get(a["data"], [])), a["T"]))
    for s in doc["sections"]:
        rows = [a for a in doc["aggregate"] if a["data"] == s["key"]
                and a["kind"] not in REGULARISERS and a["T"] in s["windows"]]
        s["figure"] = plot_accuracy_vs_t(rows, img / f"accuracy-vs-T-{s['key']}.png",
                                         s["title"]).name
    atomic_write_text(out, render(doc))
    atomic_write_text(out.with_suffix(".json"), json.dumps(doc, indent=1, default=float))
    return out
