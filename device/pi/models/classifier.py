"""The Pi-side classifier: a surface, texture or slip model run through ONNX Runtime.

A model folder holds its manifest (:mod:`device.pi.models.manifest`) and one or two
ONNX files (float, and int8 when it was quantised; the manifest's ``onnx`` names the one loaded by default). The
manifest says which classes the model outputs, how many frames ``T`` it sees, its
``input_layout`` (``vectors``, ``grids`` or ``frames``, see :mod:`device.pi.models.window`)
and whether it uses the IMU, so the caller builds its input with the same encoder as
training did::

    clf = Classifier.load("models/surface")
    x = window.encode(clf.input_layout, with_imu=clf.uses_imu)   # a RollingWindow
    class_id, probs = clf.predict(x)
    clf.classes[class_id], probs[class_id]

:meth:`Classifier.predict` is finite for any input: NaN and inf are cleaned before the
model runs, and the output is cleaned after (probabilities clipped to 0..1 and
renormalised, or logits through the stable :func:`device.pi.numerics.softmax` /
:func:`device.pi.numerics.sigmoid`). A model
that still gives nothing usable yields the uniform distribution and sets
:attr:`Classifier.fault`. Bad artefacts are refused at load time by
:func:`device.pi.models.artefact.load_model` with a message that names the file, and
so is a manifest whose ``classes`` repeat a name or do not match the size of the
model's output (one value per class).

A rule model (``"model": "rule"`` in the manifest, no ONNX file) loads as a
:class:`device.pi.models.rules.RuleClassifier`, which has the same ``predict``.
"""
from __future__ import annotations

import math

import numpy as np

from device.pi.models.artefact import BoundRun, ModelError, load_model, model_file
from device.pi.models.manifest import read_spec
from device.pi.models.rules import RuleClassifier
from device.pi.models.winfeat import WindowFeatures, feature_spec, window_stats
from device.pi.numerics import finite, sigmoid, softmax

#: tasks a classifier serves
CLASS_TASKS = ("surface", "texture", "slip")
#: no input value beyond this reaches a model
INPUT_CLIP = 1.0e6


# ----------------------------------------------------------------------------
# Numerics
# ----------------------------------------------------------------------------

def _usual_scaled(p: np.ndarray) -> np.ndarray | None:
    """The usual model output, a non-empty float64 row in 0..1 (so finite) and not all
    0, divided by its sum (the same sum and division as :func:`clean_probabilities`'
    general case); None for any other row (NaN included)."""
    if p.min() >= 0.0 and p.max() <= 1.0:              # False for a NaN
        s = p.sum()
        if s > 0:
            return p / s
    return None


def clean_probabilities(p, n_classes: int | None = None) -> tuple[np.ndarray, bool]:
    """(probabilities, fault): NaN -> 0, clipped to 0..1, renormalised to sum 1. A
    row with nothing left (all zero) becomes uniform and sets the fault flag."""
    p = np.asarray(p, dtype=np.float64)
    if p.ndim == 1 and p.size and (n_classes is None or p.size == n_classes):
        q = _usual_scaled(p)
        if q is not None:
            return q, False
    squeeze = p.ndim == 1
    p = np.atleast_2d(p).copy()
    if n_classes is not None and p.shape[1] != n_classes:
        raise ValueError(f"probabilities have {p.shape[1]} columns, expected {n_classes}")
    p = np.clip(finite(p, 0.0, 1.0, 0.0, dtype=np.float64), 0.0, 1.0)
    s = p.sum(axis=1, keepdims=True)
    bad = ~(s > 0)
    p = np.where(bad, 1.0 / max(p.shape[1], 1), p / np.where(bad, 1.0, s))
    fault = bool(bad.any())
    return (p[0] if squeeze else p), fault


# ----------------------------------------------------------------------------
# The classifier
# ----------------------------------------------------------------------------

