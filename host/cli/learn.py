"""``host train``, ``eval`` and ``report``: models from windows of frames."""
from __future__ import annotations

import logging
import os
import time
from pathlib import Path

from device.pi.models.artefact import MAX_T
from device.pi.models.manifest import read_spec
from device.config import ConfigError
from host.bench.report import TASK_KINDS, build_report
from host.cli.common import (SEED, UserError, emit, out_folder, real_data_dir, whole,
                             whole_list)
from host.data.dataset import DatasetLocked, lock_folder
from host.data.load import load_specs
from host.data.windows import DataError
from host.learn.card import data_source, read_train_toml, recordings_of, write_model_docs
from host.learn.evaluate import eval_summary, evaluate_model
from host.learn.onnx_io import models_profile
from host.learn.config import TrainConfig
from host.learn.tasks import DEFAULT_MODEL, DEFAULT_WINDOW, MODELS, TASKS, TrainError
from host.learn.train import train

_log = logging.getLogger(__name__)


def _load_windows(args, specs, task: str, window: int, profile: str, contact_only: bool):
    try:
        return load_specs(specs, task=task, window=window, contact_only=contact_only,
                          profile=profile, progress=not args.json, min_classes=1)
    except FileNotFoundError as exc:       # a spec that names a missing file
        raise UserError(str(exc)) from None


def _jsonable(res: dict) -> dict:
    return {k: v for k, v in res.items() if k not in ("onnx", "estimator", "pipeline")}


def _lock_out(args) -> tuple[int, bool]:
    """The ``--out`` folder, created and locked (:func:`host.data.dataset.lock_folder`)
    for this run: a second ``host train`` into it is refused (exit 2) instead of the
    two writing over each other. The descriptor holding the lock, and whether the
    folder was created here."""
    out = out_folder(args.out, force=args.force)
    created = not out.exists()
    try:
        out.mkdir(exist_ok=True)
    except OSError as exc:
        raise UserError(f"--out {out}: cannot create the folder ({exc.strerror or exc})") \
            from None
    try:
        fd = lock_folder(out, "another host train is writing a model to this folder; "
                              "wait for it to finish, or choose another --out")
    except DatasetLocked:                  # its own one line (a TacfootError)
        raise
    except OSError as exc:
        raise UserError(f"--out {out}: cannot lock the folder ({exc.strerror or exc})") \
            from None
    try:
        out_folder(out, force=args.force)   # filled by a run that ended since the first check
    except BaseException:
        os.close(fd)
        raise
    return fd, created


#: the flags of host train that a train.toml replaces (flag name -> config key)
CONFIG_FLAGS = {"task": "task", "model": "model", "window": "T", "data": "data",
                "test": "test", "cv": "cv", "quantise": "quantise",
                "contact_only": "contact_only", "profile": "profile", "seed": "seed",
                "no_session_copies": "sessions"}


def train_config(args) -> TrainConfig | dict:
    """The run's one config, built once from the flags, or from ``--config FILE`` (a
    model's train.toml) and the run's own flags; ``args`` is not changed. A shipped
    model's train.toml (its ``module`` one of :data:`REBUILDERS`) is returned as its
    dict, to be replayed by the module that made it. ``--config`` goes alone: a
    training flag beside it is an error naming the flag (only --out, --force, --json
    and --no-identity-check go with it)."""
    run = {"identity": not getattr(args, "no_identity_check", False), "measure": True}
    if not getattr(args, "config", None):
        if not args.task or not args.data:
            raise UserError("host train needs --task and --data (or --config FILE, a "
                            "model's train.toml)")
        return TrainConfig(task=args.task, model=args.model,
                           T=args.window or DEFAULT_WINDOW[args.task], data=args.data,
                           test=args.test or (), cv=args.cv, quantise=bool(args.quantise),
                           contact_only=bool(args.contact_only),
                           profile=args.profile or "roboskin",
                           seed=0 if args.seed is None else args.seed,
                           **({"sessions": False} if getattr(args, "no_session_copies", False)
                              else {}), **run)
    given = [f"--{k.replace('_', '-')}" for k in CONFIG_FLAGS
             if getattr(args, k) not in (None, False)]
    if given:
        raise UserError(f"--config {args.config} replays a config; it takes no "
                        f"{', '.join(given)} (edit a copy of the file instead)")
    try:
        doc = read_train_toml(args.config)
    except ConfigError as exc:
        raise UserError(f"--config: {exc}") from None
    if doc.get("module") in REBUILDERS:       # a shipped model's train.toml
        return doc
    return TrainConfig.from_replay(doc, args.config, **run)


