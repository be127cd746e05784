"""host/learn/layers.py: the MLP's fixed layers (clipped scaler, frame-to-frame changes)
and their ONNX graphs."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays


@st.composite
def training_matrix(draw):
    n = draw(st.integers(3, 12))
    d = draw(st.integers(1, 5))
    scale = draw(st.sampled_from([1e-3, 1.0, 1e3, 1e6]))
    X = draw(arrays(np.float32, (n, d), elements=st.floats(-1, 1, width=32))) * np.float32(scale)
    const = draw(st.lists(st.integers(0, d - 1), max_size=d))
    X[:, const] = np.float32(draw(st.floats(-100, 100, width=32)))   # zero-variance columns
    return X


@given(training_matrix(), arrays(np.float32, 5, elements=st.floats(width=32, allow_nan=False)))
@example(np.array([[0.0], [1e-45], [1e-45]], np.float32), np.zeros(5, np.float32))  # was NaN
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
def test_the_folded_scaler_matches_sklearn_and_stays_finite(X, probe):
    """The MLPs' scaler in the graph (Sub, Mul, Clip) equals sklearn's StandardScaler
    clipped to +-8 standard deviations, zero-variance columns included, and its
    output is finite and bounded for any input without NaN (inf included)."""
    from sklearn.preprocessing import StandardScaler
    from skl2onnx import convert_sklearn
    from skl2onnx.common.data_types import FloatTensorType

    from host.learn.layers import SCALED_CLIP, scaler_class
    from host.learn.onnx_io import session

    sc = scaler_class()().fit(X)
    m = convert_sklearn(sc, initial_types=[("x", FloatTensorType([None, X.shape[1]]))],
                        target_opset=17)
    sess = session(m)
    got = sess.run(None, {"x": X})[0]
    want = np.clip(StandardScaler().fit(X).transform(X.astype(np.float64)), -8.0, 8.0)
    # a spread float32 cannot invert counts as zero variance (host/learn/layers.py)
    flat = 1.0 / StandardScaler().fit(X).scale_.astype(np.float64) > np.finfo(np.float32).max
    want[:, flat] = 0.0
    assert SCALED_CLIP == 8.0
    assert np.allclose(got, sc.transform(X), rtol=1e-5, atol=1e-5)
    assert np.allclose(got, want, rtol=1e-3, atol=1e-3)
    const = np.ptp(X, axis=0) == 0          # every value identical
    assert np.allclose(got[:, const], 0.0, atol=1e-3)
    x = np.resize(probe, X.shape[1])[None].astype(np.float32)
    out = sess.run(None, {"x": x})[0]
    assert np.isfinite(out).all() and (np.abs(out) <= SCALED_CLIP).all()


def test_the_fnn_first_layer_in_onnx_equals_its_numpy_transform():
    from skl2onnx import convert_sklearn
    from skl2onnx.common.data_types import FloatTensorType

    from host.learn.layers import temporal_class
    from host.learn.onnx_io import session

    rng = np.random.default_rng(0)
    for Tn, imu in ((2, False), (3, True), (5, True)):
        M = 7
        X = (rng.normal(0, 3, (50, Tn * M * 2 + (6 * Tn if imu else 0)))).astype(np.float32)
        tf = temporal_class()(T=Tn, n_pins=M, uses_imu=imu).fit(X)
        m = convert_sklearn(tf, initial_types=[("x", FloatTensorType([None, X.shape[1]]))],
                            target_opset=17)
        got = session(m).run(None, {"x": X})[0]
        want = tf.transform(X)
        assert got.shape == want.shape == (50, tf.n_features_out_)
        assert np.allclose(got, want, atol=1e-5)
        # the appended columns hold what they say: e.g. the last frame's mean |v|
        v = X[:, :Tn * M * 2].reshape(50, Tn, M, 2)
        assert np.allclose(want[:, -1], np.hypot(v[:, -1, :, 0], v[:, -1, :, 1]).mean(1),
                           atol=1e-5)


def test_masked_pins_are_ignored_by_the_temporal_layer_and_its_graph():
    from skl2onnx import convert_sklearn
    from skl2onnx.common.data_types import FloatTensorType

    from host.learn.layers import temporal_class
    from host.learn.onnx_io import session

    T, M = 3, 6
    rng = np.random.default_rng(0)
    X = rng.normal(0, 1, (20, T * M * 2 + 6 * T)).astype(np.float32)
    mask = [1, 0, 1, 1, 0, 1]
    tf = temporal_class()(T=T, n_pins=M, uses_imu=True, pin_mask=mask).fit(X)
    m = convert_sklearn(tf, initial_types=[("x", FloatTensorType([None, X.shape[1]]))],
                        target_opset=17)
    sess = session(m)
    got = sess.run(None, {"x": X})[0]
    assert np.allclose(got, tf.transform(X), atol=1e-5)
    X2 = X.copy()
    v = X2[:, :T * M * 2].reshape(20, T, M, 2)
    v[:, :, [1, 4]] = rng.normal(0, 50, (20, T, 2, 2))        # only the masked pins change
    assert np.allclose(sess.run(None, {"x": X2})[0], got, atol=1e-5)
    assert not np.allclose(temporal_class()(T=T, n_pins=M, uses_imu=True).fit(X2)
                           .transform(X2), temporal_class()(T=T, n_pins=M, uses_imu=True)
                           .fit(X).transform(X))


def test_the_roughness_features_see_single_pins_pushed_not_a_uniform_shear_and_match_onnx():
    from skl2onnx import convert_sklearn
    from skl2onnx.common.data_types import FloatTensorType

    from device.pi.vision.neighbours import layout_neighbours
    from host.learn.layers import temporal_class
    from host.learn.onnx_io import session

    T, M = 3, 12
    ang = np.linspace(0, 2 * np.pi, M, endpoint=False)
    lay = np.stack([np.cos(ang), np.sin(ang)], 1) * 50
    nb = layout_neighbours(lay, 2)[0].tolist()
    assert sorted(nb[0]) == [1, M - 1]               # the two pins beside pin 0
    mask = [1] * M
    mask[5] = 0
    tf = temporal_class()(T=T, n_pins=M, pin_mask=mask, neighbours=nb)
    shear = np.tile(np.array([3.0, -2.0], np.float32), (4, T, M, 1))
    poked = shear.copy()
    poked[:, -1, 0] += 2.0                           # one pin pushed in the last frame
    X = np.concatenate([shear, poked]).reshape(8, -1)
    tf.fit(X)
    out = tf.transform(X)
    rough = out[:, -(4 * T - 2):]                    # the roughness columns come last
    assert out.shape[1] == tf.n_features_out_
    assert np.allclose(rough[:4], 0, atol=1e-6)      # a uniform shear is smooth
    assert (rough[4:, T - 1] > 0).all() and np.allclose(rough[4:, :T - 1], 0, atol=1e-6)
    m = convert_sklearn(tf, initial_types=[("x", FloatTensorType([None, X.shape[1]]))],
                        target_opset=17)
    assert np.allclose(session(m).run(None, {"x": X})[0], out, atol=1e-5)
    # a masked pin (5) and pins beside it (4, 6) do not count
    X2 = X.reshape(8, T, M, 2).copy()
    X2[:, :, 5] += 9.0
    assert np.allclose(tf.transform(X2.reshape(8, -1))[:, -(4 * T - 2):], rough, atol=1e-5)


@pytest.mark.parametrize("seed, T, N, K", [(0, 2, 1, 3), (1, 4, 9, 6), (2, 15, 3, 6)])
def test_the_roughness_graph_equals_the_transform_on_random_windows(seed, T, N, K):
    """For random pin vectors, a random layout's neighbours (a pin may list a
    neighbour twice) and a random pin mask, the ONNX graph gives the transform's
    numbers, one window (as on the leg) or a batch, and the roughness columns equal
    a per-pin loop over each pin's neighbours."""
    from skl2onnx import convert_sklearn
    from skl2onnx.common.data_types import FloatTensorType

    from device.pi.vision.neighbours import layout_neighbours
    from host.learn.layers import ROUGH_FLOOR_PX, temporal_class
    from host.learn.onnx_io import session

    rng = np.random.default_rng(seed)
    M = 20
    nb = layout_neighbours(rng.uniform(0, 100, (M, 2)), K)[0]
    nb[0, -1] = nb[0, 0]                                 # a neighbour listed twice
    mask = (rng.random(M) > 0.2).astype(int)
    mask[nb[1]] = mask[1] = 1                            # pin 1 and its neighbours are used
    X = rng.normal(0, 3, (N, T * M * 2)).astype(np.float32)
    tf = temporal_class()(T=T, n_pins=M, pin_mask=mask.tolist(),
                          neighbours=nb.tolist()).fit(X)
    want = tf.transform(X)
    m = convert_sklearn(tf, initial_types=[("x", FloatTensorType([None, X.shape[1]]))],
                        target_opset=17)
    sess = session(m)
    assert np.allclose(sess.run(None, {"x": X})[0], want, rtol=1e-5, atol=1e-5)
    assert np.allclose(sess.run(None, {"x": X[-1:]})[0], want[-1:], rtol=1e-5, atol=1e-5)
    # the roughness columns, from a loop over the pins
    v = X.reshape(N, T, M, 2) * mask[None, None, :, None]
    ok = [i for i in range(M) if mask[i] and mask[nb[i]].all()]
    assert 1 in ok
    r = np.stack([v[:, :, i] - v[:, :, nb[i]].mean(axis=2) for i in ok], axis=2)
    rm = np.linalg.norm(r, axis=3).mean(axis=2)
    drm = np.linalg.norm(r[:, 1:] - r[:, :-1], axis=3).mean(axis=2)
    den = np.linalg.norm(v, axis=3).mean(axis=2) + ROUGH_FLOOR_PX
    rough = want[:, -(4 * T - 2):]
    assert np.allclose(rough, np.concatenate([rm, rm / den, drm, drm / den[:, 1:]], axis=1),
                       rtol=1e-4, atol=1e-5)


