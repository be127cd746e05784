"""host/bench/scenes.py: randomised benchmark scenes and their parameter ranges."""
from __future__ import annotations

import numpy as np

from host.bench.scenes import bench_scene, scene_toml


def test_bench_scenes_parse_and_test_ranges_reach_beyond_training():
    from device.sim.scene import parse_scene

    try:
        import tomllib
    except ModuleNotFoundError:   # Python 3.10
        import tomli as tomllib
    from host.bench.scenes import BENCH_KINDS, SURFACE_RANGES

    for kind in BENCH_KINDS:
        for beyond in (False, True):
            doc = bench_scene(kind, np.random.default_rng(0), beyond)
            sc = parse_scene(tomllib.loads(scene_toml(doc)), source=kind)
            assert sc.duration_s > 0.3
    mus = [bench_scene("wet", np.random.default_rng(k), True)["surface"]["mu"] for k in range(60)]
    lo, hi = SURFACE_RANGES["wet"]["mu"][0]
    assert min(mus) < lo and max(mus) > hi
