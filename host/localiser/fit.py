"""Fit the localiser's Ridge regression and write it as a plain ONNX graph.

:func:`fit_ridge` is scikit-learn's Ridge (float64 Cholesky solve);
:func:`ridge_to_onnx` turns any fitted linear model into ``y = x W + b``
(float16 weights when float32 would pass 1 MB), which
:func:`host.learn.onnx_io.write_model` stores with its manifest.
"""

from __future__ import annotations

import numpy as np

from device.checks import finite_number
from host.learn.onnx_io import session

__all__ = ["DEFAULT_ALPHA", "MAX_FLOAT32_BYTES", "fit_ridge", "ridge_to_onnx", "onnx_vs_sklearn"]

DEFAULT_ALPHA = 150.0      # the seed paper's Ridge alpha


def fit_ridge(X: np.ndarray, Y: np.ndarray, alpha: float = DEFAULT_ALPHA,
              sample_weight: np.ndarray | None = None):
    """scikit-learn Ridge (float64 solve) fitted on X -> Y."""
    from sklearn.linear_model import Ridge

    alpha = finite_number("alpha", alpha, 0)
    model = Ridge(alpha=float(alpha), fit_intercept=True, solver="cholesky")
    model.fit(X.astype(np.float64), Y.astype(np.float64), sample_weight=sample_weight)
    return model


#: above this many bytes of float32 weights, :func:`ridge_to_onnx` stores float16
MAX_FLOAT32_BYTES = 1_000_000


def ridge_to_onnx(model, n_features: int, weights: str = "auto", input_name: str = "x"):
    """A fitted linear model (``coef_`` (k, n), ``intercept_`` (k,)) as ONNX ``y = x W + b``.

    A plain MatMul + Add graph (opset 17): packed initializers take 4 bytes a
    weight where skl2onnx's LinearRegressor takes 5, and it runs on any
    onnxruntime. ``weights``: "float32", "float16" (stored half precision and
    cast once when the session is built; 0.001 px worst case on roboskin), or
    "auto" (float16 when float32 would exceed 1 MB). Output name ``y``.
    """
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    W = np.asarray(model.coef_, np.float64).reshape(-1, n_features).T   # (n, k)
    b = np.asarray(model.intercept_, np.float64).reshape(-1)
    if weights == "auto":
        weights = "float16" if W.size * 4 > MAX_FLOAT32_BYTES else "float32"
    if weights not in ("float32", "float16"):
        raise ValueError(f"weights must be 'auto', 'float32' or 'float16', got weights={weights!r}")
    k = W.shape[1]
    nodes, inits = [], [numpy_helper.from_array(b.astype(np.float32), "b")]
    if weights == "float16":
        inits.append(numpy_helper.from_array(W.astype(np.float16), "W16"))
        nodes.append(helper.make_node("Cast", ["W16"], ["W"], to=TensorProto.FLOAT))
    else:
        inits.append(numpy_helper.from_array(W.astype(np.float32), "W"))
    nodes += [helper.make_node("MatMul", [input_name, "W"], ["xw"]),
              helper.make_node("Add", ["xw", "b"], ["y"])]
    graph = helper.make_graph(
        nodes, "localiser",
        [helper.make_tensor_value_info(input_name, TensorProto.FLOAT, [None, n_features])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [None, k])], inits)
    onx = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)],
                            producer_name="tacfoot.host.localiser")
    onx.ir_version = 8
    onnx.checker.check_model(onx)
    return onx


def onnx_vs_sklearn(onx, model, X: np.ndarray) -> float:
    """Largest |ONNX - scikit-learn| output on rows X (normalised units)."""
    sess = session(onx)
    got = sess.run(None, {sess.get_inputs()[0].name: X.astype(np.float32)})[0]
    return float(np.abs(got - model.predict(X)).max())
