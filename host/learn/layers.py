"""The fixed layers in front of the MLP, each with its ONNX converter:
:class:`TemporalFeatures` (frame-to-frame changes of a ``vectors`` window) and
:class:`ClippedScaler` (standard scaling clipped to +-8 sd).

The classes are defined on first use by :func:`temporal_class` and
:func:`scaler_class` (scikit-learn and skl2onnx are host-only, optional imports).
:func:`replace_temporal_graph` puts the current graph of the temporal layer into a
model already exported, without training again.
"""
from __future__ import annotations

import numpy as np

from host.learn.tasks import TrainError

__all__ = ["SCALED_CLIP", "ROUGH_FLOOR_PX", "temporal_class", "scaler_class",
           "replace_temporal_graph"]


#: added to the mean |v| (px) that the roughness is divided by, so a frame
#: without a press does not divide by about zero
ROUGH_FLOOR_PX = 0.5


def defined_once(name: str, define):
    """The module-level class ``name``, made by ``define()`` on first use: the
    layers need sklearn, which is host-only, and pickling needs one class object."""
    if name not in globals():
        globals()[name] = define()
    return globals()[name]


def temporal_class():
    """:class:`TemporalFeatures`, defined on first use."""
    return defined_once("TemporalFeatures", _define_temporal)


