"""The marker pipeline's accuracy as host/analysis/pipeline_eval.py measures it: pin
recall, centroid error, identity switches, direction and contact on simulated scenes
with ground truth, and the direction on the real clips against optical flow."""
from __future__ import annotations

import pytest

from host.analysis.pipeline_eval import (chained_flow_direction_check, evaluate_scene,
                                         evaluate_sim, farneback_direction_check)
from tests.realdata import real_data_dir


def _clip_path(name):
    return real_data_dir(f"roboskin/{name}") / "roboskin" / name


@pytest.fixture(scope="module")
def sim_eval():
    return evaluate_sim(effects=("camera_noise",))


def test_pin_recall_and_precision_on_sim(sim_eval):
    s = sim_eval["summary"]
    assert s["recall_min"] >= 0.98 and s["precision_min"] >= 0.98, s


def test_centroid_error_median_half_a_pixel(sim_eval):
    assert sim_eval["summary"]["centroid_err_px_median_max"] <= 0.5


def test_identity_switches_during_drags(sim_eval):
    assert sim_eval["summary"]["id_switch_rate_max_mean"] <= 0.005


def test_direction_error_under_shear(sim_eval):
    assert sim_eval["summary"]["direction_err_deg_median_max"] <= 5.0
    assert all(r["direction_frames"] > 20 for r in sim_eval["scenes"]
               if r["scene"].startswith("drag-"))


def test_contact_f1(sim_eval):
    assert sim_eval["summary"]["contact_f1_min"] >= 0.98


def test_glare_costs_recall_but_not_tracking():
    """Saturated glare hides some pins (as on the real sensor); what is found is
    still placed and tracked right."""
    r = evaluate_scene("drag-45", effects=("glare", "camera_noise"))
    assert 0.9 <= r["recall"] < 0.98
    assert r["precision"] >= 0.97
    assert r["centroid_err_px_median"] <= 0.5
    assert r["id_switch_rate_mean"] <= 0.005
    assert r["direction_err_deg_median"] <= 5.0


def test_identities_hold_through_skipped_frames():
    """Every third frame only (a loop that falls behind and takes the newest
    frame): pins jump further than the tracker predicts, the re-acquisition runs,
    and the pins keep their identities."""
    r = evaluate_scene("drag-45", stride=3)
    assert r["frames_processed"] < 0.5 * r["frames"]
    assert r["reacquisitions"] >= 1
    assert r["id_switch_rate_mean"] <= 0.005 and r["id_switch_rate_max"] <= 0.05


@pytest.mark.parametrize("name", [
    "north.avi",
    pytest.param("east.avi", marks=pytest.mark.xfail(
        strict=True, reason="known shortfall: 19 deg against direct Farneback from the "
                            "reference (goal 15). Pins sit ~half a pitch from rest there, "
                            "where direct flow picks the wrong neighbour; flow chained frame "
                            "to frame agrees with the tracker to 3.1 deg (test below)")),
])
def test_real_direction_agrees_with_farneback(name):
    res = farneback_direction_check(_clip_path(name), step=3)
    assert res["compared_frames"] > 40
    assert res["median_angle_err_deg"] <= 15.0, res


def test_east_tracking_agrees_with_chained_flow():
    """The independent check that holds on east.avi: Farneback flow chained frame to
    frame, sampled at the tracked pins, agrees with the tracker's average vector."""
    res = chained_flow_direction_check(_clip_path("east.avi"), step=3)
    assert res["compared_frames"] > 40
    assert res["median_angle_err_deg"] <= 15.0, res

