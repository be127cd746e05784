"""Sim-to-real: a texture model trained only on simulated frames, scored on real
recordings (the user's data spec: its labels are the textures simulated).

:func:`stroke_scene` writes a randomised scene of strokes over one texture (the
foot presses, drags in a random direction, lifts, and again), as the real
``smooth.avi`` and ``concrete.avi`` show. ``calibrated`` takes the surfaces fitted
to those clips (``roboskin-smooth`` and ``roboskin-concrete`` in
:data:`device.sim.PRESETS`) instead of the simulator's generic ``smooth`` and
``concrete``; ``randomise`` varies per trial what the real sensor varies: glare
strength and size, lost pins, brightness (and with it where the threshold falls) and
the pin pitch. :func:`sim_to_real` simulates the trials, trains the texture FNN on
them and evaluates it, through the Pi's loader, on contact windows of the real clips.
The real frames are never trained on.
"""
from __future__ import annotations

import shutil
import time
from pathlib import Path

import numpy as np

from device.sim import PRESETS, parse_scene
from host.analysis.motion import MOTION_FIGURES, motion_by_class
from host.data.load import load_spec, load_specs
from host.data.simulate import simulate_to_dataset
from host.learn.evaluate import evaluate_model
from host.learn.train import train_model
from device.errors import InputError

__all__ = ["SIM2REAL_TEXTURES", "SIM2REAL_MODEL", "SIM2REAL_TRIALS", "sim2real_table", "stroke_scene", "simulate_strokes",
           "real_texture_manifest", "sim_to_real"]

#: the textures simulated when none are given (the labels of the authors' clips)
SIM2REAL_TEXTURES = ("concrete", "smooth")
#: the sim-trained model: FNN, window T, hidden layers, L2 penalty, rotated copies
SIM2REAL_MODEL = {"model": "grid-fnn", "T": 10, "hidden": (64, 32), "alpha": 0.01, "augment": 0,
                  "epochs": 300}
FPS = 120
#: simulated stroke trials per texture `host realism` trains on by default
SIM2REAL_TRIALS = 12


def _u(rng, lo, hi) -> float:
    return round(float(rng.uniform(lo, hi)), 4)


def stroke_scene(texture: str, rng: np.random.Generator, calibrated: bool = True,
                 randomise: bool = True, strokes: int = 3) -> dict:
    """A scene document (for :func:`device.sim.parse_scene`) of ``strokes`` strokes
    over ``texture`` (a simulator surface preset; ``calibrated`` takes its
    ``roboskin-`` fit when there is one) with the roboskin profile at 120 fps."""
    if texture not in PRESETS:
        raise InputError(f"texture must be a simulator surface preset "
                         f"({', '.join(sorted(PRESETS))}), got {texture!r}")
    preset = (f"roboskin-{texture}" if calibrated and f"roboskin-{texture}" in PRESETS
              else texture)
    effects: list = [{"name": "camera_noise", "sigma": _u(rng, 1.0, 3.0)}]
    if randomise:
        effects += [{"name": "glare", "peak": _u(rng, 60.0, 180.0),
                     "sigma_px": _u(rng, 12.0, 24.0)},
                    {"name": "pin_loss", "fraction": _u(rng, 0.0, 0.12)},
                    {"name": "exposure", "gain": _u(rng, 0.85, 1.15)},
                    {"name": "pitch", "scale": _u(rng, 0.97, 1.03)},
                    {"name": "motion_blur", "exposure_ms": _u(rng, 2.0, 10.0)}]
    else:
        effects.append("glare")
    tl = [{"action": "hold", "duration_s": _u(rng, 0.03, 0.08)}]
    for _ in range(strokes):
        tl += [{"action": "lower", "depth_mm": _u(rng, 1.2, 2.2),
                "duration_s": _u(rng, 0.04, 0.1)},
               {"action": "drag", "direction_deg": _u(rng, 0.0, 360.0),
                "speed_mm_s": _u(rng, 15.0, 40.0), "duration_s": _u(rng, 0.12, 0.3)},
               {"action": "lift", "height_mm": _u(rng, 0.5, 1.5),
                "duration_s": _u(rng, 0.04, 0.08)},
               {"action": "hold", "duration_s": _u(rng, 0.03, 0.1)}]
    return {"name": f"strokes-{texture}", "hover_mm": _u(rng, 0.5, 1.5), "effects": effects,
            "sensor": {"profile": "roboskin", "fps": FPS},
            "surface": {"preset": preset}, "timeline": tl}


def simulate_strokes(out_dir, n_per_texture: int, seed: int = 0, calibrated: bool = True,
                     randomise: bool = True, progress: bool = False, strokes: int = 3,
                     textures=SIM2REAL_TEXTURES) -> Path:
    """A new dataset folder ``out_dir`` (replaced if it exists) of ``n_per_texture``
    stroke trials of each of ``textures``."""
    out = Path(out_dir)
    shutil.rmtree(out, ignore_errors=True)
    for k in range(n_per_texture):
        for j, texture in enumerate(sorted(textures)):
            rng = np.random.default_rng([seed, j, k])
            doc = stroke_scene(texture, rng, calibrated, randomise, strokes)
            scene = parse_scene(doc, source=f"{texture}_{k:03d}")
            simulate_to_dataset(scene, out, seed=seed * 100000 + k, progress=progress)
    return out


def real_texture_manifest(rows, work, frames: int | None = None) -> Path:
    """A CSV manifest of real recordings ``rows``: (path, label, start frame, end frame
    or None), each cut to its first ``frames`` frames (or whole)."""
    work = Path(work)
    work.mkdir(parents=True, exist_ok=True)
    lines = ["path,label,start_frame,end_frame"]
    for path, label, start, end in rows:
        stop = start + int(frames) if frames else end
        if end is not None and stop is not None:
            stop = min(stop, end)
        lines.append(f"{Path(path).resolve()},{label},{int(start)},"
                     f"{'' if stop is None else int(stop)}")
    path = work / "real-texture.csv"
    path.write_text("\n".join(lines) + "\n")
    return path