def test_replacing_the_temporal_graph_keeps_the_model_numbers_and_needs_its_parameters():
    """A pipeline model (temporal layer with roughness, clipped scaler) gives the same
    outputs with its first layer's graph replaced, and the rest of the graph is kept;
    parameters that do not describe the model's layer are refused."""
    from sklearn.pipeline import make_pipeline
    from skl2onnx import convert_sklearn
    from skl2onnx.common.data_types import FloatTensorType

    from host.learn.layers import replace_temporal_graph, scaler_class, temporal_class
    from host.learn.onnx_io import session
    from host.learn.tasks import TrainError

    T, M = 3, 8
    rng = np.random.default_rng(3)
    nb = [[(i + 1) % M, (i - 1) % M] for i in range(M)]
    params = {"T": T, "n_pins": M, "pin_mask": [1] * 7 + [0], "neighbours": nb}
    X = rng.normal(0, 3, (40, T * M * 2)).astype(np.float32)
    pipe = make_pipeline(temporal_class()(**params), scaler_class()()).fit(X)
    m = convert_sklearn(pipe, initial_types=[("x", FloatTensorType([None, X.shape[1]]))],
                        target_opset=17)
    new = replace_temporal_graph(m, params)
    got = session(new).run(None, {"x": X})[0]
    assert np.allclose(got, session(m).run(None, {"x": X})[0], atol=1e-5)
    assert np.allclose(got, pipe.transform(X), atol=1e-4)
    assert [n.op_type for n in new.graph.node][-3:] == ["Sub", "Mul", "Clip"]  # the scaler
    gathers = [n for n in new.graph.node if n.op_type == "Gather"]
    assert len(gathers) == 1 and gathers[0].attribute[0].i == 0   # whole pin rows
    with pytest.raises(TrainError):
        replace_temporal_graph(m, dict(params, neighbours=[[(i + 2) % M] * 2
                                                           for i in range(M)]))
