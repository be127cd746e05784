"""host/bench/costs.py: the machine line, the per-decision sum and the Pi 4 scaling,
and the vision pipeline timed on real frames."""
from __future__ import annotations

import math

from host.bench import costs
from tests.realdata import read_video, real_data_dir


def test_the_machine_line_names_cpu_cores_and_load():
    m = {"cpu": "Test CPU 9000", "cores": 2, "load": [0.5, 1.25, 3.0], "system": "Linux",
         "python": "3.11.7"}
    line = costs.machine_line(m)
    assert "Test CPU 9000, 2 cores, load average 0.50, 1.25, 3.00" in line
    now = costs.machine()
    assert now["cores"] >= 1 and now["cpu"] and len(now["load"]) == 3


def test_a_decision_is_vision_plus_model_and_the_pi_figure_scales_cpu_time():
    vision = {"wall": {"p50": 2.0, "p99": 9.0}, "cpu": {"p50": 1.5, "p99": 4.0}}
    model = {"wall": {"p50": 0.2, "p99": 1.0}, "cpu": {"p50": 0.1, "p99": 0.5}}
    c = costs.decision_cost(vision, model)
    assert math.isclose(c["wall"]["p50"], 2.2) and math.isclose(c["cpu"]["p99"], 4.5)
    assert math.isclose(c["pi4"]["p50"], costs.PI4_FACTOR * 1.6)
    assert costs.PI4_FACTOR == 4.0 and "Cortex-A72" in costs.PI4_SOURCE


def test_percentiles_of_nothing_are_none():
    assert costs.percentiles([]) == {"p50": None, "p99": None, "n": 0}
    p = costs.percentiles([1.0, 2.0, 3.0])
    assert p["p50"] == 2.0 and p["n"] == 3 and 2.0 < p["p99"] <= 3.0


def test_the_vision_pipeline_is_timed_per_real_frame():
    clip = real_data_dir("roboskin/smooth.avi") / "roboskin" / "smooth.avi"
    frames = read_video(clip, 0, 30)
    wall, cpu = costs.frame_times(frames)
    assert len(wall) == len(cpu) == 30
    assert all(w > 0 for w in wall) and all(c >= 0 for c in cpu)
    v = costs.vision_cost([frames[:15], frames[15:]], crop_px=32)
    assert v["cpu"]["n"] == 30 and v["wall"]["p50"] <= v["wall"]["p99"]
