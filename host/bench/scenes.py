"""Randomised simulated scenes for the benchmarks: surface parameter ranges per scene
kind (a training range and a wider test range beyond it), one scene per trial, and
:func:`simulate_scenes`, which simulates them into a dataset folder."""
from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np

from host.data.dataset import atomic_write_text, is_dataset
from host.data.simulate import simulate_to_dataset
from host.learn.tasks import check_choice, check_int
from host.extras import need

__all__ = ["BENCH_FPS", "SURFACE_RANGES", "BENCH_KINDS", "scene_toml", "bench_scene",
           "simulate_scenes"]


BENCH_FPS = 120
#: surface parameters per scene kind: (training range, test range beyond it).
#: The gait (depth, speeds, timings, direction) has one range for both. Friction
#: has one range for hard and soft, and one for the three textures, so that it
#: tells nothing about the class; wet is low friction by definition.
SURFACE_RANGES = {
    "hard": {"preset": "hard", "stiffness_n_per_mm": ((100, 300), (50, 600)),
             "mu": ((0.6, 1.0), (0.5, 1.2))},
    "soft": {"preset": "soft", "stiffness_n_per_mm": ((1.0, 2.0), (0.8, 2.4)),
             "mu": ((0.6, 1.0), (0.5, 1.2))},
    "wet": {"preset": "wet", "stiffness_n_per_mm": ((100, 300), (50, 600)),
            "mu": ((0.04, 0.12), (0.02, 0.15))},
    "no-touch": {"preset": "hard"},
    "smooth": {"preset": "smooth", "mu": ((0.45, 0.75), (0.35, 0.85))},
    "lego": {"preset": "lego", "mu": ((0.45, 0.75), (0.35, 0.85)),
             "texture_amplitude_mm": ((0.2, 0.3), (0.15, 0.35)),
             "stud_pitch_mm": ((7.0, 9.0), (6.0, 10.0))},
    "concrete": {"preset": "concrete", "mu": ((0.45, 0.75), (0.35, 0.85)),
                 "texture_amplitude_mm": ((0.1, 0.15), (0.08, 0.18))},
    "slip": {"preset": "hard", "mu": ((0.3, 0.6), (0.25, 0.7)),
             "wet_mu": ((0.03, 0.1), (0.02, 0.14))},
    "press-hard": {"preset": "hard", "stiffness_n_per_mm": ((100, 300), (50, 600))},
    "press-soft": {"preset": "soft", "stiffness_n_per_mm": ((1.0, 2.0), (0.8, 2.4))},
}
BENCH_KINDS = tuple(SURFACE_RANGES)


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return repr(round(float(v), 6))
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(f"cannot write {type(v).__name__} to a scene file")


def scene_toml(doc: dict) -> str:
    """A scene dict (top-level keys, tables, a ``timeline`` list and an optional
    ``surfaces`` table of tables) as scene-file TOML (docs/simulator.md)."""
    lines = []
    for k, v in doc.items():
        if not isinstance(v, dict) and k != "timeline":
            lines.append(f"{k} = {_toml_value(v)}")
    for k, v in doc.items():
        if isinstance(v, dict) and k != "surfaces":
            lines.append(f"\n[{k}]")
            lines += [f"{kk} = {_toml_value(vv)}" for kk, vv in v.items()]
    for name, table in doc.get("surfaces", {}).items():
        lines.append(f"\n[surfaces.{name}]")
        lines += [f"{kk} = {_toml_value(vv)}" for kk, vv in table.items()]
    for a in doc.get("timeline", []):
        lines.append("\n[[timeline]]")
        lines += [f"{kk} = {_toml_value(vv)}" for kk, vv in a.items()]
    return "\n".join(lines) + "\n"


