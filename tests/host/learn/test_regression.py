"""Ridge regression from all pin vectors: real vectors_soft depth, ONNX export,
and finite outputs for NaN/inf/extreme inputs."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from device.pi.models.regressor import Regressor
from host.learn.regression import cross_validate, export_regressor, vectors_npz_features


def soft_depth():
    from tests.realdata import real_data_dir
    v = np.load(real_data_dir("roboskin/vectors_soft.npy") / "roboskin" / "vectors_soft.npy")
    n_trials, n_depths = v.shape[:2]
    X = vectors_npz_features(v.reshape(-1, v.shape[2], 2))
    y = np.tile(np.arange(n_depths, dtype=float), n_trials)
    groups = np.repeat(np.arange(n_trials), n_depths)
    return X, y, groups


def test_vectors_soft_depth_grouped_cv_beats_mean_by_4x():
    X, y, groups = soft_depth()
    res = cross_validate(X, y, groups=groups, alpha=150.0, k=5)
    assert res["grouped"]
    assert res["mae"] <= 0.25 * res["mae_predict_mean"], res


def test_exported_regressor_matches_sklearn_and_stays_finite(tmp_path):
    X, y, _ = soft_depth()
    out, pipe = export_regressor(X, y, tmp_path / "depth", kind="pressure")
    reg = Regressor.load(out)
    for i in (0, 7, 123):
        assert reg.predict_one(X[i]) == pytest.approx(float(pipe.predict(X[i:i + 1])[0]),
                                                       abs=1e-3)
    bad = X[0].copy()
    bad[:10] = np.nan
    bad[10:20] = np.inf
    bad[20:30] = -1e30
    y_bad = reg.predict_one(bad)
    assert np.isfinite(y_bad) and reg.fault        # cleaned, clipped, and flagged
    lo, hi = y.min() - 3 * y.std(), y.max() + 3 * y.std()
    assert lo <= y_bad <= hi                       # clipping keeps it in a sane range
    reg.predict_one(X[0])
    assert not reg.fault                           # the next clean input clears it


@pytest.fixture(scope="module")
def small_model(tmp_path_factory):
    rng = np.random.default_rng(1)
    X = rng.normal(size=(60, 9)).astype(np.float32)
    y = X[:, 0] * 2 + 1
    out, _ = export_regressor(X, y, tmp_path_factory.mktemp("m"), kind="pressure")
    return Regressor.load(out)


@settings(max_examples=60, deadline=None)
@given(arrays(np.float32, 9, elements=st.floats(allow_nan=True, allow_infinity=True,
                                                width=32)))
def test_any_input_gives_a_finite_output(small_model, x):
    assert np.isfinite(small_model.predict_one(x))


def test_cv_errors_are_clear():
    X = np.zeros((4, 3))
    with pytest.raises(ValueError, match="needs at least 5 groups"):
        cross_validate(X, np.arange(4.0), k=5)
    with pytest.raises(ValueError, match="NaN"):
        cross_validate(np.zeros((6, 3)), np.array([1, 2, np.nan, 1, 2, 3.0]), k=2)
