"""What a model folder says about itself, written from its model spec.

* :func:`card_text` / :func:`write_card`: ``README.md``, the model card: what the
  model decides, its classes, the sensor (profile name, pin count, hash), the data
  (real or simulated, which recordings), the protocol (the split), accuracy with
  its interval and count where the metrics have them, the int8 agreement, the
  size and the cost per decision where it is known. One function writes it from a
  :class:`device.pi.models.spec.ModelSpec`.
* :func:`write_train_toml` / :func:`read_train_toml`: ``train.toml``, the config
  that made the model (the spec's ``config``); ``host train --config FILE``
  replays it.
* :func:`recordings_of`: the training data's recordings with checksums, from
  data specs (CSV manifests, dataset folders, ``.npz`` files).
* :func:`measure_cost`: the cost per decision of a model folder's files, timed
  single-threaded on this machine; :func:`write_model_docs` records it in the
  manifest (``cost_per_decision``) before it writes the card from the spec.
* :func:`write_model_docs`: both files for a model folder, from its manifest.
"""
from __future__ import annotations

import csv
import json
import math
import os
import platform
import time
from pathlib import Path

import numpy as np

from device.config import read_toml
from device.pi.models.artefact import ort_session, sha256_file
from device.pi.models.manifest import MANIFEST, read_spec, write_variant_specs
from device.pi.models.spec import ModelSpec
from host.data.dataset import atomic_write_text

__all__ = ["card_text", "write_card", "write_train_toml", "read_train_toml", "toml_text",
           "recordings_of", "data_source", "measure_cost", "machine_text", "write_model_docs",
           "CARD", "TRAIN_TOML"]

CARD = "README.md"
TRAIN_TOML = "train.toml"

#: what each kind of model decides, for the card
DECIDES = {
    "surface": "the surface under the foot at each decision (from the pin displacement "
               "field over the last T frames, and the IMU where the model uses it)",
    "texture": "the floor's texture while the foot is in contact",
    "slip": "whether the foot is slipping (a slip event and its confidence)",
    "pressure": "the contact pressure (a value per decision, in the training targets' units)",
    "localiser": "the pins' positions in a frame (the pin localiser of the marker pipeline)",
}


# -- train.toml ------------------------------------------------------------------

def _toml_value(v, key: str) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            raise ValueError(f"train.toml: {key} must be a finite number, got {v!r}")
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x, key) for x in v) + "]"
    raise ValueError(f"train.toml: {key} must be a string, number, true/false or a list, "
                     f"got {type(v).__name__}")


def toml_text(config: dict, header: str = "") -> str:
    """``config`` as TOML: top-level keys (strings, numbers, booleans, lists), then
    one table per dict value. None values are left out."""
    lines = [f"# {h}" for h in header.splitlines()] if header else []
    tables = []
    for k, v in config.items():
        if v is None:
            continue
        if isinstance(v, dict):
            tables.append((k, v))
        else:
            lines.append(f"{k} = {_toml_value(v, k)}")
    for name, t in tables:
        lines += ["", f"[{name}]"]
        lines += [f"{k} = {_toml_value(v, f'{name}.{k}')}" for k, v in t.items()
                  if v is not None and not isinstance(v, dict)]
    return "\n".join(lines) + "\n"


def write_train_toml(folder: Path | str, config: dict) -> Path:
    """``folder/train.toml``: the training config that made the model."""
    path = Path(folder) / TRAIN_TOML
    how = (f"rebuild it with: {config.get('command') or 'python -m ' + config['module']}"
           if "module" in config else
           "replay it with: host train --config train.toml --out DIR")
    atomic_write_text(path, toml_text(config, f"the config that made this model; {how}"))
    return path


def read_train_toml(path: Path | str) -> dict:
    """The config of a ``train.toml`` (ConfigError naming the file when it is not TOML)."""
    return read_toml(path)


# -- provenance --------------------------------------------------------------------

def _rec(path, frames=None) -> dict:
    p = Path(path)
    return {"path": str(path), "sha256": sha256_file(p) if p.is_file() else None,
            "frames": frames}


