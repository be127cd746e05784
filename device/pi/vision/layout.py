"""Fixed pin layout: every model sees the same M pins in the same order.

The marker pipeline tracks however many pins its reference frame had; models take
a fixed layout (the sensor profile's pin positions, ring by ring for roboskin).
:class:`LayoutMapper` puts each frame's per-reference-pin vectors onto that layout;
the host's dataset loader and the Pi runtime both use it, so a model sees the same
input on both. :func:`binary_crop` is the CNN's input frame (the thresholded image,
resized).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from device.checks import positive_number
from device.pi.vision.matching import match_pins, usable_rows
from device.profile import load_layout
from device.errors import TacfootError

__all__ = ["LayoutError", "LayoutAlignment", "fit_layout_alignment", "layout_assignment",
           "similarity", "to_layout", "LayoutMapper", "layout_for_profile", "binary_crop",
           "MAX_SCALE_CHANGE", "MAX_ROTATION_DEG", "MIN_FIT_PINS"]


class LayoutError(TacfootError, ValueError):
    """A profile has no fixed pin layout."""


#: The fitted alignment's bounds, from what a second session of one sensor can change:
#: re-seating the dome or refocusing the camera moves the pins along the optical axis
#: by a millimetre or so of a few centimetres, so the image scale by a few percent, and
#: a dome seated on its mount turns by a degree or two. The bounds are wider than that
#: and stop where the rim pins (some 12 pitches from the centre) would move by about a
#: pitch, where "which pin is which" has no answer from positions alone. A fit beyond
#: them is a bad reference (a pressed skin, a half-found frame), not a new session,
#: and is refused: the layout is then only shifted, as before, and the reason kept.
MAX_SCALE_CHANGE = 0.10
MAX_ROTATION_DEG = 5.0
#: matched pins a scale and rotation are fitted from (fewer: the shift alone)
MIN_FIT_PINS = 6


@dataclass(frozen=True)
class LayoutAlignment:
    """How a recording's reference (rest) pins line up with the profile's layout.

    The layout pin ``p`` sits at ``scale * R(rotation_deg) (p - c) + c + shift_px``
    in the reference frame, ``c`` the layout's centroid (image axes: x right, y down,
    so a positive rotation turns x toward y, clockwise on screen). ``assignment`` is, for each
    layout pin, the reference pin it stands for or -1; ``matched`` how many have
    one; ``residual_px`` the median distance of those to their aligned layout pin
    (0 with none). ``kind`` is ``similarity`` (shift, scale and rotation fitted),
    ``shift`` (the layout only shifted: ``reason`` says why the fit was not used) or
    ``none`` (nothing to match: ``reason`` says what was missing)."""

    assignment: np.ndarray
    shift_px: tuple[float, float] = (0.0, 0.0)
    scale: float = 1.0
    rotation_deg: float = 0.0
    residual_px: float = 0.0
    matched: int = 0
    kind: str = "none"
    reason: str = ""

    def summary(self) -> dict:
        """The alignment as JSON-able numbers (the runtime's status, ``host``)."""
        def r(v, n):
            return round(float(v), n) + 0.0         # + 0.0: no -0.0
        return {"kind": self.kind, "shift_px": [r(v, 3) for v in self.shift_px],
                "scale": r(self.scale, 5), "rotation_deg": r(self.rotation_deg, 4),
                "residual_px": r(self.residual_px, 3), "matched": int(self.matched),
                "layout_pins": int(len(self.assignment)), "reason": self.reason}


def similarity(pts: np.ndarray, c, scale: float, theta: float, shift) -> np.ndarray:
    """``scale * R(theta) (pts - c) + c + shift`` for (k, 2) ``pts``, with
    ``R(theta) = [[cos, -sin], [sin, cos]]`` (``theta`` in radians)."""
    co, si = np.cos(theta) * scale, np.sin(theta) * scale
    d = pts - c
    return np.column_stack((co * d[:, 0] - si * d[:, 1], si * d[:, 0] + co * d[:, 1])) + c + shift


def _fit_similarity(src: np.ndarray, dst: np.ndarray, c: np.ndarray):
    """Least-squares (scale, rotation rad, shift) taking ``src`` to ``dst`` about the
    point ``c`` (closed form for 2-D similarity); None when ``src`` has no spread."""
    a = src - c
    am = a.mean(axis=0)
    bm = dst.mean(axis=0)
    a0 = a - am
    b0 = dst - bm
    var = float((a0 * a0).sum())
    if not var > 1e-9:
        return None
    p = float((a0[:, 0] * b0[:, 0] + a0[:, 1] * b0[:, 1]).sum())     # sum a.b
    q = float((a0[:, 0] * b0[:, 1] - a0[:, 1] * b0[:, 0]).sum())     # sum a x b
    theta = float(np.arctan2(q, p))
    scale = float(np.hypot(p, q) / var)
    shift = bm - similarity(am[None, :], 0.0, scale, theta, 0.0)[0] - c
    return scale, theta, shift


def _robust_start(src: np.ndarray, dst: np.ndarray, c: np.ndarray, thresh: float):
    """(scale, rotation rad, shift) of the consensus of ``src`` -> ``dst`` pairs, some
    of them wrong (RANSAC, OpenCV's partial affine = similarity); None if it fails."""
    try:
        m, _ = cv2.estimateAffinePartial2D(
            (src - c).astype(np.float64), (dst - c).astype(np.float64), method=cv2.RANSAC,
            ransacReprojThreshold=float(thresh), maxIters=2000, confidence=0.995,
            refineIters=10)
    except cv2.error:
        return None
    if m is None or not np.isfinite(m).all():
        return None
    scale = float(np.hypot(m[0, 0], m[1, 0]))
    theta = float(np.arctan2(m[1, 0], m[0, 0]))
    return scale, theta, np.array([m[0, 2], m[1, 2]], np.float64)


def fit_layout_alignment(reference_px: np.ndarray, layout_px: np.ndarray, gate_px: float,
                         rounds: int = 3) -> LayoutAlignment:
    """Align the profile's layout to a recording's reference (rest) pins and assign.

    1. The shift: the median offset of matched pins, ``rounds`` times, starting from a
       gate of 1.5 x ``gate_px`` (what the layout mapping did before the fit).
    2. Shift, scale and rotation: a consensus fit (RANSAC) of the pairs the shift
       matches within 1.5 x ``gate_px``, then ``rounds + 2`` rounds of matching one
       to one within ``gate_px`` and a least-squares fit of the pairs within half
       the gate, until the assignment stops changing.
    3. The fit is kept when its scale is within 1 +- :data:`MAX_SCALE_CHANGE`, its
       rotation within +-:data:`MAX_ROTATION_DEG` degrees, it rests on at least
       :data:`MIN_FIT_PINS` pins and matches at least as many pins as the shift
       alone; otherwise the shift alone is used and ``reason`` says why.

    Reference or layout rows that are NaN, infinite or beyond ``MAX_COORD_PX`` never
    match; any input gives finite numbers.
    """
    ref = np.asarray(reference_px, np.float64).reshape(-1, 2)
    lay = np.asarray(layout_px, np.float64).reshape(-1, 2)
    gate_px = positive_number("gate_px", gate_px)
    rounds = max(0, int(rounds))
    out = np.full(len(lay), -1, np.int64)
    ref_rows = np.flatnonzero(usable_rows(ref))
    lay_rows = np.flatnonzero(usable_rows(lay))
    if len(ref_rows) == 0 or len(lay_rows) == 0:
        return LayoutAlignment(out, reason="no usable reference pins" if len(ref_rows) == 0
                               else "no usable layout pins")
    r = ref[ref_rows]
    L = lay[lay_rows]
    c = L.mean(axis=0)

    def result(idx, scale, theta, shift, kind, reason):
        ok = idx >= 0
        res = 0.0
        if ok.any():
            d = similarity(L[ok], c, scale, theta, shift) - r[idx[ok]]
            res = float(np.median(np.hypot(d[:, 0], d[:, 1])))
        out[lay_rows[ok]] = ref_rows[idx[ok]]
        return LayoutAlignment(out, (float(shift[0]), float(shift[1])), float(scale),
                               float(np.degrees(theta)), res, int(ok.sum()), kind, reason)

    # 1. the shift alone
    shift = np.zeros(2)
    for k in range(rounds):
        idx = match_pins(L + shift, r, gate_px * (1.5 if k == 0 else 1.0))
        ok = idx >= 0
        if ok.sum() < 3:
            break
        shift = np.median(r[idx[ok]] - L[ok], axis=0)
    base = match_pins(L + shift, r, gate_px)
    n_base = int((base >= 0).sum())

    def shift_only(reason):
        return result(base, 1.0, 0.0, shift, "shift", reason)

    # 2. shift, scale and rotation
    wide = match_pins(L + shift, r, 1.5 * gate_px)
    ok = wide >= 0
    if ok.sum() < MIN_FIT_PINS:
        return shift_only(f"{int(ok.sum())} pins matched, a scale and rotation need "
                          f"{MIN_FIT_PINS}")
    fit = _robust_start(L[ok], r[wide[ok]], c, 0.5 * gate_px)
    if fit is None:
        return shift_only("no consensus of the matched pins on a scale and rotation")
    scale, theta, t = fit
    idx = None
    for _ in range(rounds + 2):
        if not (abs(scale - 1.0) <= 2 * MAX_SCALE_CHANGE
                and abs(np.degrees(theta)) <= 2 * MAX_ROTATION_DEG):
            break                      # far outside the bounds: refused below
        new = match_pins(similarity(L, c, scale, theta, t), r, gate_px)
        if idx is not None and np.array_equal(new, idx):
            break
        idx = new
        ok = idx >= 0
        if ok.sum() >= MIN_FIT_PINS:
            d = similarity(L[ok], c, scale, theta, t) - r[idx[ok]]
            near = np.hypot(d[:, 0], d[:, 1]) <= 0.5 * gate_px
            if near.sum() >= MIN_FIT_PINS:
                got = _fit_similarity(L[ok][near], r[idx[ok]][near], c)
                if got is None:
                    break
                scale, theta, t = got
    if not (np.isfinite(scale) and np.isfinite(theta) and np.isfinite(t).all()):
        return shift_only("the scale and rotation fit gave no finite numbers")
    deg = float(np.degrees(theta))
    if abs(scale - 1.0) > MAX_SCALE_CHANGE:
        return shift_only(f"fitted scale {scale:.3f} outside {1 - MAX_SCALE_CHANGE:g}.."
                          f"{1 + MAX_SCALE_CHANGE:g}: a bad reference, not a new session")
    if abs(deg) > MAX_ROTATION_DEG:
        return shift_only(f"fitted rotation {deg:.2f} deg outside +-{MAX_ROTATION_DEG:g} deg: "
                          f"a bad reference, not a new session")
    idx = match_pins(similarity(L, c, scale, theta, t), r, gate_px)
    n_fit = int((idx >= 0).sum())
    if n_fit < MIN_FIT_PINS:
        return shift_only(f"the fit matched {n_fit} pins, a scale and rotation need "
                          f"{MIN_FIT_PINS}")
    if n_fit < n_base:
        return shift_only(f"the fit matched {n_fit} pins, the shift alone {n_base}")
    return result(idx, scale, theta, t, "similarity", "")


def layout_assignment(reference_px: np.ndarray, layout_px: np.ndarray, gate_px: float,
                      rounds: int = 3) -> np.ndarray:
    """For each fixed layout pin, the reference pin it stands for, or -1: int64
    (M_layout,). The layout is aligned to the reference by a bounded shift, scale and
    rotation, then matched one to one, nearest first, within ``gate_px``
    (:func:`fit_layout_alignment`, which also says how it was aligned)."""
    return fit_layout_alignment(reference_px, layout_px, gate_px, rounds).assignment


def to_layout(vectors: np.ndarray, lost: np.ndarray, assignment: np.ndarray,
              out_vectors: np.ndarray | None = None, out_lost: np.ndarray | None = None
              ) -> tuple[np.ndarray, np.ndarray]:
    """Per-reference-pin ``vectors`` (m, 2) / ``lost`` (m,) -> the fixed layout
    (M, 2) float32 / (M,) bool. A layout pin with no reference pin, or whose pin is
    lost, is lost with a zero vector."""
    M = len(assignment)
    v = np.zeros((M, 2), np.float32) if out_vectors is None else out_vectors
    lo = np.ones(M, bool) if out_lost is None else out_lost
    v[:] = 0.0
    lo[:] = True
    m = len(vectors)
    ok = (assignment >= 0) & (assignment < m)
    if m and ok.any():
        src = assignment[ok]
        vv = np.asarray(vectors, np.float32)[src]
        ll = np.asarray(lost, bool)[src] | ~np.isfinite(vv).all(axis=1)
        vv[ll] = 0.0
        v[ok] = vv
        lo[ok] = ll
    return v, lo


class LayoutMapper:
    """Puts a :class:`MarkerStream`'s per-reference-pin vectors on a fixed layout.

    The assignment is worked out once per reference frame (:func:`fit_layout_alignment`);
    :attr:`alignment` says how that reference lined up with the layout (None before
    the first reference). This is the one place to swap for the fixed-count localiser, which gives all
    ``M`` pins per frame directly.
    """

    def __init__(self, layout_px: np.ndarray, gate_px: float):
        self.layout_px = np.asarray(layout_px, np.float64).reshape(-1, 2)
        self.gate_px = float(gate_px)
        self._ref_id = None
        self._assignment = np.full(len(self.layout_px), -1, np.int64)
        self._alignment: LayoutAlignment | None = None

    @property
    def alignment(self) -> LayoutAlignment | None:
        """The last reference's alignment to the layout (shift, scale, rotation,
        residual, matched pins), or None before the first reference."""
        return self._alignment

    @property
    def n_pins(self) -> int:
        return len(self.layout_px)

    @property
    def assignment(self) -> np.ndarray:
        return self._assignment

    def __call__(self, stream, ff, out_vectors=None, out_lost=None):
        ref = stream.reference
        if ref is None:
            return to_layout(np.zeros((0, 2), np.float32), np.zeros(0, bool),
                             np.full(self.n_pins, -1, np.int64), out_vectors, out_lost)
        if ref is not self._ref_id:
            self._ref_id = ref
            self._alignment = fit_layout_alignment(ref, self.layout_px, self.gate_px)
            self._assignment = self._alignment.assignment
        return to_layout(ff.vectors, ff.lost, self._assignment, out_vectors, out_lost)


def layout_for_profile(profile: str) -> np.ndarray:
    """The fixed pin layout (M, 2) px of a sensor profile (ring by ring for roboskin;
    measured rest pins for a profile from ``host calibrate``)."""
    try:
        return np.asarray(load_layout(profile), np.float64)
    except Exception as exc:   # a [vision]-only file has no layout
        raise LayoutError(f"profile {profile!r}: no fixed pin layout ([profile]/[layout]) to "
                        f"map pins onto: {exc}") from None


def binary_crop(stream, size: int) -> np.ndarray:
    det = stream.detector
    b = None if det is None else det.binary
    if b is None or b.size == 0:
        return np.zeros((size, size), np.uint8)
    return cv2.resize(b, (size, size), interpolation=cv2.INTER_AREA)