def _define_temporal():
    from sklearn.base import BaseEstimator, TransformerMixin

    class TemporalFeatures(TransformerMixin, BaseEstimator):
        """The FNN's first, fixed layer over a ``vectors`` window input: it keeps
        the input and appends, from the T frames of M pin vectors,

        * the per-pin frame-to-frame changes, (T-1) x M x 2;
        * the average vector of each frame, T x 2, and its changes, (T-1) x 2;
        * the length of each average-vector change, T-1 (how far the patch moved);
        * the mean length of the per-pin changes, T-1 (how much the pins shook);
        * the mean pin displacement |v| of each frame, T (the pressure).

        ``pin_mask`` (M zeros and ones, optional): pins with 0 are read as zero
        everywhere, in the graph too, so a pin that a training recording always
        loses (glare, a worn pin) cannot become a cue for that recording.

        ``neighbours`` (M lists of K layout pin indices, optional, from
        :func:`device.pi.vision.neighbours.layout_neighbours`) adds the spatial roughness of the displacement
        field: for each pin, its vector minus the mean vector of its K neighbours
        (a smooth shear or press leaves this near zero, studs that push single
        pins do not). Over the pins whose neighbours are all used it appends

        * the mean roughness of each frame, T, and the same over
          (mean |v| + ``ROUGH_FLOOR_PX``), T (roughness for the press depth);
        * the mean length of each frame-to-frame change of the roughness, T-1,
          and the same over the later frame's (mean |v| + ``ROUGH_FLOOR_PX``), T-1.

        Texture shake, slip and a wet floor show in these changes, which are small
        next to the vectors themselves; given explicitly, the MLP finds them from
        few trials. No weights: in ONNX it is Slice / Sub / ReduceMean /
        ReduceSumSquare / Sqrt / Concat, and for the roughness a Transpose to pins
        first and a Gather of whole pin rows (:func:`_temporal_to_onnx`), left in
        float by the int8 quantiser.
        """

        def __init__(self, T: int = 3, n_pins: int = 133, uses_imu: bool = False,
                     pin_mask=None, neighbours=None):
            self.T = T
            self.n_pins = n_pins
            self.uses_imu = uses_imu
            self.pin_mask = pin_mask
            self.neighbours = neighbours

        def _rough(self):
            """use (M,) float32: 1 / (pins counted) for each pin whose neighbours are
            all used, else 0; None without ``neighbours``."""
            if self.neighbours is None:
                return None
            nb = np.asarray(self.neighbours, np.int64)
            M = self.n_pins
            if nb.ndim != 2 or nb.shape[0] != M or nb.shape[1] < 1 or nb.min() < 0 \
                    or nb.max() >= M:
                raise TrainError(f"neighbours must be {M} rows of pin indices in 0..{M - 1}, "
                                 f"got shape {nb.shape}")
            m = self._mask()
            ok = np.ones(M, bool) if m is None else m > 0
            ok = ok & ok[nb].all(axis=1)
            if not ok.any():
                raise TrainError("neighbours: no pin has all its neighbours in use")
            return (ok / ok.sum()).astype(np.float32)

        def _mask(self):
            """(M,) float32 of 1 (pin used) and 0 (pin ignored), or None."""
            if self.pin_mask is None:
                return None
            m = np.asarray(self.pin_mask, np.float32).reshape(-1)
            if m.shape != (self.n_pins,) or not np.isin(m, (0.0, 1.0)).all():
                raise TrainError(f"pin_mask must hold {self.n_pins} zeros and ones, got "
                                 f"shape {m.shape}")
            return m

        def _n_in(self) -> int:
            return self.T * self.n_pins * 2 + (6 * self.T if self.uses_imu else 0)

        def fit(self, X, y=None):
            X = np.asarray(X)
            if X.ndim != 2 or X.shape[1] != self._n_in():
                raise TrainError(f"temporal features: expected (N, {self._n_in()}) inputs for "
                                 f"T={self.T}, {self.n_pins} pins, imu={self.uses_imu}, got "
                                 f"{X.shape}")
            T, M = self.T, self.n_pins
            self._mask()
            rough = self._rough() is not None
            self.n_features_in_ = X.shape[1]
            self.n_features_out_ = (X.shape[1] + (T - 1) * M * 2 + 2 * T + 2 * (T - 1)
                                    + 2 * (T - 1) + T + (4 * T - 2 if rough else 0))
            return self

        def transform(self, X):
            X = np.asarray(X, np.float32)
            T, M, N = self.T, self.n_pins, X.shape[0]
            v = X[:, :T * M * 2].reshape(N, T, M, 2)
            mask = self._mask()
            if mask is not None:      # ignored pins read as zero everywhere below
                v = v * mask[None, None, :, None]
                X = np.concatenate([v.reshape(N, -1), X[:, T * M * 2:]], axis=1)
            avg = v.mean(axis=2, dtype=np.float32)
            parts = [X]
            dv = v[:, 1:] - v[:, :-1]
            davg = avg[:, 1:] - avg[:, :-1]
            mag = np.sqrt((v * v).sum(axis=3)).mean(axis=2)
            parts += [dv.reshape(N, -1), avg.reshape(N, -1), davg.reshape(N, -1),
                      np.sqrt((davg * davg).sum(axis=2)),
                      np.sqrt((dv * dv).sum(axis=3)).mean(axis=2), mag]
            use = self._rough()
            if use is not None:
                # each pin minus the mean of its neighbours, as the graph gathers them
                nb = np.asarray(self.neighbours, np.int64)
                r = v - sum(v[:, :, nb[:, k]] for k in range(nb.shape[1])) / nb.shape[1]
                dr = r[:, 1:] - r[:, :-1]
                rm = (np.sqrt((r * r).sum(axis=3)) * use).sum(axis=2)
                drm = (np.sqrt((dr * dr).sum(axis=3)) * use).sum(axis=2)
                den = mag + np.float32(ROUGH_FLOOR_PX)
                parts += [rm, rm / den, drm, drm / den[:, 1:]]
            return np.concatenate(parts, axis=1).astype(np.float32)

    _register_temporal(TemporalFeatures)
    return TemporalFeatures


#: standardised MLP inputs are clipped to this many standard deviations
SCALED_CLIP = 8.0


def scaler_class():
    """:class:`ClippedScaler`, defined on first use."""
    return defined_once("ClippedScaler", _define_scaler)