def _folder_recordings(p: Path) -> list[dict]:
    """A dataset folder's trials, one row each: the trial file, and the clip it was
    recorded from with that clip's sha256 (``host record``); a trial without a clip
    (a simulated run, a rig trial) gives its own file's. Without a readable
    dataset.json: the folder, with dataset.json's checksum."""
    try:
        trials = json.loads((p / "dataset.json").read_text()).get("trials") or []
    except (OSError, ValueError, AttributeError):
        trials = None
    if not isinstance(trials, list) or not trials:
        return [dict(_rec(p / "dataset.json"), path=str(p))]
    out = []
    for t in trials:
        t = t if isinstance(t, dict) else {}
        rec = t.get("recording") if isinstance(t.get("recording"), dict) else {}
        row = _rec(p / str(t.get("file", "")))
        start, n = rec.get("start_frame"), t.get("frames")
        if rec.get("sha256"):
            row.update(sha256=rec["sha256"], clip=rec.get("file") or rec.get("id"))
        elif rec.get("id"):
            row["clip"] = rec["id"]
        if isinstance(start, int) and isinstance(n, int):
            row["frames"] = f"{start}..{start + n}"
        out.append(row)
    return out


def recordings_of(specs) -> list[dict]:
    """The recordings of data ``specs``: each row of a CSV manifest (its file, with the
    frame range when the row gives one), a dataset folder (its dataset.json), an
    ``.npz``. Each ``{"path", "sha256", "frames"}``; sha256 null where the source is
    not a file (``sim://``, a folder of images) or is missing. A dataset folder
    gives one row per trial, with ``clip``: the clip it was recorded from and that
    clip's sha256 (:func:`_folder_recordings`)."""
    out = []
    for spec in specs or []:
        p = Path(spec)
        if p.suffix == ".csv" and p.is_file():
            with open(p, newline="") as fh:
                for row in csv.DictReader(fh):
                    src = (row.get("path") or "").strip()
                    if not src:
                        continue
                    a, b = (row.get("start_frame") or "").strip(), (row.get("end_frame")
                                                                    or "").strip()
                    frames = f"{a or 0}..{b or 'end'}" if (a or b) else None
                    full = src if "://" in src or Path(src).is_absolute() else str(p.parent / src)
                    out.append(_rec(full, frames) if "://" not in src else
                               {"path": src, "sha256": None, "frames": frames})
        elif p.is_dir():
            out += _folder_recordings(p)
        else:
            out.append(_rec(p))
    return out


def data_source(recordings: list[dict]) -> str:
    """real, simulated, real+simulated or unknown, from the recordings' paths (a
    ``sim://`` scene, or a dataset folder whose trials came from the simulator)."""
    kinds = set()
    for r in recordings:
        path = str(r.get("path", ""))
        if path.startswith("sim://"):
            kinds.add("simulated")
        elif Path(path).is_dir():
            try:
                doc = json.loads((Path(path) / "dataset.json").read_text())
                srcs = {str(t.get("source", "")) for t in doc.get("trials", [])}
            except (OSError, ValueError, AttributeError):
                srcs = set()
            kinds.add("simulated" if srcs and all(s.startswith("sim://") for s in srcs)
                      else "real" if srcs else "unknown")
        elif path.endswith(".npz"):
            kinds.add("unknown")
        else:
            kinds.add("real")
    kinds.discard("unknown") if len(kinds) > 1 else None
    if kinds == {"real", "simulated"}:
        return "real+simulated"
    return kinds.pop() if len(kinds) == 1 else "unknown"


# -- the card ----------------------------------------------------------------------

def _num(v, digits: int = 3) -> str:
    return f"{v:.{digits}f}" if isinstance(v, float) else str(v)


def _figure(m: dict) -> str | None:
    """'accuracy 0.957 [0.93, 0.98], n=211' from a metrics dict, or None."""
    for key in ("accuracy", "macro_f1", "mae", "median_px"):
        v = m.get(key)
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            ci = m.get(f"{key}_ci95")
            n = m.get("n_windows", m.get("n", m.get("n_pins")))
            return (f"{key} {_num(v)}" + (f" [{_num(ci[0])}, {_num(ci[1])}] (95 % interval)"
                                           if isinstance(ci, list) and len(ci) == 2 else "")
                    + (f", n={n}" if n is not None else ""))
    return None