def sim_to_real(real_specs, work, n_per_texture: int = 8, seed: int = 0,
                calibrated: bool = True, randomise: bool = True,
                real_frames: int | None = None, progress: bool = False,
                model: dict | None = None, strokes: int = 3,
                profile: str = "roboskin") -> dict:
    """Train the texture model (:data:`SIM2REAL_MODEL`, updated by ``model``) on
    ``n_per_texture`` simulated trials of ``strokes`` strokes per texture only, and
    score it on the contact windows of the real data specs ``real_specs`` (CSV
    manifests or dataset folders; their labels are the textures simulated; cut them
    with :func:`real_texture_manifest`), features with ``profile``. Its simulated
    held-out accuracy is measured on a quarter as many (at least one) further trials
    per texture, from other seeds.

    Returns accuracy over all real contact windows, per texture, the confusion
    matrix, the window counts and the settings (JSON-able)."""
    t0 = time.perf_counter()
    work = Path(work)
    m = dict(SIM2REAL_MODEL, **(model or {}))
    specs = [str(s) for s in ([real_specs] if isinstance(real_specs, (str, Path))
                              else real_specs)]
    real = load_specs(specs, "texture", m["T"], contact_only=True, progress=progress,
                      profile=profile)
    textures = sorted(set(real.labels))
    for t in textures:
        stroke_scene(t, np.random.default_rng(0), calibrated)    # a ValueError names it
    tag = f"{'cal' if calibrated else 'default'}-{'rand' if randomise else 'fixed'}"
    data = simulate_strokes(work / f"sim-{tag}-{seed}-{n_per_texture}", n_per_texture, seed,
                            calibrated, randomise, progress, strokes, textures)
    n_test = max(1, n_per_texture // 4)
    test = simulate_strokes(work / f"simtest-{tag}-{seed}-{n_test}", n_test, seed + 1000,
                            calibrated, randomise, progress, strokes, textures)
    ws = load_spec(str(data), "texture", m["T"], contact_only=True, progress=progress,
                   profile=profile)
    ws_test = load_spec(str(test), "texture", m["T"], contact_only=True, progress=progress,
                        profile=profile)
    model_dir = work / f"model-{tag}-{seed}-{n_per_texture}"
    res = train_model("texture", m["model"], ws, ws_test, seed=seed, out_dir=model_dir,
                      progress=progress, uses_imu=False, hidden=m["hidden"], alpha=m["alpha"],
                      augment=m["augment"], epochs=m["epochs"], profile=profile)
    ev = evaluate_model(model_dir, real)
    cm = ev["metrics"]["confusion"]
    per_class = ev["metrics"]["per_class"]
    per_label = {label: round(per_class[label]["recall"], 4) if label in per_class else 0.0
                 for label in textures}
    return {"accuracy": ev["metrics"]["accuracy"], "per_label": per_label, "confusion": cm,
            "sim_test_accuracy": res["metrics"]["test"]["accuracy"],
            "sim_windows": len(ws), "real_windows": len(real),
            "ignored_pins": len(res.get("ignored_pins") or []),
            "motion": {"real": motion_by_class(real), "sim": motion_by_class(ws)},
            "settings": {"calibrated": calibrated, "randomise": randomise,
                         "trials_per_texture": n_per_texture, "seed": seed,
                         "real_frames": real_frames, "uses_imu": False,
                         "real_specs": specs, "profile": str(profile),
                         **{k: (list(v) if isinstance(v, tuple) else v) for k, v in m.items()}},
            "seconds": round(time.perf_counter() - t0, 1)}


def sim2real_table(res: dict) -> str:
    """The sim-to-real figure and the pin-motion figures (real | simulated) as text."""
    st = res["settings"]
    how = ("calibrated surfaces, randomised sensor" if st["calibrated"] and st["randomise"]
           else "calibrated surfaces" if st["calibrated"]
           else "generic surfaces, randomised sensor" if st["randomise"]
           else "generic surfaces, no randomisation")
    frames = f"first {st['real_frames']} frames" if st["real_frames"] else "all frames"
    textures = sorted(res["per_label"])
    lines = [f"sim-to-real texture: {st['model']} T={st['T']} trained only on simulated strokes "
             f"({st['trials_per_texture']} trials per texture, {how}); tested on the real "
             f"recordings' contact windows ({frames})",
             "| real texture | contact windows | right texture |", "|---|--:|--:|"]
    cm = res["confusion"]
    for label in textures:
        n = sum(cm["matrix"][cm["labels"].index(label)]) if label in cm["labels"] else 0
        lines.append(f"| {label} | {n} | {res['per_label'][label]:.3f} |")
    lines += [f"| all | {res['real_windows']} | {res['accuracy']:.3f} |", "",
              f"simulated held-out accuracy: {res['sim_test_accuracy']:.3f}; pins ignored by "
              f"the model: {res['ignored_pins']}", "",
              "pin motion in contact windows, median / p90 (real | simulated)",
              "| texture | figure | real | simulated |", "|---|---|--:|--:|"]
    for label in textures:
        real, sim = res["motion"]["real"].get(label), res["motion"]["sim"].get(label)
        if real is None or sim is None:
            continue
        for key, name in MOTION_FIGURES:
            lines.append(f"| {label} | {name} | {real[key + '_p50']:.2f} / "
                         f"{real[key + '_p90']:.2f} | {sim[key + '_p50']:.2f} / "
                         f"{sim[key + '_p90']:.2f} |")
    return "\n".join(lines)