def _define_scaler():
    from sklearn.base import BaseEstimator, TransformerMixin
    from sklearn.preprocessing import StandardScaler

    class ClippedScaler(TransformerMixin, BaseEstimator):
        """Standard scaling (sklearn's: a zero-variance feature keeps scale 1), then
        every value clipped to +-``clip`` standard deviations. The clip bounds what
        an extreme window can do to the MLP and keeps one outlying feature from
        stretching the int8 range of the first layer's input for all the others.
        In ONNX: Sub, Mul, Clip (standard ops)."""

        def __init__(self, clip: float = SCALED_CLIP):
            self.clip = clip

        def fit(self, X, y=None):
            sc = StandardScaler().fit(X)
            self.mean_ = sc.mean_.astype(np.float32)
            # a spread too small for float32 to invert (a standard deviation below
            # about 3e-39) counts as zero variance: scale 1, like sklearn's constant
            # features, so the feature maps to ~0 instead of inf * 0 = NaN
            inv = 1.0 / np.asarray(sc.scale_, np.float64)
            flat = ~(inv <= np.finfo(np.float32).max)
            self.scale_ = np.where(flat, 1.0, sc.scale_)
            self.inv_scale_ = np.where(flat, 1.0, inv).astype(np.float32)
            self.n_features_in_ = sc.n_features_in_
            return self

        def transform(self, X):
            z = (np.asarray(X, np.float32) - self.mean_) * self.inv_scale_
            return np.clip(z, -self.clip, self.clip).astype(np.float32)

    from skl2onnx import update_registered_converter
    from skl2onnx.common.data_types import FloatTensorType

    def shape(operator):
        operator.outputs[0].type = FloatTensorType([None, operator.raw_operator.n_features_in_])

    def convert(scope, operator, container):
        op = operator.raw_operator
        g = OnnxGraph(scope, container)
        init, node = g.floats, g.node
        D = int(op.n_features_in_)
        z = node("Mul", [node("Sub", [operator.inputs[0].full_name, init(op.mean_, [D])]),
                         init(op.inv_scale_, [D])])
        node("Clip", [z, init([-op.clip], []), init([op.clip], [])],
             operator.outputs[0].full_name)

    update_registered_converter(ClippedScaler, "TacfootClippedScaler", shape, convert)
    return ClippedScaler


def _onnx_init(scope, container, values, dims, dtype: str = "float") -> str:
    """An initializer (float32 or int64) named by ``scope``; returns its name."""
    from onnx import TensorProto
    name = scope.get_unique_variable_name("c")
    if dtype == "int64":
        container.add_initializer(name, TensorProto.INT64, dims,
                                  np.asarray(values, np.int64).ravel().tolist())
    else:
        container.add_initializer(name, TensorProto.FLOAT, dims,
                                  np.asarray(values, np.float32).ravel().tolist())
    return name


def _onnx_node(scope, container, op_type, inputs, out=None, **attrs) -> str:
    """A node of ``op_type`` whose output is ``out`` (or a fresh name); returns it."""
    out = out or scope.get_unique_variable_name(op_type.lower())
    container.add_node(op_type, inputs, out, name=scope.get_unique_operator_name(op_type),
                       **attrs)
    return out


class OnnxGraph:
    """The one way a converter here adds to an ONNX graph: int64 vectors, float
    constants and nodes, each named by the converter's ``scope``."""

    def __init__(self, scope, container):
        self.scope, self.container = scope, container

    def ints(self, values) -> str:
        """An int64 vector (indices, axes, shapes)."""
        return _onnx_init(self.scope, self.container, values, [len(values)], "int64")

    def floats(self, values, dims) -> str:
        return _onnx_init(self.scope, self.container, values, dims)

    def node(self, op_type, inputs, out=None, **attrs) -> str:
        """A node whose output is ``out`` (or a fresh name); returns the name."""
        return _onnx_node(self.scope, self.container, op_type, inputs, out, **attrs)


def _register_temporal(cls) -> None:
    from skl2onnx import update_registered_converter
    from skl2onnx.common.data_types import FloatTensorType

    def shape(operator):
        operator.outputs[0].type = FloatTensorType([None, operator.raw_operator.n_features_out_])

    update_registered_converter(cls, "TacfootTemporalFeatures", shape, _temporal_to_onnx)