def _metric_lines(spec: ModelSpec) -> list[str]:
    out = []
    names = {"test": "held-out test", "cv": "cross-validation", "train": "training data"}
    for k in ("test", "cv", "train"):
        m = spec.metrics.get(k)
        if not m:
            continue
        fig = _figure(m)
        if fig:
            out.append(f"- {names[k]}: {fig}")
        else:
            for sub, sm in m.items():         # a dict of named tests (the localiser)
                if isinstance(sm, dict) and _figure(sm):
                    out.append(f"- {names[k]}, {sub}: {_figure(sm)}")
        if isinstance(m, dict) and m.get("same_recordings"):
            out.append("  - the test windows come from the training recordings: optimistic")
    return out or ["- no metrics recorded"]


def _int8_line(spec: ModelSpec) -> str:
    q = spec.measured.int8
    if not q:
        return "not quantised (float model)"
    if q.get("failed"):
        return f"the int8 copy failed its check, the float model is loaded: {q['failed']}"
    if q.get("skipped"):
        return str(q["skipped"])
    if "agreement" in q:
        return (f"argmax agreement {_num(q['agreement'], 4)} with the float model on "
                f"{q.get('n', '?')} {q.get('checked_on', 'windows')}"
                + (f" (accuracy change {_num(q['accuracy_change'], 4)})"
                   if isinstance(q.get("accuracy_change"), float) else ""))
    if "mae_change" in q:
        return (f"MAE change {_num(q['mae_change'], 4)} vs the float model on "
                f"{q.get('n', '?')} {q.get('checked_on', 'windows')}")
    return json.dumps(q)[:200]


def _identity_lines(spec: ModelSpec) -> list[str]:
    """The recording-identity check (host.learn.identity): its verdict per class, or
    why there is none (not run, a rule, one recording a class), and its warning,
    where the spec's metrics carry one."""
    from host.learn.identity import verdict_lines
    check = spec.measured.identity
    if isinstance(check, dict) and (check.get("classes") or check.get("skipped")):
        verdict = check.get("verdict") or ("flagged" if check.get("flagged") else
                                           "no verdict" if check.get("skipped") else
                                           "not flagged")
        out = [f"- recording-identity check: {verdict}"
               + (f" ({check['skipped']})" if check.get("skipped") else "")]
        out += [f"  - {line}" for line in verdict_lines(check) if not check.get("skipped")]
    elif spec.model == "rule":
        out = ["- recording-identity check: not run (a rule learns no recording)"]
    else:
        out = ["- recording-identity check: not run (`host train --no-identity-check`, "
               "or a model made before the check)"]
    warned = False
    for k in ("test", "cv", "train"):
        w = (spec.metrics.get(k) or {}).get("identity_warning")
        if w and f"- warning: {w}" not in out:
            out.append(f"- warning: {w}")
            warned = True
    if warned:
        out.append("  - the recording-identity check (host.learn.identity): a simple probe "
                   "tells apart recordings of one class; test on a separate recording")
    return out


def _cost_lines(spec: ModelSpec) -> list[str]:
    c = spec.measured.cost_per_decision
    if not isinstance(c, dict) or not isinstance(c.get("files"), dict):
        return ["- cost per decision: not measured here (see docs/BENCHMARKS.md, "
                "`host bench runtime`)"]
    out = [f"- cost per decision, `{f}`: median {float(r['median_ms']):.3g} ms, p99 "
           f"{float(r['p99_ms']):.3g} ms over {r['n']} runs"
           for f, r in c["files"].items()]
    out.append(f"  - one ONNX Runtime session, {c.get('threads', 1)} thread, one window "
               f"({c.get('inputs', 'inputs of its shape')}); on {c.get('machine', '?')}")
    return out