#: the ``module`` of a shipped model's train.toml -> what replays it
REBUILDERS = {"host.bench.shipped": "_rebuild_shipped",
              "host.localiser.train": "_rebuild_localiser"}


def _rebuild(args, doc: dict) -> None:
    """Replay a shipped model's train.toml ``doc`` (written by the module it names, in
    its own settings) into ``--out``: the same training its ``command`` runs."""
    import shutil
    import tempfile
    out = Path(args.out)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix=".replay-", dir=out) as tmp:
        folder = globals()[REBUILDERS[doc["module"]]](doc, Path(tmp), args)
        for f in sorted(folder.iterdir()):
            shutil.move(str(f), str(out / f.name))
    res = {"config": str(args.config), "module": doc["module"], "name": doc.get("name"),
           "out": str(out), "files": sorted(f.name for f in out.iterdir()
                                            if not f.name.startswith(".")),
           "seconds": round(time.perf_counter() - t0, 1)}
    emit(args, res, f"{args.config}: replayed {doc['module']} into {out} "
                    f"({len(res['files'])} files, {res['seconds']} s)")


def _real_data(doc: dict, args) -> Path:
    given = doc.get("real_data")
    if given and not Path(given).is_absolute():
        given = str((Path(args.config).resolve().parent / given)
                    if (Path(args.config).resolve().parent / given).is_dir() else given)
    return real_data_dir(given)


def _rebuild_shipped(doc: dict, tmp: Path, args) -> Path:
    from host.bench.shipped import DEFAULTS, build_model, build_real_texture
    name = doc.get("name")
    if name not in DEFAULTS:
        raise UserError(f"--config {args.config}: name must be one of {sorted(DEFAULTS)}, "
                        f"got {name!r}")
    seed = int(doc.get("seed", 0))
    try:
        if doc.get("real_data") is not None:
            build_real_texture(tmp, tmp / "work", _real_data(doc, args), seed,
                               progress=not args.json)
        else:
            build_model(name, tmp, tmp / "work", seed=seed, trials=doc.get("trials_per_kind"),
                        progress=not args.json)
    except TrainError as exc:
        raise UserError(f"--config {args.config}: {exc}") from None
    return tmp / name


def _rebuild_localiser(doc: dict, tmp: Path, args) -> Path:
    from host.localiser.train import train_localiser
    keys = {"profile": "profile", "seed": "seed", "alpha": "alpha", "size": "size",
            "crop_factor": "crop_factor", "sim_scenes": "n_sim_scenes",
            "max_depth_mm": "max_depth_mm", "real_weight": "real_weight",
            "real_clips": "real_clips"}
    kw = {v: doc[k] for k, v in keys.items() if k in doc}
    if "real_clips" in kw:
        kw["real_clips"] = tuple(kw["real_clips"])
    # its real clips are named under the real recordings folder
    real = _real_data(doc, args) if doc.get("real_clips") else None
    try:
        train_localiser(tmp / "model", real_data=real, progress=not args.json, **kw)
    except ValueError as exc:
        raise UserError(f"--config {args.config}: {exc}") from None
    return tmp / "model"


def cmd_train(args):
    cfg = train_config(args)
    fd, created = _lock_out(args)
    try:
        if isinstance(cfg, dict):
            _rebuild(args, cfg)
        else:
            _train(args, cfg)
    except BaseException:
        out = Path(args.out)
        if created and out.is_dir() and not any(out.iterdir()):
            out.rmdir()                 # nothing written: leave no empty folder behind
        raise
    finally:
        os.close(fd)
    return 0


