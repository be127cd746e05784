"""Window features: the per-window statistics an FNN reads, computed by the runtime
instead of by nodes of the model's ONNX graph.

The FNN's first layer (``host.learn.layers.TemporalFeatures``) has no weights: from
the ``vectors`` encoding of a window (T frames of M pin vectors, then T IMU rows when
the model uses the IMU) it appends frame-to-frame changes and per-frame means. In
ONNX those were about forty tiny nodes per model, most of the fused graph's call.
A model of features version 2 holds the scaler and the MLP alone; its manifest's
``features`` record says what to compute::

    "features": {"version": 2, "kind": "window-stats", "T": 3, "n_pins": 133,
                 "uses_imu": true, "pin_mask": null, "neighbours": null,
                 "rough_floor_px": 0.5, "n_inputs": 816, "n_features": 1365}

and :func:`window_stats` computes it, the numpy specification. The feature vector,
float32, from ``v`` (T, M, 2) = the window's vectors with ignored pins (``pin_mask``
0) read as zero, ``K`` neighbours per pin:

====================  ===========  =================================================
part                  size         value
====================  ===========  =================================================
the window            T*M*2 [+6T]  ``v`` flattened, then the IMU rows as they are
dv                    (T-1)*M*2    ``v[t+1] - v[t]``
avg                   2T           mean over the pins of ``v[t]``
davg                  2(T-1)       ``avg[t+1] - avg[t]``
\\|davg\\|            T-1          its length
mean \\|dv\\|         T-1          mean over the pins of ``|dv[t, m]|``
mag                   T            mean over the pins of ``|v[t, m]|``
(with ``neighbours``, r = v minus the mean of each pin's K neighbours)
rm, rm/den            T, T         sum over pins of ``use[m] * |r[t, m]|``; den = mag + floor
drm, drm/den[1:]      T-1, T-1     the same for ``r[t+1] - r[t]``
====================  ===========  =================================================

``use[m]`` is 1 / (pins counted) for each used pin whose neighbours are all used,
else 0. Every sum over pins or neighbours runs in float32 in pin order (pin 0 first),
and a mean is that sum divided by the count, so the compiled twin (``winfeat.c``)
gives the same numbers; ONNX Runtime's reductions sum in another order, so these
equal the old graph's to float32 rounding (about 1e-6 relative).

An input value that is not finite or beyond :data:`VALUE_BOUND` (an encoded window
never has one) is read as 0 (NaN) or the bound, so the features are finite whatever
the input.

:class:`WindowFeatures` computes the features of several models for one frame into
preallocated buffers: one call of the compiled kernel (:mod:`device.pi.vision.native`)
for all of them, or this module's numpy when the library is not loaded.
"""
from __future__ import annotations

import ctypes

import numpy as np

from device.pi.models.artefact import ModelError
from device.pi.models.window import ENCODED_BOUND

__all__ = ["FEATURES_VERSION", "FEATURES_KIND", "KNOWN_VERSIONS", "VALUE_BOUND",
           "FeatureSpec", "FeatureError", "feature_spec", "window_stats", "WindowFeatures"]

#: the version of the window features this runtime computes
FEATURES_VERSION = 2
FEATURES_KIND = "window-stats"
KNOWN_VERSIONS = (FEATURES_VERSION,)
#: input values are read within +-this (an encoded window is within ENCODED_BOUND)
VALUE_BOUND = float(ENCODED_BOUND)
#: the IMU columns per frame of a ``vectors`` encoding
IMU_COLS = 6
#: int64 slots per model in the compiled kernel's context (see winfeat.c)
CTX_SLOTS = 12          # native.WINFEAT_SLOTS (checked against the library there)


class FeatureError(ModelError):
    """A features record cannot be used; the message names the file and the field."""


