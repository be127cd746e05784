"""Train the fixed-count pin localiser (stage 6 of the marker pipeline).

A Ridge regression (alpha 150 by default, as in the seed paper) from the
downscaled binary dome image to the positions of all N pins of a sensor
profile (133 for ``roboskin``). The Pi runs it through
:class:`device.pi.models.localiser.Localiser`; this module makes the training data,
fits, checks and exports it as ONNX + JSON (``kind="localiser"``).

Training data
  * simulated frames with known true pins (:mod:`host.localiser.sim`);
  * optionally real frames, labelled automatically (:mod:`host.localiser.labels`);
    frames whose labels fail the checks are rejected and listed with the reason.

Augmentation (:func:`host.localiser.samples.augment_rows`): every frame is cut
several times around a perturbed dome, with its labels normalised by the same
dome.

Held-out checks (:mod:`host.localiser.evaluate`): simulated scenes with unseen
seeds (pressing deeper than the training scenes), and the last 20 % of each
real clip (never used for training), each also per displacement bin.

Export: the Ridge is written as a plain ONNX MatMul + Add graph
(:func:`host.localiser.fit.ridge_to_onnx`) through
:func:`host.learn.onnx_io.write_model`, with the localiser's manifest extras.

Limit: a linear map from the binary image cannot tell pins apart once they
have moved by more than about one pin pitch (~12 px on roboskin): there the
error grows to several px (see ``metrics.*.by_displacement``). The output is
still finite and plausible, and the fault flag stays clear.

Command line::

    python -m host.localiser --out models/localiser-roboskin \\
        --real-data ../shared/data [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from device.checks import finite_number, positive_number, whole_number
from device.pi.models.localiser import DEFAULT_CROP_FACTOR, KIND, effective_dome
from device.profile import has_sim_geometry
from host.learn.card import write_model_docs
from host.learn.onnx_io import json_default, write_model
from host.localiser.evaluate import error_stats, evaluate, evaluate_perturbed, pin_errors_px
from host.localiser.fit import DEFAULT_ALPHA, fit_ridge, onnx_vs_sklearn, ridge_to_onnx
from host.localiser.labels import REAL_CLIPS, REAL_HOLDOUT_FRAC, LabelChecks, real_samples
from host.localiser.samples import augment_rows, sensor_geometry, vision_params_for
from host.localiser.sim import sim_frames

__all__ = ["DEFAULT_SIZE", "TRAIN_MAX_DEPTH_MM", "TEST_MAX_DEPTH_MM", "train_localiser",
           "add_arguments", "run", "main"]

DEFAULT_SIZE = 32          # 32 x 32 inputs: 1024 x 266 weights, float16: 0.55 MB
#: the Pi checks the input's foreground share per cell of this grid (see Localiser)
FILL_GRID = 4
#: simulated training scenes press at most this deep by default. Deeper presses
#: drag the pins by more than a pitch (> 12 px), where a linear map from the image
#: can hardly tell which pin is which; training on many of them costs accuracy
#: on the real clips (real held-out median 0.37 / 0.40 / 0.48 px for 2 / 2.5 / 3
#: mm), training on none loses the large-shear frames (median error there 7.3 /
#: 3.9 / 3.7 px). 2.5 mm is the compromise.
TRAIN_MAX_DEPTH_MM = 2.5
#: held-out simulated scenes press up to this deep
TEST_MAX_DEPTH_MM = 3.0


def _check_args(size, alpha, crop_factor, n_aug) -> None:
    whole_number("size", size, 8, 128)
    finite_number("alpha", alpha, 0)
    finite_number("crop_factor", crop_factor, 0.3, 2.0)
    whole_number("n_aug", n_aug, 1)


def train_localiser(
    out_dir: Path | str, profile: str = "roboskin", real_data=None, seed: int = 0,
    alpha: float = DEFAULT_ALPHA, size: int = DEFAULT_SIZE, progress: bool = True,
    crop_factor: float = DEFAULT_CROP_FACTOR,
    # simulated frames and augmentation
    n_sim_scenes: int = 120, frames_per_scene: int = 30, n_test_scenes: int = 20,
    n_aug: int = 3, shift_px: float = 2.0, zoom: float = 0.02,
    max_depth_mm: float = TRAIN_MAX_DEPTH_MM,
    # real frames
    real_clips: Sequence[str] = REAL_CLIPS, real_stride: int = 1, real_weight: float = 2.0,
    checks: LabelChecks = LabelChecks(),
    weights: str = "auto",
) -> dict:
    """Train, check and export a localiser; returns the summary (and the estimator).

    ``profile``: a built-in profile or a profile TOML; one from ``host calibrate``
    has no simulator geometry, so it trains on real clips only (``n_sim_scenes=0``).
    ``real_data``: None (simulated frames only, or the clip files ``real_clips``
    of any sensor), a folder holding the roboskin clips named in ``real_clips``
    (``<dir>/roboskin/<clip>.avi`` or ``<dir>/<clip>.avi``), or a mapping clip
    name -> list of frames. Training scenes use seeds
    ``seed .. seed + n_sim_scenes - 1``; held-out scenes the seeds from
    ``seed + 100000`` on; the last 20 % of each real clip is held out.
    Real rows weigh ``real_weight`` times a simulated row in the fit (the
    simulator's pins are an ideal layout; the real ones are the target).
    Simulated training scenes press at most ``max_depth_mm`` deep, held-out
    ones up to 3 mm; the held-out metrics are also given per displacement bin.

    The result dict holds ``out_dir``, ``size_bytes``, ``train_s`` (and
    ``stage_s`` per stage), ``training`` (counts, the rejected real frames
    with clip, frame and reason), ``metrics`` (held-out pin errors, px) and
    ``estimator`` (the fitted scikit-learn Ridge; it is not written
    anywhere: the artefact is model.onnx + its manifest).
    """
    _check_args(size, alpha, crop_factor, n_aug)
    params = vision_params_for(profile)
    clip_files = real_data is None and real_clips is not REAL_CLIPS and bool(real_clips)
    if real_data is not None and not isinstance(real_data, Mapping) and not (
            Path(real_data).is_dir()):
        raise ValueError(f"real_data must be a folder with the roboskin clips or a mapping "
                         f"clip -> frames, got real_data={str(real_data)!r}")
    if n_sim_scenes and not has_sim_geometry(profile):
        raise ValueError(f"profile {str(profile)!r} has no simulator geometry, so there are "
                         f"no simulated frames to train on: use n_sim_scenes=0 "
                         f"(--sim-scenes 0) with real clips of the sensor")
    positive_number("real_weight", real_weight)
    t0 = time.perf_counter()
    stage_s: dict = {}
    n_pins = len(sensor_geometry(profile)[0])
    rng = np.random.default_rng(seed)

    sim_train = sim_frames(n_sim_scenes, frames_per_scene, seed, profile, params, progress,
                           max_depth_mm)
    # held out: unseen seeds, and deeper presses than in training (up to 3 mm)
    n_test_scenes = n_test_scenes if n_sim_scenes else 0
    sim_test = sim_frames(n_test_scenes, max(4, frames_per_scene // 2), seed + 100000, profile,
                          params, progress, TEST_MAX_DEPTH_MM)
    stage_s["simulate"] = round(time.perf_counter() - t0, 1)
    t1 = time.perf_counter()
    real = {"train": [], "test": [], "rejected": [], "labelled": {}, "fits": {}}
    if real_data is not None or clip_files:
        real = real_samples(real_data, profile, params, real_clips, REAL_HOLDOUT_FRAC, checks,
                            real_stride, progress)
    stage_s["label_real"] = round(time.perf_counter() - t1, 1)
    train = sim_train + real["train"]
    if not train:
        raise ValueError("no training frames: n_sim_scenes=0 and no accepted real frames")
    t1 = time.perf_counter()
    X, Y = augment_rows(train, size, crop_factor, n_aug, shift_px, zoom, rng, progress,
                        "augment")
    w = np.ones(len(X))
    w[len(sim_train) * n_aug:] = real_weight
    model = fit_ridge(X, Y, alpha, sample_weight=w)
    fit_pred = model.predict(X)
    stage_s["fit"] = round(time.perf_counter() - t1, 1)

    # the fallback layout and the plausibility limits the Pi checks at run time
    mean_layout = np.average(Y.astype(np.float64), axis=0, weights=w)
    dev = max(float(np.abs(fit_pred - mean_layout).max()), float(np.abs(Y - mean_layout).max()))
    max_dev_norm = 2.0 * dev
    fill = X.mean(1)
    fill_range = [0.5 * float(fill.min()), min(1.0, 1.5 * float(fill.max()))]
    grid = FILL_GRID if size % FILL_GRID == 0 else 0
    cells_range = [[0.0], [1.0]]
    if grid:
        c = X.reshape(len(X), grid, size // grid, grid, size // grid).mean(axis=(2, 4))
        c = c.reshape(len(X), -1).astype(np.float64)
        cells_range = [np.round(0.5 * c.min(0), 6).tolist(),
                       np.round(np.minimum(1.0, 1.5 * c.max(0) + 0.02), 6).tolist()]

    t1 = time.perf_counter()
    r_train = np.array([effective_dome(s.dome, crop_factor)[2] for s in train])
    metrics = {"train_fit": error_stats(pin_errors_px(fit_pred[::n_aug], Y[::n_aug], r_train))}
    if sim_test:
        metrics["sim_heldout"] = evaluate(model, sim_test, size, crop_factor, False)
        metrics["sim_heldout_perturbed_dome"] = evaluate_perturbed(
            model, sim_test, size, crop_factor, shift_px, zoom, seed + 7)
    if real["test"]:
        metrics["real_heldout_measured"] = evaluate(model, real["test"], size, crop_factor, True)
        metrics["real_heldout_all_labels"] = evaluate(model, real["test"], size, crop_factor,
                                                       False)
        metrics["real_heldout_perturbed_dome"] = evaluate_perturbed(
            model, real["test"], size, crop_factor, shift_px, zoom, seed + 11)

    onx = ridge_to_onnx(model, size * size, weights)
    onnx_diff = onnx_vs_sklearn(onx, model, X[:: max(1, len(X) // 256)])
    weights_dtype = "float16" if any(i.name == "W16" for i in onx.graph.initializer) else "float32"
    metrics["onnx_vs_sklearn_max_abs_norm"] = onnx_diff
    stage_s["evaluate_export"] = round(time.perf_counter() - t1, 1)
    training = {
        "sim_frames": len(sim_train), "sim_scenes": n_sim_scenes,
        "sim_max_depth_mm": max_depth_mm, "sim_test_max_depth_mm": TEST_MAX_DEPTH_MM,
        "sim_seeds": [seed, seed + n_sim_scenes - 1],
        "sim_test_frames": len(sim_test),
        "sim_test_seeds": [seed + 100000, seed + 100000 + n_test_scenes - 1],
        "real_frames": len(real["train"]), "real_test_frames": len(real["test"]),
        "real_weight": float(real_weight),
        "real_labelled": real["labelled"], "real_layout_fit": real["fits"],
        "real_holdout": f"last {REAL_HOLDOUT_FRAC:.0%} of each clip",
        "label_checks": {k: getattr(checks, k) for k in checks.__dataclass_fields__},
        "rows": int(len(X)),
        "augment": {"copies": n_aug, "shift_px_sigma": shift_px, "zoom_sigma": zoom},
        "rejected": real["rejected"],
    }
    train_s = round(time.perf_counter() - t0, 1)
    recs = [{"path": str(c), "sha256": _clip_sha256(real_data, c), "frames": v.get("frames")}
            for c, v in real["labelled"].items()]
    source = ("real+simulated" if recs and n_sim_scenes else "real" if recs
              else "simulated")
    extra = {
        "task": KIND, "model": KIND, "T": 1, "input_layout": "image", "crop_size": size,
        "output": "y", "output_kind": "pins",
        "profile": profile, "n_pins": n_pins, "size": size, "crop_factor": crop_factor,
        "output_doc": "y (1, 2N): u0, v0, u1, v1, ... with u = (x - cx) / r, "
                      "v = (y - cy) / r for the effective dome of the crop",
        "weights_dtype": weights_dtype,
        "mean_layout_norm": np.round(mean_layout.reshape(-1, 2), 6).tolist(),
        "fill_range": [round(v, 6) for v in fill_range], "fill_grid": grid,
        "fill_cells_range": cells_range, "max_dev_norm": round(max_dev_norm, 6),
        "alpha": float(alpha), "vision_params": {k: getattr(params, k) for k in (
            "block", "offset", "blur_sigma_px", "min_area_px", "max_area_px", "roi_shrink")},
        "seed": seed, "train_s": train_s, "training": training,
        "metrics": {"train": {"fit": metrics["train_fit"]}, "cv": None,
                    "test": {k: v for k, v in metrics.items() if k != "train_fit"}},
        "trained_on": {"data": source, "recordings": recs, "scenes": n_sim_scenes,
                       "split": f"simulated: unseen seeds from {seed + 100000}, presses up "
                                f"to {TEST_MAX_DEPTH_MM} mm; real: "
                                f"{training['real_holdout']}"},
        "config": {"module": "host.localiser.train", "profile": str(profile), "seed": seed,
                   "size": size, "crop_factor": crop_factor, "alpha": float(alpha),
                   "sim_scenes": n_sim_scenes, "frames_per_scene": frames_per_scene,
                   "max_depth_mm": max_depth_mm, "real_weight": float(real_weight),
                   "real_clips": [str(c) for c in real_clips]},
    }
    out = write_model(onx, out_dir, KIND, size * size, extra=extra)
    write_model_docs(out)                  # README.md (the model card) and train.toml
    size_bytes = (Path(out) / "model.onnx").stat().st_size
    return {"out_dir": str(out), "size_bytes": int(size_bytes), "weights_dtype": weights_dtype,
            "train_s": train_s, "stage_s": stage_s, "n_pins": n_pins, "size": size,
            "crop_factor": crop_factor, "alpha": float(alpha), "training": training,
            "metrics": metrics, "estimator": model}


def _clip_sha256(real_data, clip) -> str | None:
    """SHA-256 of a real clip's file, where it is one (None for frames given in memory)."""
    from device.pi.models.artefact import sha256_file
    cands = [Path(str(clip))]
    if real_data is not None and not isinstance(real_data, Mapping):
        cands = [Path(real_data) / "roboskin" / f"{clip}.avi", Path(real_data) / f"{clip}.avi",
                 *cands]
    for c in cands:
        if c.is_file():
            return sha256_file(c)
    return None


# --------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------


def add_arguments(ap) -> None:
    """The localiser trainer's options (``host localiser`` and ``python -m host.localiser``)."""
    ap.add_argument("--out", required=True, type=Path, help="model folder to write")
    ap.add_argument("--profile", default="roboskin")
    ap.add_argument("--real-data", type=Path, default=None,
                    help="folder with the real roboskin clips (e.g. ../shared/data)")
    ap.add_argument("--clip", action="append", default=[],
                    help="a recording of the sensor (repeatable), starting at rest; "
                         "with a calibrated --profile, use --sim-scenes 0")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--alpha", type=float, default=DEFAULT_ALPHA)
    ap.add_argument("--size", type=int, default=DEFAULT_SIZE)
    ap.add_argument("--sim-scenes", type=int, default=120)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--quiet", action="store_true", help="no progress bars")


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m host.localiser",
                                 description="train the fixed-count pin localiser (ONNX + JSON)")
    add_arguments(ap)
    return run(ap.parse_args(argv))