def _train(args, cfg: TrainConfig) -> None:
    load = lambda specs: _load_windows(args, specs, cfg.task, cfg.window,  # noqa: E731
                                       cfg.profile, cfg.contact_only)
    ws = load(cfg.data)
    ws_test = load(cfg.test) if cfg.test else None
    if cfg.task == "pressure":              # the leg would refuse such a model
        _check_pins(cfg, ((ws, "--data"), (ws_test, "--test")))
    recs = recordings_of(cfg.data)
    made = {"config": cfg.replay(),
            "trained_on": {"data": data_source(recs), "recordings": recs,
                           "test_recordings": recordings_of(cfg.test) if cfg.test else []}}
    res = _jsonable(train(cfg, ws, ws_test, args.out, not args.json, made))
    # README.md and train.toml; the run timed the model and wrote its manifest once
    write_model_docs(args.out, measure=False)
    _log_identity("host train", res.get("identity_check"), args.json)
    emit(args, res, f"wrote {args.out} ({cfg.task} {cfg.model}, T={cfg.window}): "
                    f"{figure_text(res)}")


def figure_text(res: dict) -> str:
    """The figures host train prints: the held-out one with its interval and what was
    held out (whole recordings, or a split inside one recording: optimistic), the
    --cv one beside it, and the int8 agreement."""
    metrics = res.get("metrics") or {}
    m = metrics.get("test") or {}
    parts = [", ".join(f"held-out {k} {m[k]:.4g}" + _interval(m, k)
                       for k in ("accuracy", "macro_f1", "mae")
                       if isinstance(m.get(k), (int, float)))]
    held = m.get("held_out") or {}
    name = lambda r: str(r).split(" sha256:")[0]  # noqa: E731
    if held.get("whole"):
        parts.append("held-out recordings: " + ", ".join(
            f"{name(r)} ({n} windows)" for r, n in sorted(held["whole"].items())))
    if held.get("inside"):
        parts.append("split inside one recording (optimistic: the same session): " +
                     ", ".join(f"{name(r)} ({n} windows)"
                               for r, n in sorted(held["inside"].items())))
    if held.get("given"):
        parts.append(f"given test data ({held['given']} windows)")
    cv = metrics.get("cv") or {}
    cv_text = ", ".join(f"{k} {cv[k]:.4g}" + _interval(cv, k)
                        for k in ("accuracy", "macro_f1", "mae")
                        if isinstance(cv.get(k), (int, float)))
    if cv_text:
        parts.append(f"grouped {cv.get('folds')}-fold CV (--cv, on the training windows): "
                     f"{cv_text}")
    int8 = res.get("int8")
    if isinstance(int8, dict) and "agreement" in int8:
        parts.append(f"int8 agreement {int8['agreement']:.4f}")
    if not held:
        parts.append(f"held out: {res.get('holdout')}")
    return "; ".join(p for p in parts if p)


def _interval(m: dict, key: str) -> str:
    """' [lo, hi] (95 %), n=N windows' for a metric that has its interval."""
    ci = m.get(f"{key}_ci95")
    if not (isinstance(ci, list) and len(ci) == 2):
        return ""
    n = m.get("n_windows", m.get("n"))
    return f" [{ci[0]:.4g}, {ci[1]:.4g}] (95 %)" + (f", n={n} windows" if n else "")


def cmd_eval(args):
    spec, mpath = read_spec(args.model_dir)
    profile, _ = models_profile({mpath: spec}, args.profile)
    ws = _load_windows(args, args.data, spec.kind, spec.T, profile, args.contact_only)
    res = evaluate_model(args.model_dir, ws, variant=args.variant)
    if args.identity:
        res["identity_check"] = _identity(spec, ws, profile)
    _log_identity("host eval", res.get("identity_check"), args.json)
    emit(args, res, eval_summary(res))


def _check_pins(cfg, sets) -> None:
    """Pressure windows the pipeline made with the profile must have its pin count
    (a model off it is refused by the leg). A vector set given as ``.npz`` was made
    elsewhere (another rig's markers, such as the hard plate's 146): no profile made it,
    so there is nothing to hold it to."""
    from host.learn.pressure import check_pin_count
    for ws, where in sets:
        trials = (ws.source.get("trials") or []) if ws is not None else []
        if ws is None or (trials and all(t.get("kind") == "npz" for t in trials)):
            continue
        check_pin_count(ws, cfg.profile, where)


