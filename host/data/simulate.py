"""Render simulated scenes into a tacfoot dataset folder (``host simulate``)."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from device.sim import SURFACE_LABELS, TEXTURE_LABELS, Scene, Simulator, load_scene
from host.data.dataset import DatasetWriter
from host.data.recordings import profile_ref, sim_recording
from host.extras import need

__all__ = ["simulate_to_dataset"]


def _progress(total: int, desc: str, enabled: bool = True):
    tqdm = need("tqdm").tqdm
    return tqdm(total=total, desc=desc, unit="frame", disable=not enabled or None,
                file=sys.stderr, leave=False)


def simulate_to_dataset(scene_ref, out: Path, seed: int = 0, trials: int = 1,
                        progress: bool = True) -> dict:
    """Render ``trials`` runs of a scene (a built-in name, a scene file or a
    :class:`device.sim.Scene`; seeds ``seed``, ``seed + 1``, ...) into the dataset
    folder ``out``; returns the folder, the trial files and the frame count."""
    scene = scene_ref if isinstance(scene_ref, Scene) else load_scene(scene_ref)
    files = []
    with DatasetWriter(out, meta={"surface_labels": list(SURFACE_LABELS),
                                  "texture_labels": list(TEXTURE_LABELS),
                                  "source": "simulator"}) as writer:
        for k in range(trials):
            sim = Simulator(scene, seed=seed + k)
            frames = np.empty((sim.n_frames, sim.height, sim.width), np.uint8)
            with _progress(sim.n_frames, f"{scene.name} seed {seed + k}", progress) as bar:
                for i in range(sim.n_frames):
                    sim.render(i, frames[i])
                    bar.update(1)
            truth = dict(sim.truth, rest_pins_px=sim.rest_pins_px)
            info = {"scene": scene.name, "scene_file": scene.source, "seed": seed + k,
                    "fps": scene.fps, "width": sim.width, "height": sim.height,
                    "recording": sim_recording(scene.name, seed + k),
                    "profile": scene.profile.name,
                    "profile_sha256": profile_ref(scene.profile.name)["sha256"],
                    "n_pins": scene.profile.n_pins,
                    "effects": list(scene.effect_names)}
            files.append(str(writer.add_trial(frames, truth, info)))
    return {"out": str(out), "trials": files, "frames": int(sum(
        e["frames"] for e in writer.index["trials"][-trials:]))}