def run(args) -> int:
    """Train from parsed options; 2 with one line on stderr for bad input."""
    try:
        kw = {"real_clips": tuple(args.clip)} if args.clip else {}
        if args.clip and args.real_data is not None:
            raise ValueError("give --clip files or --real-data, not both")
        res = train_localiser(args.out, profile=args.profile, real_data=args.real_data,
                              seed=args.seed, alpha=args.alpha, size=args.size,
                              n_sim_scenes=args.sim_scenes, progress=not args.quiet, **kw)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    res.pop("estimator", None)
    if args.json:
        print(json.dumps(res, default=json_default))
    else:
        m = res["metrics"]
        print(f"wrote {res['out_dir']} ({res['size_bytes'] / 1e6:.2f} MB) in {res['train_s']} s")
        for k, v in m.items():
            if not isinstance(v, dict):
                print(f"  {k:<30} {v:.3g}")
                continue
            print(f"  {k:<30} median {v['median_px']:.2f} px  p90 {v['p90_px']:.2f} px  "
                  f"({v['n_pins']} pins)")
        rej = res["training"]["rejected"]
        print(f"  real frames: {res['training']['real_frames']} train, "
              f"{res['training']['real_test_frames']} held out, {len(rej)} rejected")
    return 0


if __name__ == "__main__":
    sys.exit(main())