def _augment_lines(training: dict) -> list[str]:
    """The copies the fit added: frame-rate (host.learn.rates) and session
    (host.learn.sessions) copies, as the spec's ``training`` records them."""
    out = []
    if training.get("rates"):
        out.append(f"- trained also on frame-rate copies: {', '.join(training['rates'])}")
    s = training.get("sessions")
    if s:
        out.append(f"- trained also on {s.get('copies')} session copies (host.learn.sessions): "
                   f"gain {s.get('gain')}, gamma {s.get('gamma')}, offset {s.get('offset')}, "
                   f"layout up to {s.get('shift_px')} px / {s.get('scale')} scale / "
                   f"{s.get('rotate_deg')} deg, lost pins {s.get('lost')}; "
                   f"{s.get('frame_level_trials')} re-extracted, "
                   f"{s.get('lost_pins_only_trials')} with lost pins only")
    return out


def card_text(spec: ModelSpec, name: str = "") -> str:
    """The model card (markdown) of ``spec``; ``name`` is the model folder's name."""
    t = spec.measured.trained_on
    recs = t.get("recordings") or []
    lines = [f"# Model card: {name or spec.kind}", "",
             f"Written from the model's {MANIFEST} (the model spec) by "
             "`host.learn.card`; do not edit by hand.", "",
             "## What it decides", "",
             f"{DECIDES.get(spec.kind, spec.task)}.", "",
             f"- task `{spec.task}`, model `{spec.model}`, T = {spec.T} frame(s), input "
             f"`{spec.input_layout}` ({spec.n_inputs} values"
             + (", with the IMU" if spec.uses_imu else "") + ")"
             + (f", crops of {spec.crop_size} px" if spec.crop_size else ""),
             "- classes: " + (", ".join(f"`{c}`" for c in spec.classes) if spec.classes
                              else "none (a regressor)"), "",
             "## Sensor", "",
             f"- profile `{spec.profile['name']}`, {spec.profile['n_pins']} pins, "
             f"sha256 `{spec.profile['sha256'][:16]}`",
             f"- the profile's full text is in {MANIFEST} (`profile.toml`); host eval, "
             "analyse, bench and the runtime use it, and refuse another profile", "",
             "## Data", "",
             f"- {t.get('data', 'unknown')} data"
             + (f"; scenes {t['scenes']}" if t.get("scenes") else "")
             + (f", {t['trials_per_kind']} trials per kind" if t.get("trials_per_kind")
                else "")]
    if recs:
        lines += ["", "| recording | clip | sha256 | frames |", "|---|---|---|---|"]
        lines += [f"| {r['path']} | {r.get('clip') or '-'} | {r.get('sha256') or '-'} | "
                  f"{r.get('frames') if r.get('frames') is not None else 'all'} |"
                  for r in recs]
    lines += ["", "## Protocol", "", f"- {t.get('split') or 'not recorded'}"]
    lines += _augment_lines(getattr(spec, "training", None) or {})
    if isinstance(t.get("real_accuracy"), (int, float)):
        lines.append(f"- accuracy on real frames: {_num(t['real_accuracy'])}")
    lines += ["", "## Accuracy", ""] + _metric_lines(spec) + _identity_lines(spec)
    lines += ["", "## int8", "", f"- {_int8_line(spec)}", "", "## Size and cost", ""]
    files = spec.files or ({spec.onnx: {"size_bytes": spec.size_bytes}} if spec.onnx else {})
    for f, rec in files.items():
        lines.append(f"- `{f}`: {rec.get('size_bytes', '?')} bytes"
                     + (" (loaded by default)" if f == spec.onnx else ""))
    if not files:
        lines.append("- a rule: no model file")
    lines += _cost_lines(spec)
    if spec.config:
        lines += ["", "## How it was made", "",
                  "`train.toml` beside this file holds the config; replay it with "
                  "`host train --config train.toml --out DIR`." if "task" in spec.config
                  and "module" not in spec.config else
                  f"`train.toml` beside this file holds the config "
                  f"({spec.config.get('module', spec.config.get('made_by', 'host train'))})."]
    return "\n".join(lines) + "\n"


def write_card(folder: Path | str, spec: ModelSpec) -> Path:
    path = Path(folder) / CARD
    atomic_write_text(path, card_text(spec, Path(folder).name))
    return path