def _temporal_to_onnx(scope, operator, container):
    """ONNX for :class:`TemporalFeatures` (the same numbers as its transform)."""
    op = operator.raw_operator
    T, M = int(op.T), int(op.n_pins)

    g = OnnxGraph(scope, container)
    const, fconst, node = g.ints, g.floats, g.node

    def frames(a, lo, hi):          # a[:, lo:hi] along axis 1
        return node("Slice", [a, const([lo]), const([hi]), const([1])])

    def flat(a, width):
        return node("Reshape", [a, const([-1, width])])

    x = operator.inputs[0].full_name
    v = node("Reshape", [node("Slice", [x, const([0]), const([T * M * 2]), const([1])]),
                         const([-1, T, M, 2])])
    mask = op._mask()
    if mask is not None:                 # ignored pins read as zero
        v = node("Mul", [v, fconst(np.repeat(mask, 2), [1, 1, M, 2])])
        rest = node("Slice", [x, const([T * M * 2]), const([op.n_features_in_]), const([1])])
        x = node("Concat", [flat(v, T * M * 2), rest], axis=1)
    avg = node("ReduceMean", [v], axes=[2], keepdims=0)                       # (N, T, 2)
    dv = node("Sub", [frames(v, 1, T), frames(v, 0, T - 1)])                  # (N, T-1, M, 2)
    davg = node("Sub", [frames(avg, 1, T), frames(avg, 0, T - 1)])            # (N, T-1, 2)
    mag = node("ReduceMean", [node("Sqrt", [node("ReduceSumSquare", [v], axes=[3],
                                                 keepdims=0)])], axes=[2], keepdims=0)
    parts = [x, flat(dv, (T - 1) * M * 2), flat(avg, 2 * T), flat(davg, 2 * (T - 1)),
             node("Sqrt", [node("ReduceSumSquare", [davg], axes=[2], keepdims=0)]),
             node("ReduceMean", [node("Sqrt", [node("ReduceSumSquare", [dv], axes=[3],
                                                    keepdims=0)])], axes=[2], keepdims=0),
             mag]
    use = op._rough()
    if use is not None:
        nb = np.asarray(op.neighbours, np.int64)
        nbn = _onnx_init(scope, container, nb, list(nb.shape), "int64")   # a matrix
        # pins first, so the Gather copies whole rows of N x T x 2 values (a Gather
        # along the last axis copies them one by one); a Gather and a mean, not a
        # MatMul, so the int8 quantiser leaves it in float
        vm = node("Transpose", [v], perm=[2, 0, 1, 3])                         # (M, N, T, 2)
        nbmean = node("ReduceMean", [node("Gather", [vm, nbn], axis=0)], axes=[1],
                      keepdims=0)                                              # (M, N, T, 2)
        r = node("Sub", [vm, nbmean])

        def pins_frames(a, lo, hi):  # a[:, :, lo:hi]
            return node("Slice", [a, const([lo]), const([hi]), const([2])])

        dr = node("Sub", [pins_frames(r, 1, T), pins_frames(r, 0, T - 1)])
        u = fconst(use, [M, 1, 1])

        def pooled(a):              # sum over pins of use * |a|, (N, frames)
            n = node("Sqrt", [node("ReduceSumSquare", [a], axes=[3], keepdims=0)])
            return node("ReduceSum", [node("Mul", [n, u]), const([0])], keepdims=0)

        rm, drm = pooled(r), pooled(dr)
        den = node("Add", [mag, fconst([ROUGH_FLOOR_PX], [])])
        parts += [rm, node("Div", [rm, den]), drm, node("Div", [drm, frames(den, 1, T)])]
    container.add_node("Concat", parts, operator.outputs[0].full_name, axis=1,
                       name=scope.get_unique_operator_name("Concat"))