def _log_identity(cmd: str, check: dict | None, quiet: bool) -> None:
    """The recording-identity check's verdict lines (INFO) and, when it flagged, its
    one-line warning (WARNING) on stderr; nothing with --json, whose output holds it."""
    from host.learn.identity import verdict_lines, warning_line
    if not check or quiet:
        return
    for line in verdict_lines(check):
        _log.info("%s: identity check: %s", cmd, line)
    warn = warning_line(check)
    if warn:
        _log.warning("%s: warning: %s", cmd, warn)


def _identity(spec, ws, profile: str) -> dict:
    """host eval --identity: the recording-identity check (host.learn.identity) of
    the model's kind on the evaluation windows."""
    from host.learn.estimators import hyperparameters
    from host.learn.identity import identity_check
    from host.learn.tasks import TASK_HIDDEN
    from host.learn.train import fnn_temporal_spec
    model = spec.model
    if model not in ("fnn", "grid-fnn", "ridge"):
        return {"skipped": f"model {model}: host eval --identity checks fnn, grid-fnn or "
                           f"ridge models", "flagged": False, "warning": None}
    uses_imu = bool(spec.uses_imu) and ws.imu is not None
    tspec = (fnn_temporal_spec(spec.kind, ws, ws.window, uses_imu, profile)
             if model == "fnn" and ws.window >= 2 else None)
    hp = hyperparameters(model, TASK_HIDDEN.get(spec.kind) if model != "ridge" else None,
                         None, None, tspec)
    return identity_check(ws, spec.kind, model, hp, uses_imu, 0)


def _spec_hint(spec: str) -> str:
    """A hint when the folder holding the authors' clips is given as a data spec."""
    if (Path(spec) / "roboskin").is_dir() and not (Path(spec) / "dataset.json").is_file():
        return (f"; for the authors' clips write their specs first: python -m "
                f"host.bench.specs --real-data {spec} --out out/specs, then pass "
                f"--data out/specs/lego-vs-smooth.csv --data out/specs/concrete-vs-smooth.csv")
    return ""


def cmd_report(args):
    specs = args.data or []
    if not specs:
        _log.info("host report: no --data; simulated sections only")
    if args.jobs == 0 or args.jobs < -1:
        raise UserError(f"--jobs: a number of workers >= 1 (or -1 for all cores), got "
                        f"{args.jobs}")
    windows, seeds = args.windows, args.seeds
    sim_windows, sim_seeds = args.sim_windows, args.sim_seeds
    text = lambda xs: ",".join(map(str, xs))  # noqa: E731
    cmd = (f"host report --out {args.out} --work {args.work}"
           + "".join(f" --data {d}" for d in specs)
           + (f" --profile {args.profile}" if args.profile != "roboskin" else "")
           + f" --windows {text(windows)} --seeds {text(seeds)} --sim-windows "
           f"{text(sim_windows)} --sim-seeds {text(sim_seeds)} --jobs {args.jobs}"
           + (" --quick" if args.quick else "") + (" --cnn" if args.cnn else "")
           + (" --real-only" if args.real_only else ""))
    if args.real_only and not specs:
        raise UserError("--real-only needs real data: pass --data SPEC (a CSV manifest or a "
                        "dataset folder)")
    try:
        out = build_report(args.out, args.work, specs, quick=args.quick,
                           progress=not args.json, command=cmd, jobs=args.jobs,
                           real_windows=windows, seeds=seeds, sim_windows=sim_windows,
                           sim_seeds=sim_seeds, cnn=args.cnn,
                           tasks=() if args.real_only else TASK_KINDS, profile=args.profile,
                           real_kinds=args.kinds)
    except DataError as exc:
        raise UserError(f"{exc}{''.join(_spec_hint(d) for d in specs[:1])}") from None
    emit(args, {"out": str(out)}, f"wrote {out}")