class Classifier:
    """A loaded classifier; :meth:`predict` is the per-decision call.

    Parameters are read from the model's spec (``model.spec``): ``classes``, ``T``, ``input_layout``,
    ``uses_imu``, ``output_kind`` and ``output`` (the name of the output that holds
    the probabilities or logits; default ``probabilities``, else the last output).
    """

    def __init__(self, model):
        self.model = model
        spec = model.spec               # checked as a classifier's by the one parse
        where = str(model.source)
        self.classes = list(spec.classes)
        self.T = spec.T
        self.input_layout = spec.input_layout
        self.uses_imu = spec.uses_imu
        self.output_kind = spec.output_kind
        self.task = spec.kind
        self.onnx_path = model_file(model.path, spec.onnx, where)
        sess = model.session
        shape = list(sess.get_inputs()[0].shape)
        dims = [d if isinstance(d, int) else None for d in shape[1:]]
        if not dims or any(d is None for d in dims):
            dims = list(spec.input_dims or [spec.n_inputs])
        if not dims or any(d is None or d < 1 for d in dims):
            raise ModelError(f"{self.onnx_path}: cannot tell the input shape ({shape})")
        #: what the runtime computes from the window for a graph that reads window
        #: features (features version 2), else None (the graph reads the window)
        self.features = feature_spec(spec.features, where)
        graph_shape = tuple(int(d) for d in dims)
        if self.features is not None:
            if self.input_layout != "vectors" or self.features.T != self.T or \
                    self.features.uses_imu != self.uses_imu or \
                    graph_shape != (self.features.n_features,):
                raise ModelError(f"{where}: features (T={self.features.T}, imu="
                                 f"{self.features.uses_imu}, {self.features.n_features} values) "
                                 f"do not match the model's T={self.T}, uses_imu={self.uses_imu}, "
                                 f"layout {self.input_layout!r} and graph input {graph_shape}")
            #: the window encoding the model reads (its features are computed from it)
            self.input_shape = (self.features.n_inputs,)
        else:
            self.input_shape = graph_shape
        self.n_features = int(np.prod(self.input_shape))
        names = [o.name for o in sess.get_outputs()]
        want = spec.output
        self._out_index = names.index(want) if want in names else len(names) - 1
        self._out_name = names[self._out_index]
        self._x = np.zeros((1,) + graph_shape, np.float32)
        self._feats: dict = {}
        self._runner = BoundRun(sess, model.input_name, self._x, self._out_name)
        self.fault = False
        self._check_output_size(where)

    def _check_output_size(self, where: str) -> None:
        """ModelError naming the manifest unless the model's output holds one value
        per class of the manifest's ``classes`` (or one for 2 classes: a sigmoid's
        positive class). The graph's declared size, else one run on a zero window."""
        shape = self.model.session.get_outputs()[self._out_index].shape
        dims = list(shape[1:]) if isinstance(shape, (list, tuple)) else []
        if dims and all(isinstance(d, int) and d > 0 for d in dims):
            n = int(np.prod(dims))
        else:
            try:
                n = int(np.asarray(self._runner()).size)
            except Exception as exc:  # onnxruntime's own exception types
                raise ModelError(f"{self.onnx_path}: ONNX Runtime failed on a zero window: "
                                 f"{exc}") from None
        C = self.n_classes
        if n != C and not (n == 1 and C == 2):
            raise ModelError(f"{where}: 'classes' lists {C} names {self.classes} but the model "
                             f"{self.onnx_path.name} outputs {n} values per window "
                             f"({self._out_name!r}); the manifest and the model do not match")

    @classmethod
    def load(cls, path, expect_kind: str | None = None):
        """A classifier from a model folder (or its manifest). ``expect_kind`` (a task
        name) is checked against the manifest's ``kind``. A rule manifest gives a
        :class:`device.pi.models.rules.RuleClassifier`."""
        spec, mpath = read_spec(path)
        if spec.model == "rule":
            return RuleClassifier.load(path, expect_kind=expect_kind)
        if expect_kind is None and spec.kind not in CLASS_TASKS:
            raise ModelError(f"{mpath}: kind is {spec.kind!r}, not a classifier task "
                             f"({', '.join(CLASS_TASKS)})")
        return cls(load_model(path, expect_kind=expect_kind))

    @property
    def n_classes(self) -> int:
        return len(self.classes)

    def predict(self, window_input) -> tuple[int, np.ndarray]:
        """(class id, probabilities (C,) float64) for one encoded window: (D,), (1, D)
        or the layout's (1, T, S, S). Finite for any values; a wrong size raises
        :class:`ModelError` naming the model file."""
        a = self._sized(window_input)
        if self.features is not None:
            window_stats(self.features, a.reshape(1, -1), self._x)
            return self._run()
        np.clip(finite(a.reshape(-1), 0.0, INPUT_CLIP, -INPUT_CLIP), -INPUT_CLIP, INPUT_CLIP,
                out=self._x.reshape(-1))
        return self._run()

    def _sized(self, window_input) -> np.ndarray:
        a = np.asarray(window_input)
        if a.size != self.n_features:
            raise ModelError(f"{self.onnx_path}: expects an input of {self.n_features} values "
                             f"{self.input_shape}, got {a.size} (shape {a.shape}); build it "
                             f"with device.pi.models.window.encode({self.input_layout!r}, ...)")
        return a

    def _run(self) -> tuple[int, np.ndarray]:
        """The model on the input buffer, which holds finite values within INPUT_CLIP."""
        try:
            out = self._runner()
        except Exception as exc:  # onnxruntime's own exception types
            raise ModelError(f"{self.onnx_path}: ONNX Runtime failed: {exc}") from None
        probs = self.probabilities_from_output(out)
        return int(np.argmax(probs)), probs

    def probabilities_from_output(self, out) -> np.ndarray:
        """The model's raw output for one window -> cleaned probabilities (C,)."""
        o = np.asarray(out, dtype=np.float64).reshape(-1)
        C = self.n_classes
        if self.output_kind == "probabilities" and o.size == C:
            q = _usual_scaled(o)                          # the usual output: no fault
            if q is not None:
                self.fault = False
                return q
            p, fault = clean_probabilities(o)            # finite, sums to 1
            self.fault = fault or not np.isfinite(o).all()
            return p
        if self.output_kind == "logits":
            if o.size == C:
                p = softmax(o)
            elif o.size == 1 and C == 2:
                s = float(sigmoid(o)[0])
                p = np.array([1.0 - s, s])
            else:
                p = np.zeros(C)
            fault = o.size not in (C, 1) or not np.isfinite(o).all()
        else:
            if o.size == 1 and C == 2:
                s = float(np.clip(np.nan_to_num(o[0], nan=0.5), 0.0, 1.0))
                p, fault = np.array([1.0 - s, s]), not math.isfinite(float(o[0]))
            else:
                p, fault = np.full(C, 1.0 / C), True
        if not np.isfinite(p).all() or p.sum() <= 0:
            p, fault = np.full(C, 1.0 / C), True
        self.fault = bool(fault)
        return p

    def predict_window(self, window) -> tuple[int, np.ndarray]:
        """:meth:`predict` on a :class:`device.pi.models.window.RollingWindow`, encoded the
        way the model was trained. The window must hold T frames. A window's encoding
        is finite and within ``window.ENCODED_BOUND`` (<= INPUT_CLIP) for any pushed
        values, so it goes to the model as it is, without :meth:`predict`'s cleaning."""
        self.fill_window(window, self._x)
        return self._run()

    def fill_window(self, window, x: np.ndarray) -> None:
        """Write the model's input for ``window`` into ``x`` (its input buffer, or a
        fused graph's, :mod:`device.pi.models.fused`), as :meth:`predict_window` runs it."""
        if window.T != self.T:
            raise ModelError(f"{self.onnx_path}: the model sees T={self.T} frames, the "
                             f"window holds {window.T}")
        if self.features is not None:
            self.features_into(x).compute([window])
            return
        a = self._sized(window.encode(self.input_layout, with_imu=self.uses_imu))
        x.reshape(-1)[:] = a.reshape(-1)

    def features_into(self, x: np.ndarray) -> WindowFeatures:
        """The :class:`WindowFeatures` that writes this model's features into ``x``."""
        wf = self._feats.get(x.ctypes.data)
        if wf is None:
            wf = self._feats[x.ctypes.data] = WindowFeatures([self.features], [x])
        return wf
