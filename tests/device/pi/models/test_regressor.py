"""The Pi's Regressor: an untracked pin (input exactly 0) reaches the graph as 0,
even when the training range of that input excludes 0; a NaN/inf input or one no
window encoding gives is cleaned, clipped and raises the fault."""
from __future__ import annotations

import numpy as np
import pytest

from device.pi.models.regressor import Regressor
from host.learn.regression import export_regressor


def test_zero_input_is_not_clipped_into_the_training_range(tmp_path):
    rng = np.random.default_rng(0)
    X = rng.uniform(2.0, 4.0, (50, 4)).astype(np.float32)    # input 0 never below 2
    y = 100.0 * X[:, 0] + X[:, 1]
    out, pipe = export_regressor(X, y, tmp_path / "m", kind="pressure", alpha=0.01)
    reg = Regressor.load(out)
    x = X[0].copy()
    x[0] = 0.0                                   # pin lost: the runtime gives 0
    want = float(pipe.predict(x[None])[0])
    clipped = float(pipe.predict(np.r_[X[:, 0].min(), x[1:]][None])[0])
    assert abs(want - clipped) > 50              # clipping would move it far
    assert reg.predict_one(x) == pytest.approx(want, abs=1e-2)
    x[0] = 1e6                                   # a non-zero extreme is still clipped
    assert reg.predict_one(x) == pytest.approx(clipped + 100.0 * (X[:, 0].max()
                                                                  - X[:, 0].min()), abs=0.5)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf, -1e30, 1e39, 2001.0])
def test_bad_input_gives_a_finite_output_and_the_fault(tmp_path, bad):
    rng = np.random.default_rng(2)
    X = rng.uniform(-3.0, 3.0, (40, 4)).astype(np.float32)
    y = 2.0 * X[:, 0] - X[:, 2]
    out, pipe = export_regressor(X, y, tmp_path / "m", kind="pressure", alpha=0.01)
    reg = Regressor.load(out)
    good = reg.predict_one(X[0])
    assert not reg.fault and good == pytest.approx(float(pipe.predict(X[:1])[0]), abs=1e-2)
    x = X[0].astype(np.float64)
    x[1] = bad
    got = reg.predict_one(x)
    assert reg.fault and np.isfinite(got)
    assert abs(got) <= 4 * (abs(y).max() + 1)          # clipped into the training range
    reg.predict_one(X[0])
    assert not reg.fault                                # a clean input clears it
    x[1] = 63.5                                         # inside every encoding: no fault
    reg.predict_one(x)
    assert not reg.fault