def layer_in_graph(model, X: np.ndarray, want: np.ndarray, what: str, tol: float):
    """Where a layer's output is in ``model`` (an onnx.ModelProto), found by its
    numbers: the one Concat whose output, on input ``X``, equals ``want`` within
    ``tol``. Returns (its tensor name, the inner tensors of the nodes that compute
    it, the nodes that do not). TrainError naming ``what`` when the model cannot be
    run or no single Concat matches."""
    import onnx
    from onnx import helper

    from host.learn.onnx_io import session

    g = model.graph
    probe = onnx.ModelProto()
    probe.CopyFrom(model)
    cands = [n.output[0] for n in g.node if n.op_type == "Concat"]
    del probe.graph.output[:]
    # outputs of any type (a shape Concat is int64): ONNX Runtime infers them
    probe.graph.output.extend(helper.make_empty_tensor_value_info(c) for c in cands)
    try:
        outs = session(probe).run(cands, {g.input[0].name: X})
    except Exception as exc:            # ONNX Runtime's own exception types
        raise TrainError(f"the model cannot be probed for {what}: "
                         + " ".join(str(exc).split())) from None
    hits = [c for c, o in zip(cands, outs) if o.shape == want.shape
            and np.allclose(o, want, rtol=tol, atol=tol)]
    if len(hits) != 1:
        raise TrainError(f"no single tensor of the model equals {what} ({len(hits)} do)")
    out = hits[0]
    made = {o: i for i, n in enumerate(g.node) for o in n.output}
    old, todo = set(), [out]
    while todo:                          # the nodes the layer's output is computed by
        i = made.get(todo.pop())
        if i is not None and i not in old:
            old.add(i)
            todo += list(g.node[i].input)
    inner = {o for i in old for o in g.node[i].output} - {out}
    kept = [n for i, n in enumerate(g.node) if i not in old]
    return out, inner, kept


def replace_temporal_graph(model, params: dict, seed: int = 0):
    """``model`` (an onnx.ModelProto whose first layer is a :class:`TemporalFeatures`
    with ``params``, e.g. a manifest's ``training.temporal``) with that layer's nodes
    replaced by the graph :func:`_temporal_to_onnx` writes now. The rest (scaler,
    MLP, int8 nodes) is kept as it is. The layer's output is found by its numbers:
    the Concat whose output equals the transform on random windows. TrainError when
    none does, or when a later node reads one of the layer's inner tensors."""
    import onnx
    from skl2onnx import convert_sklearn
    from skl2onnx.common.data_types import FloatTensorType

    tf = temporal_class()(**params)
    n_in = tf._n_in()
    X = np.random.default_rng(seed).normal(0, 3, (8, n_in)).astype(np.float32)
    want = tf.fit(X).transform(X)
    g = model.graph
    x_name = g.input[0].name
    out, inner, kept = layer_in_graph(model, X, want, "the temporal layer's output", 1e-4)
    if any(i in inner for n in kept for i in n.input) or \
            any(o.name in inner for o in g.output):
        raise TrainError("a node after the temporal layer reads one of its inner tensors")
    layer = convert_sklearn(tf, initial_types=[(x_name, FloatTensorType([None, n_in]))],
                            target_opset={"": next(o.version for o in model.opset_import
                                                   if o.domain in ("", "ai.onnx"))})
    lg = layer.graph
    names = {t for n in g.node for t in (*n.input, *n.output, n.name)}
    names |= {i.name for i in g.initializer}
    k = 0
    while any(t.startswith(f"temporal{k}_") for t in names):
        k += 1
    pre = f"temporal{k}_"                 # no name of the model starts with it
    rename = {i.name: pre + i.name for i in lg.initializer}
    rename.update({o: pre + o for n in lg.node for o in n.output})
    rename[lg.output[0].name] = out
    nodes = []
    for n in lg.node:
        m = onnx.NodeProto()
        m.CopyFrom(n)
        m.name = pre + n.name
        m.input[:] = [rename.get(i, i) for i in n.input]
        m.output[:] = [rename[o] for o in n.output]
        nodes.append(m)
    inits = []
    for i in lg.initializer:
        t = onnx.TensorProto()
        t.CopyFrom(i)
        t.name = rename[i.name]
        inits.append(t)
    new = onnx.ModelProto()
    new.CopyFrom(model)
    del new.graph.node[:]
    new.graph.node.extend(nodes + kept)
    used = {i for n in kept for i in n.input}
    keep_inits = [i for i in g.initializer if i.name in used]
    del new.graph.initializer[:]
    new.graph.initializer.extend(keep_inits + inits)
    del new.graph.value_info[:]
    onnx.checker.check_model(new)
    return new
