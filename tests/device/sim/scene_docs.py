"""Small scenes shared by the simulator tests (tests/device/sim/test_*.py): built-in
scenes at 160x120 and a scene document to mutate."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from device.sim import load_scene

__all__ = ["SMALL", "small", "scene_doc", "all_frames"]

SMALL = dict(width=160, height=120)


def small(name: str, **kw):
    return replace(load_scene(name), **{**SMALL, **kw})


def scene_doc(**over):
    doc = {"sensor": {"profile": "roboskin", "fps": 60, "width": 160, "height": 120},
           "surface": {"preset": "hard"},
           "timeline": [{"action": "lower", "depth_mm": 2.0, "duration_s": 0.1},
                        {"action": "drag", "direction_deg": 0.0, "speed_mm_s": 20.0,
                         "duration_s": 0.3},
                        {"action": "lift", "duration_s": 0.1}]}
    doc.update(over)
    return doc


def all_frames(sim):
    return np.stack([sim.render(i) for i in range(sim.n_frames)])

