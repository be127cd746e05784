"""A regressor (pressure or depth from all pin vectors) run through ONNX Runtime.

The model reads the ``vectors`` window encoding, in which a lost (untracked) pin is
exactly (0, 0): :mod:`host.learn.pressure` models fill those pins from the tracked
ones inside their graph, so a 0 must reach the graph as 0."""
from __future__ import annotations

import math

import numpy as np

from device.pi.models.artefact import BoundRun, ModelError, load_model
from device.pi.models.window import ENCODED_BOUND
from device.pi.numerics import finite


class Regressor:
    """Loaded once; :meth:`predict_one` is the per-frame call.

    Inputs are cleaned (NaN/inf -> 0) and clipped to the range seen in
    training (the spec's ``params.input_clip``), so an extreme frame
    cannot push the output to infinity; an input of exactly 0 (an untracked pin)
    is left at 0 even when the training range excludes it, so it still reads as
    untracked. :attr:`fault` is set for the call when an input was NaN/inf or larger
    in size than any window encoding gives (``ENCODED_BOUND``: it was cleaned and
    clipped, the output is still finite), and when the output is non-finite (the
    training mean is given instead).
    """

    def __init__(self, model, kind: str = "pressure"):
        self.model = model
        spec = model.spec
        p = spec.params                 # RegressorParams, typed by the one parse
        self.n_features = spec.n_inputs
        self._lo = self._hi = None
        if p.input_clip is not None:
            self._lo = np.asarray(p.input_clip[0], np.float32)
            self._hi = np.asarray(p.input_clip[1], np.float32)
        self.fallback = float(p.target_mean)
        #: the window the model reads: T frames, encoded as ``input_layout``
        self.T = spec.T
        self.input_layout = spec.input_layout
        self.uses_imu = spec.uses_imu
        self._x = np.zeros((1, self.n_features), np.float32)
        sess = model.session
        self._runner = BoundRun(sess, model.input_name, self._x, sess.get_outputs()[0].name)
        self.fault = False

    @classmethod
    def load(cls, path, kind: str = "pressure") -> "Regressor":
        return cls(load_model(path, expect_kind=kind), kind)

    def predict_window(self, window) -> float | None:
        """The prediction for a :class:`~device.pi.models.window.RollingWindow` of
        this model's ``T``, encoded as in training; None until the window is full."""
        self._check_T(window)
        if not window.full:
            return None
        return self.predict_one(window.encode(self.input_layout, with_imu=self.uses_imu))

    def _check_T(self, window) -> None:
        if window.T != self.T:
            raise ModelError(f"{self.model.path}: reads windows of T={self.T}, "
                             f"got T={window.T}")

    def predict_one(self, features: np.ndarray) -> float:
        bad_input = self.prepare(features, self._x)
        return self.finish(self._runner(), bad_input)

    def prepare_window(self, window, x: np.ndarray) -> bool:
        """:meth:`prepare` for a full window of this model's T (a fused graph's
        input, :mod:`device.pi.models.fused`)."""
        self._check_T(window)
        return self.prepare(window.encode(self.input_layout, with_imu=self.uses_imu), x)

    def prepare(self, features: np.ndarray, x: np.ndarray) -> bool:
        """Write the cleaned, clipped input for ``features`` into ``x`` (1, D); True
        when an input was NaN/inf or beyond any encoding (the fault)."""
        f = np.asarray(features)
        if f.dtype != np.float32:
            with np.errstate(over="ignore", invalid="ignore"):   # beyond float32: inf
                f = f.astype(np.float32)
        f = f.reshape(-1)
        if f.size != self.n_features:
            raise ModelError(f"{self.model.path}: expects {self.n_features} features, "
                             f"got {f.size}")
        clean = bool(np.isfinite(f).all())
        x[0] = f if clean else finite(f)
        # NaN/inf became 0 (finite); beyond ENCODED_BOUND no encoder gives it
        bad_input = not (clean and float(np.abs(x).max()) <= ENCODED_BOUND)
        if self._lo is not None:
            zero = x == 0
            np.clip(x, self._lo, self._hi, out=x)
            x[zero] = 0
        return bad_input

    def finish(self, out, bad_input: bool) -> float:
        """The prediction from the model's raw output, and :attr:`fault` set: the
        training mean for a non-finite output."""
        y = float(np.asarray(out).reshape(-1)[0])
        bad_output = not math.isfinite(y)
        self.fault = bad_input or bad_output
        return self.fallback if bad_output else y