class FeatureSpec:
    """A checked ``features`` record: the window (T, n_pins, uses_imu), the ignored
    pins, the neighbours for the roughness and the sizes in and out."""

    def __init__(self, T: int, n_pins: int, uses_imu: bool, pin_mask=None, neighbours=None,
                 rough_floor_px: float = 0.5, where: str = "features"):
        def bad(field, why, v):
            raise FeatureError(f"{where}: features.{field} {why}, got {v!r}")
        for f, v in (("T", T), ("n_pins", n_pins)):
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 1 <= v <= 100000:
                bad(f, "must be a whole number >= 1", v)
        self.T, self.M = int(T), int(n_pins)
        if not isinstance(uses_imu, (bool, np.bool_)):
            bad("uses_imu", "must be true or false", uses_imu)
        self.uses_imu = bool(uses_imu)
        self.mask = None
        if pin_mask is not None:
            m = np.asarray(pin_mask, np.float32).reshape(-1)
            if m.shape != (self.M,) or not np.isin(m, (0.0, 1.0)).all():
                bad("pin_mask", f"must hold {self.M} zeros and ones", pin_mask)
            self.mask = m
        self.nb = None
        self.use = None
        if neighbours is not None:
            try:
                nb = np.asarray(neighbours, np.int64)
            except (TypeError, ValueError):
                nb = np.zeros((0,), np.int64)
            if nb.ndim != 2 or nb.shape[0] != self.M or nb.shape[1] < 1 or \
                    nb.min() < 0 or nb.max() >= self.M:
                bad("neighbours", f"must be {self.M} rows of pin indices in 0..{self.M - 1}",
                    f"shape {nb.shape}")
            ok = np.ones(self.M, bool) if self.mask is None else self.mask > 0
            ok = ok & ok[nb].all(axis=1)
            if not ok.any():
                bad("neighbours", "leave no pin with all its neighbours in use", "none")
            self.nb = np.ascontiguousarray(nb, np.int32)
            self.use = (ok / ok.sum()).astype(np.float32)
        try:
            floor = float(rough_floor_px)
        except (TypeError, ValueError):
            floor = float("nan")
        if not (0.0 < floor < 1e6):
            bad("rough_floor_px", "must be a number > 0", rough_floor_px)
        self.floor = np.float32(floor)
        T, M = self.T, self.M
        self.n_inputs = T * M * 2 + (IMU_COLS * T if self.uses_imu else 0)
        self.n_features = (self.n_inputs + (T - 1) * M * 2 + 2 * T + 2 * (T - 1) + 2 * (T - 1)
                           + T + (4 * T - 2 if self.nb is not None else 0))

    @property
    def K(self) -> int:
        return 0 if self.nb is None else int(self.nb.shape[1])

    def record(self) -> dict:
        """The manifest's ``features`` record of this spec."""
        return {"version": FEATURES_VERSION, "kind": FEATURES_KIND, "T": self.T,
                "n_pins": self.M, "uses_imu": self.uses_imu,
                "pin_mask": None if self.mask is None else [int(v) for v in self.mask],
                "neighbours": None if self.nb is None else self.nb.astype(int).tolist(),
                "rough_floor_px": float(self.floor), "n_inputs": self.n_inputs,
                "n_features": self.n_features}

    def key(self) -> tuple:
        """Equal for two specs that compute the same features from the same input."""
        return (self.T, self.M, self.uses_imu,
                None if self.mask is None else self.mask.tobytes(),
                None if self.nb is None else self.nb.tobytes(), float(self.floor))


def feature_spec(rec, where: str = "manifest") -> FeatureSpec | None:
    """The :class:`FeatureSpec` of a manifest's ``features`` record; None for no
    record (a model whose graph computes its own features). FeatureError in one line
    naming ``where`` for a version this runtime does not know or a bad field."""
    if rec is None:
        return None
    if not isinstance(rec, dict):
        raise FeatureError(f"{where}: features must be a table, got {rec!r}")
    v = rec.get("version")
    if v not in KNOWN_VERSIONS or rec.get("kind") != FEATURES_KIND:
        raise FeatureError(f"{where}: features version {v!r} kind {rec.get('kind')!r} is not "
                           f"one this runtime computes (version {FEATURES_VERSION}, kind "
                           f"{FEATURES_KIND!r}); update tacfoot or re-export the model")
    spec = FeatureSpec(rec.get("T"), rec.get("n_pins"), rec.get("uses_imu"), rec.get("pin_mask"),
                       rec.get("neighbours"), rec.get("rough_floor_px", 0.5), where)
    for f in ("n_inputs", "n_features"):
        if rec.get(f) != getattr(spec, f):
            raise FeatureError(f"{where}: features.{f} must be {getattr(spec, f)} for this "
                               f"window, got {rec.get(f)!r}")
    return spec


# ----------------------------------------------------------------------------
# The numpy specification
# ----------------------------------------------------------------------------

def _seq_sum(a: np.ndarray, axis: int) -> np.ndarray:
    """float32 sum along ``axis`` in index order (a running sum: the C loop's order)."""
    return np.cumsum(a, axis=axis, dtype=np.float32).take(-1, axis=axis)


def _bounded(x: np.ndarray) -> np.ndarray:
    """float32 ``x`` with NaN -> 0 and values beyond +-VALUE_BOUND (inf too) -> the bound."""
    b = np.float32(VALUE_BOUND)
    return np.clip(np.nan_to_num(np.asarray(x, np.float32), nan=0.0, posinf=b, neginf=-b), -b, b)


def _norm2(a: np.ndarray) -> np.ndarray:
    """sqrt(a[..., 0]^2 + a[..., 1]^2), float32."""
    return np.sqrt(a[..., 0] * a[..., 0] + a[..., 1] * a[..., 1])


