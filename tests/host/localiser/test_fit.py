"""Ridge fit and ONNX export of the localiser (host/localiser/fit.py)."""

from __future__ import annotations

import numpy as np
import pytest

from host.localiser.fit import fit_ridge, onnx_vs_sklearn, ridge_to_onnx


def _data(n_features: int = 12, k: int = 4, seed: int = 0):
    rng = np.random.default_rng(seed)
    X = rng.random((200, n_features)).astype(np.float32)
    W = rng.normal(size=(n_features, k))
    return X, (X @ W + 0.5).astype(np.float32)


def test_fit_ridge_recovers_a_linear_map():
    X, Y = _data()
    model = fit_ridge(X, Y, alpha=1e-6)
    np.testing.assert_allclose(model.predict(X), Y, atol=1e-3)


@pytest.mark.parametrize("weights, stored", [("float32", "W"), ("float16", "W16")])
def test_onnx_graph_gives_the_model_output(weights, stored):
    X, Y = _data()
    model = fit_ridge(X, Y, alpha=1.0)
    onx = ridge_to_onnx(model, X.shape[1], weights)
    assert stored in {i.name for i in onx.graph.initializer}
    assert [o.name for o in onx.graph.output] == ["y"]
    assert onnx_vs_sklearn(onx, model, X) < (1e-4 if weights == "float32" else 1e-2)


def test_auto_weights_switch_to_float16_above_1_mb():
    X, Y = _data(n_features=600, k=500)
    onx = ridge_to_onnx(fit_ridge(X, Y), 600, "auto")
    assert "W16" in {i.name for i in onx.graph.initializer}
    X, Y = _data()
    assert "W" in {i.name for i in ridge_to_onnx(fit_ridge(X, Y), 12, "auto").graph.initializer}


def test_bad_arguments_name_the_field():
    X, Y = _data()
    with pytest.raises(ValueError, match="alpha"):
        fit_ridge(X, Y, alpha=float("nan"))
    with pytest.raises(ValueError, match="weights='float64'"):
        ridge_to_onnx(fit_ridge(X, Y), 12, "float64")
