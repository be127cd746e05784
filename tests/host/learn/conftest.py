"""Fixtures of the host.learn tests: small simulated step scenes (surface) and a
model trained once per module on them."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from host.bench.scenes import bench_scene, scene_toml
from host.data.simulate import simulate_to_dataset
from host.data.load import load_spec
from host.learn.train import train_model

T = 3
SURFACE_KINDS = ("hard", "soft", "wet", "no-touch")

def _simulate(out: Path, n_per_kind: int, seed: int, beyond: bool) -> Path:
    """Small randomised step scenes: bench_scene without camera effects (for speed)
    and with the stance direction near 90 degrees (12 trials cannot teach that the
    direction does not matter)."""
    scenes = out.parent / f"{out.name}-scenes"
    scenes.mkdir(parents=True)
    for k in range(n_per_kind):
        for i, kind in enumerate(SURFACE_KINDS):
            doc = bench_scene(kind, np.random.default_rng([seed, i, k]), beyond=beyond)
            doc["effects"] = ["imu_noise"]
            for a in doc["timeline"]:
                if a["action"] == "drag":
                    a["direction_deg"] = 90.0 + 10.0 * (k - 1)
            path = scenes / f"{kind}_{k}.toml"
            path.write_text(scene_toml(doc))
            simulate_to_dataset(str(path), out, seed=seed * 1000 + k, progress=False)
    return out


@pytest.fixture(scope="module")
def surface_sets(tmp_path_factory):
    """Train: 3 step trials per class; test: 1 per class, unseen seeds, surface
    parameters drawn beyond the training range."""
    base = tmp_path_factory.mktemp("surface")
    tr = _simulate(base / "train", 3, seed=1, beyond=False)
    te = _simulate(base / "test", 1, seed=2, beyond=True)
    cache = {}
    return (load_spec(str(tr), "surface", T, progress=False, cache=cache),
            load_spec(str(te), "surface", T, progress=False, cache=cache))


@pytest.fixture(scope="module")
def surface_model(surface_sets, tmp_path_factory):
    ws_tr, ws_te = surface_sets
    out = tmp_path_factory.mktemp("models") / "surface"
    res = train_model("surface", "fnn", ws_tr, ws_te, quantise=True, seed=0, out_dir=out,
                      progress=False, alpha=0.1, epochs=200)
    return res, out