def window_stats(spec: FeatureSpec, x, out: np.ndarray | None = None) -> np.ndarray:
    """The features (N, n_features) float32 of windows ``x`` ((N, n_inputs) or
    (n_inputs,): the ``vectors`` encoding), written into ``out`` when given."""
    x = np.asarray(x)
    if x.shape[-1] != spec.n_inputs or x.ndim not in (1, 2):
        raise FeatureError(f"window features: expected (N, {spec.n_inputs}) windows for T="
                           f"{spec.T}, {spec.M} pins, imu={spec.uses_imu}, got {x.shape}")
    x = _bounded(x.reshape(-1, spec.n_inputs))
    N, T, M = x.shape[0], spec.T, spec.M
    f = np.float32
    v = x[:, :T * M * 2].reshape(N, T, M, 2)
    if spec.mask is not None:
        v = v * spec.mask[None, None, :, None]
    avg = _seq_sum(v, 2) / f(M)                                  # (N, T, 2)
    dv = v[:, 1:] - v[:, :-1]
    davg = avg[:, 1:] - avg[:, :-1]
    mag = _seq_sum(_norm2(v), 2) / f(M)                          # (N, T)
    parts = [v.reshape(N, -1), x[:, T * M * 2:], dv.reshape(N, -1), avg.reshape(N, -1),
             davg.reshape(N, -1), _norm2(davg), _seq_sum(_norm2(dv), 2) / f(M), mag]
    if spec.nb is not None:
        K = spec.K
        nbsum = _seq_sum(v[:, :, spec.nb], 3)                    # (N, T, M, 2), k in order
        r = v - nbsum / f(K)
        dr = r[:, 1:] - r[:, :-1]
        rm = _seq_sum(_norm2(r) * spec.use, 2)
        drm = _seq_sum(_norm2(dr) * spec.use, 2)
        den = mag + spec.floor
        parts += [rm, rm / den, drm, drm / den[:, 1:]]
    if out is None:
        out = np.empty((N, spec.n_features), np.float32)
    np.concatenate(parts, axis=1, out=out.reshape(N, spec.n_features))
    return out


# ----------------------------------------------------------------------------
# One call per frame
# ----------------------------------------------------------------------------

class WindowFeatures:
    """The features of several models for one frame, each written into its buffer
    ``outs[i]`` ((1, n_features) float32, e.g. a model's graph input), from the
    window each reads (a :class:`device.pi.models.window.RollingWindow` or a
    ``WindowTail`` of one). :meth:`compute` makes one call of the compiled kernel
    for all of them, or runs :func:`window_stats` (the same numbers) without it."""

    def __init__(self, specs: list, outs: list):
        self.specs = list(specs)
        self.outs = list(outs)
        for s, o in zip(self.specs, self.outs):
            if o.dtype != np.float32 or o.size != s.n_features or not o.flags.c_contiguous:
                raise FeatureError(f"window features: a buffer of {s.n_features} contiguous "
                                   f"float32 is needed, got {o.dtype} {o.shape}")
        self._scratch = [np.zeros(s.T * s.M * 2, np.float32) for s in self.specs]
        self._ctx: dict = {}              # (which, buffers' addresses) -> int64 context
        self._keep: dict = {}

    def compute(self, windows: list, which=None) -> None:
        """Write the features of the models ``which`` (indices, default all) from
        ``windows`` (one per model, in the same order as ``which``)."""
        idx = range(len(self.specs)) if which is None else which
        fn = _native().winfeat_fn()
        if fn is not None:
            srcs = [_source(w) for w in windows]
            key = (tuple(idx), tuple((s[0].ctypes.data, s[1].ctypes.data if s[1] is not None
                                      else 0) for s in srcs))
            ctx = self._ctx.get(key)
            if ctx is None:
                ctx = self._context(list(idx), srcs)
                if len(self._ctx) > 16:
                    self._ctx.clear()
                self._ctx[key] = ctx
            if fn(ctx.ctypes.data) == 0:
                return
        for i, w in zip(idx, windows):
            s = self.specs[i]
            window_stats(s, w.encode("vectors", with_imu=s.uses_imu), self.outs[i])

    def _context(self, idx: list, srcs: list) -> np.ndarray:
        c = np.zeros(1 + CTX_SLOTS * len(idx), np.int64)
        c[0] = len(idx)
        for j, (i, (vec, imu)) in enumerate(zip(idx, srcs)):
            s = self.specs[i]
            floor = np.array([s.floor], np.float32).view(np.int32)[0]
            c[1 + j * CTX_SLOTS:1 + (j + 1) * CTX_SLOTS] = [
                s.T, s.M, IMU_COLS if s.uses_imu else 0, s.K, vec.ctypes.data,
                imu.ctypes.data if s.uses_imu else 0,
                0 if s.mask is None else s.mask.ctypes.data,
                0 if s.nb is None else s.nb.ctypes.data,
                0 if s.use is None else s.use.ctypes.data,
                self.outs[i].ctypes.data, self._scratch[i].ctypes.data, int(floor)]
        return c


def _native():
    """device.pi.vision.native, imported on first use (it imports this module's
    CTX_SLOTS when it loads the library)."""
    global _NATIVE
    if _NATIVE is None:
        from device.pi.vision import native
        _NATIVE = native
    return _NATIVE


_NATIVE = None


def _source(w):
    """(vectors rows (T, M*2), IMU rows (T, 6)) of a window's ``vectors`` encoding:
    views of its quantised buffers, newest T rows, which keep their addresses."""
    base = getattr(w, "window", w)
    T = w.T
    return base._qvectors[-T:], base._qimu[-T:]


def call_kernel(fn, ctx: np.ndarray) -> int:
    """``fn(ctx)`` (for tests: the context's address as a ctypes argument)."""
    return fn(ctypes.c_void_p(ctx.ctypes.data))
