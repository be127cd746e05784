"""Texture accuracy on proxies for a recording session the model never saw.

    host bench texture-robustness --data ../shared/data [--json] [--work DIR]
    python -m host.bench.texture_robust --data ../shared/data [--json] [--profile TOML]

There is one real recording per surface (``roboskin/concrete.avi``, ``smooth.avi``,
``lego_train.avi``), so a new session is stood in for by changing the held-out
frames the way a new session changes them. The models are trained as ``host
train --task texture`` trains them by default (:func:`host.learn.train.train_model`:
the default kind, T and layer sizes), on the first 70 % of each recording, contact
windows only; each proxy is scored on contact windows of the rest of the recording
after a gap of T frames:

``later``       the held-out frames as they are (proxy (a): later frames after a gap);
``rate-3of5``   only 3 of every 5 frames kept (200 fps replayed as 120 fps; concrete,
                taken at 120 fps, becomes 72 fps);
``rate-drops``  3 of 5 kept, then 10 % of the rest dropped at random (seeded);
``gain-0.8``, ``gain-1.25``, ``gamma-0.7``, ``gamma-1.4``, ``offset+25``: the
                exposure of every frame changed before the marker pipeline (the rest
                frame too, as in a session with another exposure);
``gain-0.6``, ``blur-1.5``, ``noise-6``, ``layout-rot4``: stand-ins that ``host
                train``'s session copies (:mod:`host.learn.sessions`) do not draw from:
                an exposure beyond their gain range, a Gaussian blur (sigma 1.5 px, a
                dome out of focus), Gaussian noise (sd 6 grey levels, seeded), and the
                pin layout rotated 4 degrees and moved 6 px before the reference pins
                are assigned to it (they draw up to 1 degree and 3 px). The session
                copies' exposure range covers gain 0.8-1.25, so ``gain-0.8`` and
                ``gain-1.25`` are inside what a model trained with them has seen;
                gamma 0.7 / 1.4 and offset +25 lie just outside theirs.

Three tasks, as the figures of issue 23 name them: Lego vs smooth, concrete vs
smooth, and all three (whose per-recording recall is the share of contact frames
right the runtime gives on the held-out frames). The identity check trains the same
model kind to tell the first half of one recording from its second half (70 % of
each half trained, the rest tested after a gap): far above 0.5 means the features
can learn which part of which session they are watching.

``--model DIR`` scores a model folder (e.g. the shipped ``models/texture``) on the
all-three proxies instead of training one: its per-recording recall on the held-out
contact windows is the runtime's share of contact frames right (the runtime feeds
the model the same encoder's windows).

Every accuracy has a 95 % interval from a block bootstrap (blocks of T consecutive
windows, which overlap and are not independent) and the number of windows.
Extracted clip features are cached under ``--work``.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from device.config import ConfigError
from device.profile import load_pipeline_profile
from host.data.windows import DataError, TrialPart, WindowSet, stack_parts, window_ends
from host.learn.rates import kept_frames
from host.learn.sessions import exposure
from host.learn.tasks import DEFAULT_WINDOW, TrainError

__all__ = ["Variant", "VARIANTS", "CLIPS", "TASKS", "keep_indices",
           "clip_variant", "clip_windows", "block_bootstrap", "model_trainer", "robustness",
           "main"]

#: the real recordings: file under roboskin/ -> texture label
CLIPS = {"concrete.avi": "concrete", "smooth.avi": "smooth", "lego_train.avi": "lego"}
#: the share of each recording (its start) trained on
TRAIN_FRAC = 0.7
#: name -> the recordings (labels) the task classifies
TASKS = {"lego-vs-smooth": ("lego", "smooth"), "concrete-vs-smooth": ("concrete", "smooth"),
         "all-three": ("concrete", "lego", "smooth")}


@dataclass(frozen=True)
class Variant:
    """How a proxy session differs from the recording: which frames the camera
    delivers (``keep``: ``all``, ``3of5``, or ``3of5+dropP`` with P percent dropped
    at random), the exposure (``gain``, ``offset`` in grey levels, ``gamma``), a
    Gaussian ``blur`` (sigma px) and ``noise`` (sd, grey levels), and the pin layout
    rotated ``layout_deg`` about its centre and moved ``layout_px`` (along x)."""

    name: str
    keep: str = "all"
    gain: float = 1.0
    offset: float = 0.0
    gamma: float = 1.0
    blur: float = 0.0
    noise: float = 0.0
    layout_deg: float = 0.0
    layout_px: float = 0.0

    @property
    def exposed(self) -> bool:
        return ((self.gain, self.offset, self.gamma) != (1.0, 0.0, 1.0)
                or self.blur > 0 or self.noise > 0)


VARIANTS = (Variant("later"), Variant("rate-3of5", "3of5"), Variant("rate-drops", "3of5+drop10"),
            Variant("gain-0.8", gain=0.8), Variant("gain-1.25", gain=1.25),
            Variant("gamma-0.7", gamma=0.7), Variant("gamma-1.4", gamma=1.4),
            Variant("offset+25", offset=25.0), Variant("gain-0.6", gain=0.6),
            Variant("blur-1.5", blur=1.5), Variant("noise-6", noise=6.0),
            Variant("layout-rot4", layout_deg=4.0, layout_px=6.0))


def keep_indices(n: int, keep: str, seed: int = 0) -> np.ndarray:
    """The frame indices (of ``n``) a camera of rule ``keep`` delivers
    (:func:`host.learn.rates.kept_frames`: ``all``, ``3of5``, ``3of5+dropP``), with
    the rest frame (frame 0) always kept, since a replayed clip starts from it."""
    try:
        idx = kept_frames(n, keep, seed)
    except TrainError as exc:
        raise DataError(str(exc)) from None
    if int(n) > 0 and (len(idx) == 0 or idx[0] != 0):
        idx = np.concatenate((np.zeros(1, np.int64), idx))
    return idx


def clip_variant(path, variant: Variant, profile: str = "roboskin", seed: int = 0,
                 cache_dir=None):
    """(features, frame index of each) of the recording ``path`` as ``variant``
    delivers it: the kept frames, exposed, through the Pi's frame encoder
    (:func:`host.data.extract.extract_features`), from the first kept frame. Cached
    as an .npz in ``cache_dir`` when given."""
    from device.pi.sources.camera import open_camera
    from host.data.extract import ClipFeatures, extract_features

    path = Path(path)
    key = (f"{path.stem}-{variant.keep}-g{variant.gain}-o{variant.offset}-y{variant.gamma}"
           + (f"-b{variant.blur}-n{variant.noise}-l{variant.layout_deg}_{variant.layout_px}"
              if (variant.blur, variant.noise, variant.layout_deg, variant.layout_px)
              != (0.0, 0.0, 0.0, 0.0) else "")
           + f"-s{seed}-{Path(profile).stem}.npz")
    hit = Path(cache_dir) / key if cache_dir else None
    if hit is not None and hit.is_file():
        z = np.load(hit)
        return ClipFeatures(vectors=z["vectors"], lost=z["lost"], grids=z["grids"],
                            frames=None, contact=z["contact"], ready=z["ready"],
                            faults=z["faults"], fps=None), z["orig"]
    with open_camera(f"file://{path.resolve()}") as cam:
        n = cam.n_frames
        keep = keep_indices(n, variant.keep, seed)
        wanted = np.zeros(n, bool)
        wanted[keep] = True

        rng = np.random.default_rng(seed)

        def frames():
            for fr in cam:
                if fr.index < n and wanted[fr.index]:
                    yield _changed(fr.image, variant, rng) if variant.exposed else fr.image

        clip = extract_features(frames(), profile, None, progress=False,
                                mapper=_variant_mapper(variant, profile))
    orig = keep[:clip.n_frames]
    if hit is not None:
        hit.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(hit, vectors=clip.vectors, lost=clip.lost, grids=clip.grids,
                            contact=clip.contact, ready=clip.ready, faults=clip.faults,
                            orig=orig)
    return clip, orig


def _changed(image: np.ndarray, v: Variant, rng) -> np.ndarray:
    """A frame as variant ``v`` changes it: exposure, then blur, then noise."""
    import cv2
    out = exposure(image, v.gain, v.gamma, v.offset)
    if v.blur > 0:
        out = cv2.GaussianBlur(out, (0, 0), v.blur)
    if v.noise > 0:
        out = np.clip(out + rng.normal(0.0, v.noise, out.shape), 0, 255).astype(np.uint8)
    return out


def _variant_mapper(v: Variant, profile: str):
    """The layout mapper of a variant that moves the pin layout, else None."""
    if (v.layout_deg, v.layout_px) == (0.0, 0.0):
        return None
    from device.pi.vision.layout import LayoutMapper
    from host.data.extract import layout_for_profile
    from host.learn.sessions import SessionDraw, perturbed_layout
    lay = perturbed_layout(layout_for_profile(profile),
                           SessionDraw(dx=v.layout_px, rot_deg=v.layout_deg))
    return LayoutMapper(lay, load_pipeline_profile(profile).match_gate_px)


def clip_windows(clip, orig: np.ndarray, label: str, T: int, first: int, last: int,
                 key: str = "clip", file=None) -> WindowSet | None:
    """Contact windows of T delivered frames of ``clip`` whose frames all lie in the
    recording's frames ``first`` .. ``last - 1`` (``orig``: the recording's index of
    each delivered frame), labelled ``label``; None when there are none. ``file``:
    the recording, named in the windows' trial so that training can read its frames
    again (:mod:`host.learn.sessions`)."""
    ends, _ = window_ends(clip.ready, 0, clip.n_frames, T, 1)
    ends = ends[(orig[ends - T + 1] >= first) & (orig[ends] < last) & clip.contact[ends]]
    if not len(ends):
        return None
    part = TrialPart(clip, ends, np.full(len(ends), label, object), None, clip.contact[ends],
                     None, key, 0, clip.n_frames)
    arrays = stack_parts([part], "texture", T, {key: {}})
    arrays["t_index"] = orig[ends]             # the recording's frame, not the delivered one
    trial = ({"path": key, "group": 0} if file is None else
             {"path": str(Path(file).resolve()), "kind": "clip", "span_start": 0, "group": 0})
    return WindowSet(task="texture", window=T, classes=[], source={"trials": [trial],
                                                                  "contact_only": True},
                     **arrays)


def block_bootstrap(right: np.ndarray, block: int, n_boot: int = 1000,
                    seed: int = 0) -> tuple[float, float]:
    """The 95 % interval of the mean of ``right`` (0/1 per window, in time order)
    from a circular block bootstrap: blocks of ``block`` consecutive windows (at most
    a quarter of the windows, so a short set still has several blocks), wrapped at
    the end, drawn until there are as many windows as in ``right``."""
    r = np.asarray(right, np.float64).reshape(-1)
    n = len(r)
    if n == 0:
        return (float("nan"), float("nan"))
    if int(block) < 1:
        raise DataError(f"block must be >= 1 window, got block={block!r}")
    b = max(1, min(int(block), n // 4))
    k = -(-n // b)
    rng = np.random.default_rng(seed)
    starts = rng.integers(0, n, size=(n_boot, k))
    idx = (starts[:, :, None] + np.arange(b)[None, None, :]) % n
    means = r[idx.reshape(n_boot, -1)[:, :n]].mean(axis=1)
    lo, hi = np.quantile(means, [0.025, 0.975])
    return float(lo), float(hi)


def score(right: np.ndarray, T: int) -> dict:
    """Accuracy, its block-bootstrap 95 % interval and the window count."""
    right = np.asarray(right, bool)
    if not len(right):
        return {"accuracy": None, "ci95": None, "n": 0}
    lo, hi = block_bootstrap(right, T)
    return {"accuracy": round(float(right.mean()), 4), "ci95": [round(lo, 4), round(hi, 4)],
            "n": int(len(right))}


def _train(ws_train: WindowSet, ws_test: WindowSet, seed: int, trainer, fit=None):
    """A predict(ws) -> class ids and the classes, from ``trainer`` (default: the
    default texture model of ``host train``, float, written to a temporary folder;
    ``fit``: its ``rates`` (frame-rate copies) and ``sessions`` (session copies),
    each None = host train's, and the ``profile``)."""
    if trainer is not None:
        return trainer(ws_train, ws_test, seed)
    from host.learn.inputs import model_inputs
    from host.learn.onnx_io import FLOAT_NAME, run_onnx, session
    from host.learn.tasks import DEFAULT_MODEL
    from host.learn.train import train_model

    with tempfile.TemporaryDirectory(prefix="tacfoot-robust-") as tmp:
        res = train_model("texture", DEFAULT_MODEL["texture"], ws_train, ws_test,
                          quantise=False, seed=seed, out_dir=tmp, progress=False,
                          **(fit or {}))
        sess = session((Path(tmp) / FLOAT_NAME).read_bytes())

    def predict(ws):
        return run_onnx(sess, model_inputs(ws, "vectors", False)).argmax(axis=1)
    return predict, res["classes"]


def model_trainer(folder):
    """A trainer that trains nothing: the texture model in ``folder`` (e.g. the shipped
    ``models/texture``, its default variant) classifies the windows. Returns
    (trainer, T of the model)."""
    from device.pi.models.manifest import read_spec
    from host.learn.cut import graph_inputs
    from host.learn.inputs import model_inputs
    from host.learn.onnx_io import run_onnx, session

    folder = Path(folder)
    try:
        spec, _ = read_spec(folder)
    except (OSError, ValueError) as exc:
        raise DataError(f"--model {folder}: {exc}") from None
    if spec.input_layout != "vectors" or spec.uses_imu:
        raise DataError(f"--model {folder}: a texture model reading vectors without the IMU "
                        f"is needed, got input_layout={spec.input_layout!r} "
                        f"uses_imu={spec.uses_imu!r}")
    sess = session((folder / spec.onnx).read_bytes())
    classes = [str(c) for c in spec.classes]

    def trainer(ws_train, ws_test, seed):
        def predict(ws):
            return run_onnx(sess, graph_inputs(spec, model_inputs(ws, "vectors", False),
                                               folder)).argmax(axis=1)
        return predict, classes
    return trainer, spec.T


def _scored(predict, classes, sets: dict, T: int) -> dict:
    """The score over all the recordings' windows (with its interval: blocks of T
    windows, each recording's in time order) and ``per_recording``."""
    per, right = {}, [np.zeros(0, bool)]
    for label, ws in sets.items():
        want = classes.index(label) if label in classes else -1
        r = np.zeros(0, bool) if ws is None else predict(ws) == want
        per[label] = score(r, T)
        right.append(r)
    return {**score(np.concatenate(right), T), "per_recording": per}


def robustness(data, work=None, T: int | None = None, seed: int = 0, variants=VARIANTS,
               tasks=tuple(TASKS), identity: bool = True, trainer=None,
               profile: str = "roboskin", progress=None, rates=None, sessions=None) -> dict:
    """The proxy figures (module doc) as a JSON-able dict: for each task and proxy,
    the accuracy over its windows and per recording (accuracy, ci95, n); and the
    identity check per recording. ``trainer(ws_train, ws_test, seed) -> (predict,
    classes)`` replaces the default model (for comparisons); ``rates`` the default
    model's frame-rate copies (:mod:`host.learn.rates`; None = host train's, () =
    none, as before they were added) and ``sessions`` its session copies
    (:mod:`host.learn.sessions`; None = host train's, False = none)."""
    T = DEFAULT_WINDOW["texture"] if T is None else int(T)
    load_pipeline_profile(profile)     # a profile that does not load fails before any clip
    root = Path(data).expanduser() / "roboskin"
    say = progress or (lambda m: None)
    for t in tasks:
        if t not in TASKS:
            raise DataError(f"tasks: {t!r} is not one of {list(TASKS)}")
    needed = {lab for t in tasks for lab in TASKS[t]} | (set(CLIPS.values()) if identity
                                                         else set())
    paths = {lab: root / clip for clip, lab in CLIPS.items() if lab in needed}
    for p in paths.values():
        if not p.is_file():
            raise DataError(f"no such recording: {p}")
    cache = None if work is None else Path(work)
    base = {lab: clip_variant(p, Variant("later"), profile, seed, cache) for lab, p in
            paths.items()}
    n_frames = {lab: int(orig[-1]) + 1 for lab, (_, orig) in base.items()}
    cut = {lab: int(TRAIN_FRAC * n) for lab, n in n_frames.items()}

    fit = {"rates": rates, "sessions": sessions, "profile": profile}

    def train_set(lab):
        clip, orig = base[lab]
        return clip_windows(clip, orig, lab, T, 0, cut[lab], lab, paths[lab])

    def test_set(lab, variant):
        clip, orig = (base[lab] if variant.name == "later" else
                      clip_variant(paths[lab], variant, profile, seed, cache))
        return clip_windows(clip, orig, lab, T, cut[lab] + T, n_frames[lab], lab)

    tests = {}
    for v in variants:
        say(f"proxy {v.name}")
        tests[v.name] = {lab: test_set(lab, v) for lab in paths}
    out = {"T": T, "train_frac": TRAIN_FRAC, "seed": seed, "tasks": {}, "identity": {}}
    for task in tasks:
        labs = TASKS[task]
        say(f"training {task}")
        tr = WindowSet.concat([train_set(lab) for lab in labs])
        te = WindowSet.concat([tests["later"][lab] for lab in labs
                               if tests["later"][lab] is not None])
        predict, classes = _train(tr, te, seed, trainer, fit)
        res = {"train_windows": len(tr), "proxies": {}}
        for v in variants:
            res["proxies"][v.name] = _scored(predict, classes,
                                             {lab: tests[v.name][lab] for lab in labs}, T)
        out["tasks"][task] = res
    if identity:
        for lab in paths:
            say(f"identity {lab}")
            out["identity"][lab] = identity_check(base[lab], n_frames[lab], T, seed, trainer,
                                                  dict(fit, file=paths[lab]))
    return out


def identity_check(clip_orig, n: int, T: int, seed: int = 0, trainer=None,
                   fit=None) -> dict:
    """Can the model tell the first half of a recording from its second half? Each
    half is cut into chunks of ``4 T`` frames; the windows inside even chunks are
    trained on, and those of odd chunks at least T frames from either chunk end are
    tested (so no test window shares a frame with, or touches, a training one).
    ``fit``: as :func:`_train` takes it, with ``file`` the recording. The
    accuracy over the test windows (0.5 is chance; near 1 means the windows carry
    what tells one part of a session from another)."""
    clip, orig = clip_orig
    fit = dict(fit or {})
    file = fit.pop("file", None)
    half, chunk = n // 2, 4 * T
    tr, te = [], []
    for lab, (a, b) in {"first-half": (0, half), "second-half": (half, n)}.items():
        for i, c0 in enumerate(range(a, b, chunk)):
            c1 = min(c0 + chunk, b)
            got = (clip_windows(clip, orig, lab, T, c0, c1, lab, file) if i % 2 == 0 else
                   clip_windows(clip, orig, lab, T, c0 + T, c1 - T, lab))
            if got is not None:
                (tr if i % 2 == 0 else te).append(got)
    labs = {str(x) for s in tr for x in s.labels}
    if len(labs) < 2 or {str(x) for s in te for x in s.labels} != labs:
        return {"accuracy": None, "ci95": None, "n": 0,
                "note": "a half has no contact windows to train or test on"}
    ws_te = WindowSet.concat(te)
    predict, classes = _train(WindowSet.concat(tr), ws_te, seed, trainer, fit)
    want = np.array([classes.index(str(x)) for x in ws_te.labels])
    return score(predict(ws_te) == want, T)


def format_robustness(res: dict) -> str:
    lines = [f"texture on proxies for a new session (T = {res['T']}, trained on the first "
             f"{res['train_frac']:.0%} of each recording, contact windows; acc [95 % CI] n)"]
    for task, r in res["tasks"].items():
        lines.append(f"{task} (the model {res['model']}, not trained here)" if res.get("model")
                     else f"{task} ({r['train_windows']} training windows)")
        for name, p in r["proxies"].items():
            cells = "  ".join(
                f"{lab} {v['accuracy'] if v['n'] else '-'} "
                f"[{v['ci95'][0] if v['n'] else '-'}, {v['ci95'][1] if v['n'] else '-'}] "
                f"n={v['n']}" for lab, v in p["per_recording"].items())
            ci = p.get("ci95") or ["-", "-"]
            lines.append(f"  {name:11s} all {p['accuracy']} [{ci[0]}, {ci[1]}] n={p['n']}  "
                         f"{cells}")
    if res.get("identity"):
        lines.append("identity check: first vs second half of one recording (0.5 = chance)")
        for lab, r in res["identity"].items():
            ci = r.get("ci95") or ["-", "-"]
            lines.append(f"  {lab:9s} {r['accuracy']} [{ci[0]}, {ci[1]}] n={r['n']}")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m host.bench.texture_robust",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--data", required=True, help="folder holding roboskin/")
    p.add_argument("--work", default="out/texture-robust", help="cache of clip features")
    p.add_argument("--window", type=int, default=None, help="T (default: host train's)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--tasks", default=",".join(TASKS))
    p.add_argument("--no-identity", action="store_true")
    p.add_argument("--model", help="score this texture model folder (e.g. models/texture) "
                                   "on the all-three proxies instead of training")
    p.add_argument("--rates", default=None,
                   help="frame-rate copies the trained model fits, comma-separated "
                        "(e.g. 3of5,3of5+drop10); 'none' for none (default: host train's)")
    p.add_argument("--sessions", default=None, choices=("none", "default"),
                   help="recording-session copies the trained model fits "
                        "(host.learn.sessions): 'none' for none (default: host train's)")
    p.add_argument("--profile", default="roboskin",
                   help="the pipeline profile the frames go through: a built-in name or a "
                        "TOML path (e.g. one with [vision] contrast_ref, to compare the "
                        "exposure-scaled offset with the fixed one)")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    try:
        tasks = [t.strip() for t in args.tasks.split(",") if t.strip()]
        trainer, T = (None, args.window) if not args.model else model_trainer(args.model)
        if args.model:
            tasks = ["all-three"]
        rates = (None if args.rates is None else () if args.rates.strip() == "none" else
                 tuple(r.strip() for r in args.rates.split(",") if r.strip()))
        sessions = {None: None, "default": True, "none": False}[args.sessions]
        res = robustness(args.data, args.work, T, args.seed, tasks=tasks, rates=rates,
                         sessions=sessions,
                         identity=not args.no_identity and not args.model, trainer=trainer,
                         profile=args.profile,
                         progress=lambda m: print(f"texture-robustness: {m}", file=sys.stderr))
    except (DataError, TrainError, ConfigError) as exc:
        print(f"texture-robustness: error: {exc}", file=sys.stderr)
        return 2
    if args.model:
        res["model"] = str(args.model)
    print(json.dumps(res, indent=1) if args.json else format_robustness(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
