"""host/learn/quantise.py: static int8 quantisation and its check against float."""
from __future__ import annotations

import numpy as np
import pytest

import host.learn.quantise as hq
from host.learn.inputs import model_inputs
from host.learn.quantise import compare_int8, quantise_model
from host.learn.tasks import QuantisationError
from host.learn.train import train_model


def test_int8_check_fails_loudly_and_keeps_nothing(small_model, tmp_path, monkeypatch):
    res, out, ws = small_model
    X = model_inputs(ws, "vectors", True)
    y = np.array([sorted(set(ws.labels)).index(x) for x in ws.labels])
    fbytes = (out / "model.onnx").read_bytes()
    rep = quantise_model(fbytes, X, tmp_path / "q.onnx", check_inputs=X, check_targets=y)
    assert rep["passed"] and rep["agreement"] >= 0.99 and (tmp_path / "q.onnx").exists()
    # corrupt the int8 weights: the comparison catches it
    import onnx
    from onnx import numpy_helper

    q = onnx.load(str(tmp_path / "q.onnx"))
    last = [n for n in q.graph.node if n.op_type == "MatMul"][-1]       # the output layer
    dq = next(n for n in q.graph.node if last.input[1] in n.output)
    init = next(i for i in q.graph.initializer if i.name == dq.input[0])
    a = numpy_helper.to_array(init)
    assert a.dtype == np.int8                                        # its int8 weights
    init.CopyFrom(numpy_helper.from_array((-a.astype(np.int16)).clip(-127, 127)
                                          .astype(np.int8), init.name))
    bad = compare_int8(fbytes, q.SerializeToString(), X, y)
    assert not bad["passed"] and bad["agreement"] < 0.99 and bad["accuracy_int8"] < 0.9
    # force the disagreement inside quantise_model: it raises and keeps no file
    real = hq.compare_int8

    def disagree(*a, **kw):
        r = real(*a, **kw)
        return dict(r, agreement=0.9, passed=False)

    monkeypatch.setattr(hq, "compare_int8", disagree)
    with pytest.raises(QuantisationError, match=r"q2\.onnx agrees with the float model on "
                                                r"90\.00% of \d+ held-out windows .*below the "
                                                r"required 99\.00%") as err:
        quantise_model(fbytes, X, tmp_path / "q2.onnx", check_inputs=X)
    assert err.value.kind == "classifier" and err.value.agreement == 0.9
    assert err.value.required == 0.99 and err.value.path == str(tmp_path / "q2.onnx")
    assert not (tmp_path / "q2.onnx").exists()
    # and train --quantise fails as a whole, writing nothing
    with pytest.raises(QuantisationError, match="int8 check failed"):
        train_model("surface", "fnn", ws, quantise=True, out_dir=tmp_path / "m",
                    progress=False, hidden=(8, 4), epochs=20)
    assert not (tmp_path / "m").exists()
