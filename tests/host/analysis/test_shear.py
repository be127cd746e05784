"""The tactip_shear evaluation (host/analysis/shear.py): pin assignment and Ridge
regressions on the real tactip_shear images (skipped without the recordings)."""
from __future__ import annotations

import math

import pytest

from host.analysis.shear import evaluate_tactip_shear
from tests.realdata import real_data_dir


@pytest.fixture(scope="module")
def shear_result():
    data = real_data_dir("tactip_shear/targets_images.csv", "tactip_shear/images/image_1.png")
    return evaluate_tactip_shear(data)


@pytest.mark.real
@pytest.mark.slow
def test_tactip_shear_pins_found_and_assigned(shear_result):
    r = shear_result
    print(f"tactip_shear: {r['n_reference_pins']} layout pins, pitch {r['pitch_px']:.1f} px; "
          f"{r['frac_images_95']:.1%} of {r['n_images']} images have >= 95% assigned "
          f"(5th percentile {r['assigned_frac_p5']:.1%}); {r['track_ms_per_image']:.1f} ms/image")
    assert r["n_images"] == 400
    assert 320 <= r["n_reference_pins"] <= 335                     # the 331-pin layout, rim fragments dropped
    assert r["frac_images_95"] >= 0.95


@pytest.mark.real
@pytest.mark.slow
def test_tactip_shear_regression_beats_the_mean(shear_result):
    ratios = {k: v["ratio"] for k, v in shear_result["ratios"].items()}
    raw = {k: v["ratio"] for k, v in shear_result["ratios_raw_features"].items()}
    print("MAE(mean) / MAE(ridge):", {k: round(v, 2) for k, v in ratios.items()},
          "raw vectors + lost flags:", {k: round(v, 2) for k, v in raw.items()})
    assert ratios["pose_z"] >= 3.0
    assert ratios["shear_x"] >= 2.0
    assert ratios["shear_y"] >= 2.0
    for key in ("pose_Rx", "pose_Ry"):                             # reported; must at least beat the mean
        assert math.isfinite(ratios[key]) and ratios[key] > 1.0