def register(sub) -> None:
    """The sub-commands train, eval and report."""
    s = sub.add_parser("train", help="train a surface/texture/slip/pressure model")
    s.add_argument("--config", metavar="FILE",
                   help="replay a model's train.toml (the config that made it); given alone "
                        "(with --out, --force, --json only)")
    s.add_argument("--task", choices=list(TASKS),
                   help="required unless --config")
    s.add_argument("--model", choices=list(MODELS),
                   help="model kind (default per task: " +
                   ", ".join(f"{t} {m}" for t, m in DEFAULT_MODEL.items()) + ")")
    s.add_argument("--window", type=whole(1, MAX_T),
                   help="T, frames per window (default per task: " +
                   ", ".join(f"{t} {w}" for t, w in DEFAULT_WINDOW.items()) + ")")
    s.add_argument("--data", action="append",
                   help="CSV manifest, dataset folder or .npz (repeatable; required unless "
                        "--config)")
    s.add_argument("--test", action="append",
                   help="held-out data spec (repeatable); default: a split of --data that "
                        "keeps every class (whole trials, else the end of each trial)")
    s.add_argument("--cv", type=whole(2, 100), help="also report grouped K-fold CV metrics")
    s.add_argument("--no-identity-check", action="store_true",
                   help="skip the recording-identity check (can the model kind tell the "
                        "recordings of one class apart? host.learn.identity), for speed")
    s.add_argument("--no-session-copies", action="store_true",
                   help="fit no recording-session copies of the training windows (texture "
                        "fits two by default: exposure, layout offset, lost pins; "
                        "host.learn.sessions), for speed")
    s.add_argument("--quantise", action="store_true", help="also write an int8 model")
    s.add_argument("--contact-only", action="store_true",
                   help="drop windows without contact instead of labelling them no-touch")
    s.add_argument("--profile", help="sensor profile (name or .toml; default roboskin): "
                                      "every feature is computed with it and the model "
                                      "carries it")
    s.add_argument("--seed", type=SEED)
    s.add_argument("--out", required=True, help="model folder to write (new or empty)")
    s.add_argument("--force", action="store_true",
                   help="write into a folder that is not empty, replacing the model in it")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_train)

    s = sub.add_parser("eval", help="evaluate a model folder on data")
    s.add_argument("model_dir")
    s.add_argument("--data", action="append", required=True)
    s.add_argument("--variant", choices=["float", "int8"])
    s.add_argument("--contact-only", action="store_true")
    s.add_argument("--identity", action="store_true",
                   help="also run the recording-identity check on the data: can the "
                        "model's kind tell apart the recordings of one class?")
    s.add_argument("--profile", help="default: the model's own; another is an error")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_eval)

    s = sub.add_parser("report", help="what accuracy costs in time: tables + figures")
    s.add_argument("--out", default="docs/accuracy-vs-time.md")
    s.add_argument("--work", default="out/report",
                   help="simulated data, models and finished cells, reused by a later run "
                        "on the same windows (remove it after changing the training code)")
    s.add_argument("--data", action="append", metavar="SPEC",
                   help="real data: a CSV manifest (path,label[,...]) or a dataset folder, "
                        "one report section each (repeatable); none: simulated only")
    s.add_argument("--profile", default="roboskin",
                   help="sensor profile of the real data (name or .toml; default roboskin)")
    s.add_argument("--kinds", type=lambda v: [k for k in v.split(",") if k],
                   help="model kinds of the real sections, comma-separated (default: the "
                        "task's kinds)")
    s.add_argument("--windows", type=whole_list(1, MAX_T), default="1-10",
                   help="window lengths T of the real sections (1,3,10 or 1-10)")
    s.add_argument("--seeds", type=whole_list(0, 2**32 - 1), default="0,1,2",
                   help="seeds of the real sections")
    s.add_argument("--sim-windows", type=whole_list(1, MAX_T), default="1,3,10",
                   help="window lengths T of the simulated sections")
    s.add_argument("--sim-seeds", type=whole_list(0, 2**32 - 1), default="0,1",
                   help="seeds of the simulated sections")
    s.add_argument("--jobs", type=int, default=1,
                   help="parallel cells (joblib workers; -1: all cores); the times are "
                        "taken afterwards, one at a time")
    s.add_argument("--quick", action="store_true", help="fewer simulated trials")
    s.add_argument("--cnn", action="store_true", help="also sweep the CNN (PyTorch; slow)")
    s.add_argument("--real-only", action="store_true",
                   help="only the real sections and the fnn's regulariser comparison")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_report)
