"""host/rig/plan.py: trial files expand to one trial per plate, repetition and
variant; a bad file names the entry before anything moves."""
from __future__ import annotations

import json

import pytest

from device.config import ConfigError
from host.cli import main as host_main
from host.rig.plan import load_plan, parse_plan
from tests import REPO_ROOT

TRIALS = REPO_ROOT / "trials"

GOOD = {
    "name": "t", "repetitions": 2,
    "plates": [{"name": "hard", "surface": "hard"}],
    "actions": [{"action": "press", "depths_mm": [1.0, 2.0]}],
}


def _doc(**over):
    d = json.loads(json.dumps(GOOD))
    d.update(over)
    return d


def test_a_good_plan_expands_to_one_trial_per_plate_repetition_and_variant():
    plan = parse_plan(_doc(plates=[{"name": "hard", "surface": "hard"},
                                   {"name": "foam", "surface": "soft"}]))
    assert len(plan.trials) == 2 * 2 * 2
    assert len({t.id for t in plan.trials}) == len(plan.trials)
    assert plan.plates[1].sim == "soft"                # foam: simulated by the soft preset


@pytest.mark.parametrize("over, needle", [
    ({"actions": [{"action": "poke", "depths_mm": [1]}]}, "actions[0].action"),
    ({"actions": [{"action": "press", "depths_mm": [1, 2, 25]}]}, "actions[0].depths_mm[2]"),
    ({"actions": [{"action": "press", "depths_mm": [1]},
                  {"action": "drag", "loads_n": [1, 50]}]}, "actions[1].loads_n[1]"),
    ({"actions": [{"action": "drag", "loads_n": [1], "directions": ["up"]}]},
     "actions[0].directions[0]"),
    ({"actions": [{"action": "drag", "loads_n": [1], "distance_mm": 80}]},
     "actions[0].distance_mm"),
    ({"actions": [{"action": "press", "depths_mm": [1], "depth": 2}]}, "actions[0].depth"),
    ({"plates": [{"name": "x", "surface": "sticky"}]}, "plates[0].surface"),
    ({"rig": {"surface_mm": 50}}, "rig.surface_mm"),
])
def test_a_bad_trial_file_names_the_entry(over, needle):
    with pytest.raises(ConfigError) as ei:
        parse_plan(_doc(**over), source="bad.toml")
    assert needle in str(ei.value)
    assert "bad.toml" in str(ei.value)


def test_depth_beyond_travel_says_how_far_the_rig_can_go():
    with pytest.raises(ConfigError, match=r"at most 20 mm"):
        parse_plan(_doc(actions=[{"action": "press", "depths_mm": [20.5]}]))


def test_shipped_trial_files_reproduce_the_paper(capsys):
    counts = {}
    for p in sorted(TRIALS.glob("*.toml")):
        assert host_main(["rig", "check", str(p), "--json"]) == 0
        counts[p.stem] = json.loads(capsys.readouterr().out)
    press = counts["paper-press-depths"]
    assert press["trials"] == 100 * 5 * 3 and press["plates"] == ["hard", "foam", "wet"]
    sens = counts["paper-sensations"]
    assert sens["trials"] == 30 * 3 * 3
    assert {v.split("-")[1] for v in sens["variants"]} == {"left", "right", "centre"}
    tex = load_plan(TRIALS / "paper-texture-drags.toml")
    assert {p.texture for p in tex.plates} == {"smooth", "lego", "concrete"}
