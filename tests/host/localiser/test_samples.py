"""Training samples and the augmented design matrix (host/localiser/samples.py)."""

from __future__ import annotations

import numpy as np
import pytest

from device.pi.vision.extract import ROBOSKIN_PARAMS
from device.pi.models.localiser import from_normalised, localiser_input
from host.localiser.samples import Sample, augment_rows, vision_params_for


def _sample(seed: int = 0) -> Sample:
    rng = np.random.default_rng(seed)
    binary = ((rng.random((80, 100)) < 0.2) * 255).astype(np.uint8)
    pins = rng.uniform(30, 90, (5, 2))
    return Sample(binary, (10, 5, 110, 85), (60.0, 45.0, 35.0), pins, np.ones(5, bool),
                  "sim:0", 0, 0.0)


def test_augment_rows_first_copy_is_the_unperturbed_crop():
    s = _sample()
    X, Y = augment_rows([s, _sample(1)], 16, 0.75, 3, 2.0, 0.02, np.random.default_rng(0))
    assert X.shape == (6, 256) and Y.shape == (6, 10)
    assert X.dtype == np.float32 and Y.dtype == np.float32
    np.testing.assert_allclose(X[0], localiser_input(s.binary, s.box, s.dome, 16, 0.75)[0])
    np.testing.assert_allclose(from_normalised(Y[0].reshape(-1, 2), s.dome, 0.75), s.pins_px,
                               atol=1e-3)
    # perturbed copies move the crop and its labels together
    assert not np.allclose(Y[1], Y[0]) and not np.allclose(X[1], X[0])


def test_augment_rows_without_perturbation_repeats_the_row():
    X, Y = augment_rows([_sample()], 16, 0.75, 2, 0.0, 0.0, np.random.default_rng(0))
    np.testing.assert_array_equal(X[0], X[1])
    np.testing.assert_array_equal(Y[0], Y[1])


def test_bad_arguments_name_the_field():
    with pytest.raises(ValueError, match="n_aug"):
        augment_rows([_sample()], 16, 0.75, 0, 0.0, 0.0, np.random.default_rng(0))
    with pytest.raises(ValueError, match="profile='nope'"):
        vision_params_for("nope")
    assert vision_params_for("roboskin") == ROBOSKIN_PARAMS