def bench_scene(kind: str, rng: np.random.Generator, beyond: bool = False) -> dict:
    """A randomised scene (a dict for :func:`scene_toml`) of one kind:

    * ``hard``, ``soft``, ``wet``, ``no-touch``: a step. The foot comes down while
      still moving sideways (a touchdown with foot speed, as in a gait: one-frame
      lower and drag steps in turn, so friction acts from the first touch), drags
      through the stance, and lifts; ``no-touch`` swings the same way in the air;
    * ``smooth``, ``lego``, ``concrete``: a press and a long drag that slides;
    * ``slip``: the ``slip-onset`` scene randomised: a drag on a hard floor until
      friction saturates and the patch slips, a lift, then a wet patch that slips
      almost at once;
    * ``press-hard``, ``press-soft``: presses to two random depths with holds
      (pressure).

    Surface parameters (mu, stiffness, texture amplitude, stud pitch) come from the
    training range, or with ``beyond=True`` from the wider test range
    (:data:`SURFACE_RANGES`); camera noise too. The gait (depths, speeds, timings,
    directions) has one range for both.
    """
    check_choice("kind", kind, BENCH_KINDS)
    spec = SURFACE_RANGES[kind]

    def U(lo, hi):
        return float(rng.uniform(lo, hi))

    def surf(key):
        lo, hi = spec[key][1 if beyond else 0]
        return U(lo, hi)

    noise = U(0.5, 4.0) if beyond else U(1.0, 3.0)
    doc = {"name": f"bench-{kind}", "description": f"benchmark {kind} scene (host.bench.scenes)",
           "hover_mm": U(1.5, 2.5),
           "effects": ["glare", {"name": "camera_noise", "sigma": round(noise, 3)},
                       "imu_noise"],
           "sensor": {"profile": "roboskin", "fps": BENCH_FPS}}
    surface = {"preset": spec["preset"]}
    for key in ("stiffness_n_per_mm", "mu", "texture_amplitude_mm", "stud_pitch_mm"):
        if key in spec:
            surface[key] = surf(key)
    doc["surface"] = surface
    theta = U(0.0, 360.0)
    step = 1.0 / BENCH_FPS
    tl = [{"action": "hold", "duration_s": U(0.03, 0.08)}]
    if kind in ("hard", "soft", "wet", "no-touch"):
        speed = U(8.0, 14.0)
        if kind == "no-touch":
            tl += [{"action": "drag", "direction_deg": theta, "speed_mm_s": speed,
                    "duration_s": U(0.3, 0.45)},
                   {"action": "lift", "height_mm": U(0.5, 2.0), "duration_s": 0.1},
                   {"action": "drag", "direction_deg": (theta + 180) % 360,
                    "speed_mm_s": speed, "duration_s": U(0.1, 0.2)}]
        else:
            depth = U(2.3, 3.0)
            n_low = int(round(U(0.06, 0.1) * BENCH_FPS))
            tl.append({"action": "lower", "depth_mm": 0.0, "duration_s": U(0.03, 0.06)})
            for k in range(1, n_low + 1):
                tl.append({"action": "lower", "depth_mm": depth * k / n_low, "duration_s": step})
                tl.append({"action": "drag", "direction_deg": theta, "speed_mm_s": 2 * speed,
                           "duration_s": step})
            tl += [{"action": "drag", "direction_deg": theta, "speed_mm_s": speed,
                    "duration_s": U(0.3, 0.45)},
                   {"action": "lift", "height_mm": doc["hover_mm"], "duration_s": U(0.06, 0.1)},
                   {"action": "hold", "duration_s": U(0.03, 0.06)}]
    elif kind in ("smooth", "lego", "concrete"):
        tl += [{"action": "lower", "depth_mm": U(1.5, 2.5), "duration_s": U(0.1, 0.15)},
               {"action": "drag", "direction_deg": theta, "speed_mm_s": U(15.0, 25.0),
                "duration_s": U(0.6, 0.9)},
               {"action": "lift", "height_mm": doc["hover_mm"], "duration_s": U(0.1, 0.15)}]
    elif kind == "slip":
        wet = {"preset": "wet", "mu": surf("wet_mu")}
        doc["surfaces"] = {"patch": wet}
        speed = U(6.0, 10.0)
        tl += [{"action": "lower", "depth_mm": U(2.0, 3.0), "duration_s": U(0.15, 0.25)},
               {"action": "drag", "direction_deg": theta, "speed_mm_s": speed,
                "duration_s": U(0.5, 0.8)},
               {"action": "lift", "height_mm": doc["hover_mm"], "duration_s": U(0.15, 0.25)},
               {"action": "lower", "surface": "patch", "depth_mm": U(2.0, 3.0),
                "duration_s": U(0.15, 0.25)},
               {"action": "drag", "direction_deg": (theta + U(90, 270)) % 360,
                "speed_mm_s": U(6.0, 10.0), "duration_s": U(0.3, 0.5)},
               {"action": "lift", "height_mm": doc["hover_mm"], "duration_s": U(0.15, 0.25)}]
    else:                                   # press-hard, press-soft
        d1, d2 = U(0.5, 3.5), U(0.5, 3.5)
        tl += [{"action": "lower", "depth_mm": d1, "duration_s": U(0.1, 0.3)},
               {"action": "hold", "duration_s": U(0.05, 0.15)},
               {"action": "lower", "depth_mm": d2, "duration_s": U(0.1, 0.2)},
               {"action": "hold", "duration_s": U(0.05, 0.15)},
               {"action": "lift", "height_mm": doc["hover_mm"], "duration_s": U(0.1, 0.3)}]
    doc["timeline"] = tl
    return doc


def simulate_scenes(out_dir, kinds, n_per_kind: int, seed: int, beyond: bool = False,
                    progress: bool = True) -> Path:
    """A dataset folder of ``n_per_kind`` randomised trials of each kind, the scene
    files beside it (``out_dir/scenes``). Trial k of a kind uses simulator seed
    ``seed * 100000 + k`` and its parameters come from a random stream of
    (``seed``, kind, k), so two calls with different seeds share nothing.
    Reuses a complete folder written with the same arguments."""
    tqdm = need("tqdm").tqdm

    kinds = [check_choice("kind", k, BENCH_KINDS) for k in kinds]
    n_per_kind = check_int("n_per_kind", n_per_kind, 1)
    seed = check_int("seed", seed, 0)
    out = Path(out_dir)
    data = out / "data"
    key = {"kinds": kinds, "n_per_kind": n_per_kind, "seed": seed, "beyond": bool(beyond),
           "ranges": json.loads(json.dumps({k: SURFACE_RANGES[k] for k in kinds})),
           "version": 1}
    stamp = out / "bench.json"
    if stamp.is_file() and is_dataset(data):
        try:
            if json.loads(stamp.read_text()) == key:
                return data
        except json.JSONDecodeError:
            pass
    if data.exists():
        shutil.rmtree(data)
    scenes = out / "scenes"
    scenes.mkdir(parents=True, exist_ok=True)
    jobs = [(kind, k) for k in range(n_per_kind) for kind in kinds]
    for kind, k in tqdm(jobs, desc=f"simulate {out.name}", unit="trial",
                        disable=not progress or None, file=sys.stderr, leave=False):
        rng = np.random.default_rng([seed, BENCH_KINDS.index(kind), k, int(beyond)])
        path = scenes / f"{kind}_{k:03d}.toml"
        path.write_text(scene_toml(bench_scene(kind, rng, beyond)))
        simulate_to_dataset(str(path), data, seed=seed * 100000 + k, trials=1, progress=False)
    atomic_write_text(stamp, json.dumps(key))
    return data

