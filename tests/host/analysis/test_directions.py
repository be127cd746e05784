"""Average-vector directions from tracked vectors and from localiser pins
(host.analysis.directions)."""
from __future__ import annotations


import numpy as np
import pytest

from host.analysis.directions import (angle_diff_deg, compare_directions, direction_deg,
                                      direction_series, read_lines)
from host.cli import main
from tests import REPO_ROOT


def _line(i, contact, shear, pins, faults=()):
    return {"frame": i, "contact": contact, "shear_x": shear[0], "shear_y": shear[1],
            "faults": list(faults), "localised_px": np.asarray(pins).tolist()}


def test_directions_and_angle_differences():
    assert direction_deg([[1, 0], [0, 1], [-1, 0], [0, -1], [0, 0]]).tolist() == \
        [0.0, 90.0, 180.0, 270.0, 0.0]
    assert angle_diff_deg([350.0, 10.0, 180.0], [10.0, 350.0, 0.0]).tolist() == \
        [-20.0, 20.0, -180.0]


def test_series_measures_pins_from_the_rest_frame():
    rest = np.array([[10.0, 10.0], [20.0, 10.0], [15.0, 20.0]])
    lines = [_line(0, False, (0, 0), rest + 5, faults=["reference_not_set"]),
             _line(1, False, (0, 0), rest),                       # the rest frame
             _line(2, True, (2.0, 0.0), rest + [[1, 0], [3, 0], [2, 0]]),
             _line(3, True, (0.0, -4.0), rest + [0, -3]),
             _line(4, True, (9.0, 9.0), rest + 50, faults=["localiser"]),   # not sound
             _line(5, False, (0.1, 0.0), rest)]
    s = direction_series(lines)
    assert s["rest_frame"] == 1
    assert s["frame"].tolist() == [2, 3]
    assert s["vectors_px"].tolist() == [[2.0, 0.0], [0.0, -4.0]]
    assert s["localised_px"].tolist() == [[2.0, 0.0], [0.0, -3.0]]
    c = compare_directions(s)
    assert c["frames"] == 2 and c["compared"] == 2 and not c["weak"]
    assert c["median_abs_diff_deg"] == 0.0 and c["within_30deg"] == 1.0
    assert c["vectors_deg"] == pytest.approx(296.57, abs=0.01)    # mean (1, -2)
    assert c["localised_deg"] == pytest.approx(303.69, abs=0.01)  # mean (1, -1.5)


def test_hard_cases_are_finite_with_a_flag_or_a_named_error():
    rest = np.zeros((3, 2))
    still = direction_series([_line(0, False, (0, 0), rest), _line(1, True, (0, 0), rest)])
    c = compare_directions(still)
    assert c["weak"] and c["compared"] == 0 and c["median_abs_diff_deg"] == 0.0
    assert all(np.isfinite(c[k]) for k in ("vectors_deg", "localised_deg", "within_30deg"))
    with pytest.raises(ValueError, match="localised_px"):
        direction_series([{"frame": 0, "contact": True, "shear_x": 1, "shear_y": 0}])
    with pytest.raises(ValueError, match="no rest frame"):
        direction_series([_line(0, True, (1, 0), rest, faults=["localiser"])])


def test_read_lines_names_the_bad_line(tmp_path):
    p = tmp_path / "a.jsonl"
    p.write_text('{"frame": 0}\n\n{"summary": true}\n')
    assert read_lines(p) == [{"frame": 0}]
    p.write_text('{"frame": 0}\nnot json\n')
    with pytest.raises(ValueError, match="a.jsonl:2"):
        read_lines(p)


@pytest.mark.parametrize("scene, expected_deg", [("drag-45", 225.0), ("drag-90", 270.0)])
def test_vectors_and_localiser_agree_on_a_simulated_drag(tmp_path, scene, expected_deg):
    # the pins move opposite to the commanded drag direction (image axes)
    out = tmp_path / "a.jsonl"
    assert main(["analyse", f"sim://{scene}", "--localiser",
                 str(REPO_ROOT / "models" / "localiser-roboskin"), "--out", str(out)]) == 0
    s = direction_series(read_lines(out))
    c = compare_directions(s)
    assert c["frames"] > 50 and c["compared"] > 0.6 * c["frames"]
    assert abs(angle_diff_deg(c["vectors_deg"], expected_deg)) < 3.0
    assert abs(angle_diff_deg(c["localised_deg"], expected_deg)) < 15.0
    assert c["median_abs_diff_deg"] < 15.0 and c["within_30deg"] > 0.8
