"""Simulated training frames of the localiser (host/localiser/sim.py)."""

from __future__ import annotations

import numpy as np
import pytest

from device.profile import load_profile
from host.localiser.sim import random_scene_doc, sim_frames


def test_random_scene_doc_is_seeded_and_bounded():
    a = random_scene_doc(np.random.default_rng(4), max_depth_mm=1.5)
    b = random_scene_doc(np.random.default_rng(4), max_depth_mm=1.5)
    assert a == b
    lower = a["timeline"][0]
    assert lower["action"] == "lower" and 0.3 <= lower["depth_mm"] <= 1.5
    assert a["timeline"][-1]["action"] == "lift"
    assert all(5 <= s["speed_mm_s"] <= 30 for s in a["timeline"] if s["action"] == "drag")
    assert a["sensor"]["profile"] == "roboskin"


def test_sim_frames_carry_true_pins_of_every_scene():
    n_pins = load_profile("roboskin").n_pins
    out = sim_frames(2, 3, seed=10)
    assert len(out) == 6
    assert {s.source for s in out} == {"sim:10", "sim:11"}
    for s in out:
        assert s.pins_px.shape == (n_pins, 2) and s.measured.all()
        assert s.binary.dtype == np.uint8 and set(np.unique(s.binary)) <= {0, 255}
        x0, y0, x1, y1 = s.box
        assert s.binary.shape == (y1 - y0, x1 - x0)
        assert s.disp_px >= 0.0
    # the same seed gives the same frames
    again = sim_frames(1, 3, seed=10)
    assert [s.frame for s in again] == [s.frame for s in out[:3]]


@pytest.mark.parametrize("kwargs, field", [({"n_scenes": -1}, "n_scenes"),
                                           ({"frames_per_scene": 0}, "frames_per_scene")])
def test_sim_frames_bad_counts_name_the_field(kwargs, field):
    args = {"n_scenes": 1, "frames_per_scene": 1, "seed": 0}
    args.update(kwargs)
    with pytest.raises(ValueError, match=field):
        sim_frames(**args)
