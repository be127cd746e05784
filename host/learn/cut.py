"""Cut an FNN's window features out of its ONNX graph (features version 2).

An ``fnn`` exported with its first, fixed layer (``TemporalFeatures``,
:mod:`host.learn.layers`) computes the window statistics in some forty small ONNX
nodes before the scaler and the MLP. :func:`cut_features` removes them: the graph's
input becomes the feature vector itself, which the leg computes in one compiled call
per frame (:mod:`device.pi.models.winfeat`). Nothing is trained again: the scaler and
MLP nodes, their weights and the int8 nodes are kept as they are.

    python -m host.learn.cut models           # every fnn of models/ not cut yet

:func:`cut_folder` cuts ``model.onnx`` and ``model.int8.onnx`` of a model folder,
checks each against the old graph on random windows (the same class, probabilities
within :data:`PROB_TOL`; nothing is written unless every file passes), and records
the new files (SHA-256, sizes), the input (the feature vector) and the ``features``
record in the manifests (the default's and the float one's), so ``host
deploy`` signs them as any other model. ``make models`` runs it before the fuse.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from device.pi.models.artefact import ModelError
from device.pi.models.manifest import has_manifest, read_spec
from device.pi.models.winfeat import FeatureSpec, window_stats
from host.learn.layers import layer_in_graph
from host.learn.tasks import TrainError

__all__ = ["cut_features", "cut_folder", "graph_inputs", "feature_node_types", "PROB_TOL",
           "main"]

#: the cut graph's probabilities may differ from the old one's by this much: the
#: features equal the old nodes' to float32 rounding (their sums run in another order)
PROB_TOL = 1e-4
#: the input of a cut graph
INPUT_NAME = "x"


def graph_inputs(model_spec, X: np.ndarray, where="manifest") -> np.ndarray:
    """What the graph of the model of ``model_spec`` (a ModelSpec) reads for encoded
    windows ``X``: their window features when the spec has a ``features`` record,
    else ``X`` itself."""
    from device.pi.models.winfeat import feature_spec
    spec = feature_spec(model_spec.features, str(where))
    return X if spec is None else window_stats(spec, X)


def feature_node_types() -> frozenset:
    """ONNX operators that only a window-feature layer uses in an fnn graph."""
    return frozenset({"Slice", "Reshape", "ReduceMean", "ReduceSumSquare", "ReduceSum", "Sqrt",
                      "Concat", "Div", "Transpose", "Gather"})


def _windows(spec: FeatureSpec, n: int, seed: int) -> np.ndarray:
    """Random encoded windows: vectors on the 0.25 px grid, IMU rows in range."""
    rng = np.random.default_rng(seed)
    X = np.round(rng.normal(0, 3, (n, spec.n_inputs)) * 4) / 4
    return np.clip(X, -64, 64).astype(np.float32)


def cut_features(model, spec: FeatureSpec, seed: int = 0):
    """``model`` (an onnx.ModelProto whose first layer computes the window features of
    ``spec`` from its input) without that layer: its input ``x`` is the feature
    vector, (N, spec.n_features) float32. The layer's output is found by its numbers
    (the Concat equal to :func:`window_stats` on random windows). TrainError when no
    single tensor is, or when a kept node reads the old input or the layer's inner
    tensors."""
    import onnx
    from onnx import TensorProto, helper


    g = model.graph
    if len(g.input) != 1:
        raise TrainError(f"the graph has {len(g.input)} inputs; an fnn reads one window")
    x_name = g.input[0].name
    X = _windows(spec, 16, seed)
    want = window_stats(spec, X)
    out, inner, kept = layer_in_graph(model, X, want, "the window features", 1e-5)
    reads = {i for n in kept for i in n.input}
    if reads & (inner | {x_name}) or any(o.name in inner for o in g.output):
        raise TrainError("a node after the window features reads the window or one of the "
                         "features' inner tensors")
    nodes = []
    for n in kept:
        m = onnx.NodeProto()
        m.CopyFrom(n)
        m.input[:] = [INPUT_NAME if i == out else i for i in n.input]
        nodes.append(m)
    new = onnx.ModelProto()
    new.CopyFrom(model)
    del new.graph.node[:]
    new.graph.node.extend(nodes)
    del new.graph.input[:]
    new.graph.input.append(helper.make_tensor_value_info(INPUT_NAME, TensorProto.FLOAT,
                                                         [None, spec.n_features]))
    used = {i for n in nodes for i in n.input}
    inits = [i for i in g.initializer if i.name in used]
    del new.graph.initializer[:]
    new.graph.initializer.extend(inits)
    vinfo = [v for v in g.value_info if v.name in used and v.name != out]
    del new.graph.value_info[:]
    new.graph.value_info.extend(vinfo)
    onnx.checker.check_model(new)
    return new


def _spec_of(model_spec, where) -> FeatureSpec:
    params = model_spec.training.get("temporal")
    if not params:
        raise TrainError(f"{where}: the manifest records no window-feature layer to cut")
    return FeatureSpec(params["T"], params["n_pins"], params.get("uses_imu", False),
                       params.get("pin_mask"), params.get("neighbours"), where=str(where))


def _outputs(sess, X) -> tuple[np.ndarray, np.ndarray]:
    names = [o.name for o in sess.get_outputs()]
    got = sess.run(["label", "probabilities"] if "label" in names else names[:2],
                   {sess.get_inputs()[0].name: X})
    return np.asarray(got[0]), np.asarray(got[1])


def cut_folder(folder, seed: int = 0) -> dict:
    """Cut the window features out of the fnn in ``folder`` (see the module doc).
    Returns {file: (bytes before, bytes after)}; {} when it is cut already."""
    import onnx

    from host.learn.onnx_io import FLOAT_NAME, INT8_NAME, replace_graphs, session

    folder = Path(folder)
    mspec, mpath = read_spec(folder)
    if mspec.features is not None:
        return {}
    spec = _spec_of(mspec, mpath)
    if mspec.n_inputs != spec.n_inputs or mspec.input_dims is not None:
        raise TrainError(f"{folder}: input of {mspec.n_inputs} values is not the window of "
                         f"{spec.n_inputs} values its layer reads")
    names = [n for n in (FLOAT_NAME, INT8_NAME) if (folder / n).is_file()]
    X = _windows(spec, 512, seed + 1)
    F = window_stats(spec, X)
    new_bytes = {}
    for name in names:                  # every file is checked before any is written
        old = onnx.load(str(folder / name))
        new = cut_features(old, spec, seed)
        try:
            la, pa = _outputs(session(old), X)
            lb, pb = _outputs(session(new), F)
        except Exception as exc:       # ONNX Runtime's own exception types
            raise TrainError(f"{folder / name}: the cut graph does not run: "
                             + " ".join(str(exc).split())) from None
        if not (np.array_equal(la, lb) and np.allclose(pa, pb, rtol=0, atol=PROB_TOL)):
            raise TrainError(f"{folder / name}: the cut graph gives other outputs (max "
                             f"probability change {np.abs(pa - pb).max():.3g})")
        new_bytes[name] = new.SerializeToString()
    mspec.features = spec.record()
    mspec.n_inputs = spec.n_features
    return replace_graphs(folder, mspec, new_bytes)


def main(argv=None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if len(args) != 1:
        print("usage: python -m host.learn.cut MODELS_FOLDER", file=sys.stderr)
        return 2
    done = {}
    try:
        for folder in sorted(Path(args[0]).iterdir()):
            if not has_manifest(folder):
                continue
            mspec, _ = read_spec(folder)
            if mspec.model != "fnn" or not mspec.training.get("temporal"):
                continue
            done[folder.name] = {k: list(v) for k, v in cut_folder(folder).items()}
    except (ModelError, TrainError, OSError, ValueError) as exc:
        print(f"host.learn.cut: error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(done))
    return 0


if __name__ == "__main__":                      # pragma: no cover
    raise SystemExit(main())