def machine_text() -> str:
    """This machine, for a timing: CPU model, cores, load, ONNX Runtime version."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        import onnxruntime
        ort = f", onnxruntime {onnxruntime.__version__}"
    except ImportError:                          # pragma: no cover - a host dependency
        ort = ""
    load = f", load {os.getloadavg()[0]:.1f}" if hasattr(os, "getloadavg") else ""
    return f"{cpu} ({platform.machine()}, {os.cpu_count()} cores{load}){ort}"


_DTYPES = {"tensor(float)": np.float32, "tensor(double)": np.float64,
           "tensor(uint8)": np.uint8, "tensor(int64)": np.int64, "tensor(int32)": np.int32}


def _one_input(session, spec: ModelSpec, seed: int = 0) -> tuple[str, np.ndarray]:
    """A window of the model's input shape (batch 1): seeded standard normal values,
    clipped to the spec's ``input_clip`` where it has one (uint8 images: 0..255)."""
    inp = session.get_inputs()[0]
    shape = [d if isinstance(d, int) and d > 0 else 1 for d in inp.shape]
    dtype = _DTYPES.get(inp.type, np.float32)
    rng = np.random.default_rng(seed)
    if np.issubdtype(dtype, np.integer):
        x = rng.integers(0, 256, size=shape).astype(dtype)
    else:
        x = rng.standard_normal(shape).astype(dtype)
        clip = getattr(spec.params, "input_clip", None)
        if isinstance(clip, list) and len(clip) == 2 and len(clip[0]) == x.shape[-1]:
            x = np.clip(x, np.asarray(clip[0], dtype), np.asarray(clip[1], dtype))
    return inp.name, x


def measure_cost(folder: Path | str, spec: ModelSpec, inputs: np.ndarray | None = None,
                 runs: int = 200, budget_s: float = 1.0) -> dict:
    """The cost per decision of each model file of ``folder``: one single-threaded
    ONNX Runtime session run on one window (``inputs[:1]``, else a window of the
    model's shape, :func:`_one_input`), ``runs`` timed runs after 10 untimed ones
    (fewer, at least 20, when they pass ``budget_s``). Returns ``{"files": {name:
    {"median_ms", "p99_ms", "n"}}, "threads": 1, "inputs", "machine"}``."""
    if isinstance(runs, bool) or not isinstance(runs, int) or runs < 20:
        raise ValueError(f"measure_cost: runs must be a whole number >= 20, got {runs!r}")
    folder = Path(folder)
    names = list(spec.files or {}) or ([spec.onnx] if spec.onnx else [])
    out = {"files": {}, "threads": 1,
           "inputs": ("a window of its own inputs" if inputs is not None else
                      "a window of its input shape, seeded normal values"),
           "machine": machine_text()}
    for name in names:
        sess = ort_session(str(folder / name), threads=1)
        in_name, x = _one_input(sess, spec)
        if inputs is not None:
            x = np.ascontiguousarray(np.asarray(inputs)[:1], x.dtype).reshape(x.shape)
        for _ in range(10):
            sess.run(None, {in_name: x})
        times = []
        end = time.perf_counter() + budget_s
        while len(times) < runs and (len(times) < 20 or time.perf_counter() < end):
            t = time.perf_counter_ns()
            sess.run(None, {in_name: x})
            times.append((time.perf_counter_ns() - t) / 1e6)
        out["files"][name] = {"median_ms": round(float(np.median(times)), 4),
                              "p99_ms": round(float(np.percentile(times, 99)), 4),
                              "n": len(times)}
    return out


def write_model_docs(folder: Path | str, measure: bool = True,
                     inputs: np.ndarray | None = None) -> dict:
    """README.md (the model card) and, when the spec has a config, train.toml, for
    the model folder ``folder`` from its spec. With ``measure`` (a writer that did
    not time the model itself), the cost per decision is timed here first
    (:func:`measure_cost`, on ``inputs`` when given) and recorded in the spec's
    ``measured`` (the manifests written again, from the spec). Returns {name: path}."""
    spec, _ = read_spec(folder)
    if measure and (spec.files or spec.onnx):
        spec.measured.cost_per_decision = measure_cost(folder, spec, inputs)
        write_variant_specs(folder, spec)
    out = {CARD: write_card(folder, spec)}
    if spec.config:
        out[TRAIN_TOML] = write_train_toml(folder, spec.config)
    return out
