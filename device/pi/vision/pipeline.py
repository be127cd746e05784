"""The marker pipeline as one stream object: frames in, per-frame features out.

frames -> ROI (dome) -> adaptive threshold, glare-blob removal -> pin centroids
-> reference frame -> tracking to per-pin vectors (and the fixed-count
localiser, when one is given) -> contact grid -> average vector, magnitude sum.
The fault bits are device.pi.faults'. Pressure is not a per-frame feature: a pressure
model reads its own window (device.pi.models.regressor.Regressor.predict_window).

With the profile's ``[vision] contrast_ref`` (the dome's local contrast at
calibration), the threshold offset follows the exposure. At the first frame of each
run of still frames the reference may be chosen from (after start, a rezero, a new
frame size, or a run broken), the dome's local contrast is measured, the offset
becomes ``offset * clamp(contrast / contrast_ref, 0.5, 1)``
(:func:`device.pi.vision.extract.offset_scale`: not scaled within 5 % of the
calibration's contrast, nor for a black, white or blank dome) and that frame is
detected again with it. The offset then stays until the next run begins, so the
reference and every frame after it share one threshold, and a frame after the
reference costs what it did. Without ``contrast_ref`` nothing is measured and the
offset is the profile's.

A frame the sensor cannot make (device.pi.vision.plausibility: noise, black, white,
the dome moved; or pixel values that are NaN/inf, beyond 0..255 or boolean) gets the
``frame`` fault and no contact: its pins are counted but not tracked (every reference
pin is reported lost, vectors 0), the contact grid fades, and it never becomes the
reference.

The Pi runtime and the host (``host analyse``, training) use this one class; no
stage is written twice. Nothing on the per-frame path raises: a bad frame gives
finite numbers and fault bits.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
# np.median imports numpy.ma on its first call (about 6 ms here, far more on a Pi):
# imported with the pipeline, so no frame pays for it
import numpy.ma  # noqa: F401

from device.pi.faults import (FAULT_BAD_FRAME, FAULT_FRAME, FAULT_FRAME_SIZE_CHANGED,
                              FAULT_LOCALISER, FAULT_NO_DOME, FAULT_NO_REFERENCE,
                              FAULT_TOO_FEW_PINS, fault_names)
from device.pi.vision import frame, native
from device.pi.vision.features import ContactGrid, shear_and_sum_lost
from device.pi.vision.frame import FrameCore
from device.pi.vision.plausibility import FramePlausibility, stats_from_sums
from device.profile import PipelineProfile, load_pipeline_profile
from device.pi.vision.matching import match_pins
from device.pi.vision.tracking import Tracker
from device.pi.vision.extract import (PinDetector, find_dome, image_shape, offset_scale,
                                      to_gray)

#: the per-stage timers of FrameFeatures.timings_ms (besides "total"). A frame the fused
#: call takes (device.pi.vision.frame) reports "gray", then "core" (detection, the
#: plausibility check, tracking, the grid and the features in one call), "localise";
#: a stage it hands back to Python keeps its own timer ("track", "grid", "features")
STAGES = ("gray", "detect", "core", "track", "localise", "grid", "features")


@dataclass
class FrameFeatures:
    index: int
    t_s: float
    pins: np.ndarray              # (n, 2) detected pin centroids, px
    vectors: np.ndarray           # (m, 2) displacement of each reference pin, px
    lost: np.ndarray              # (m,) reference pins not found in this frame
    grid: np.ndarray              # (g, g) contact grid
    contact: bool
    shear_x: float                # the average vector, px
    shear_y: float
    magnitude: float              # |average vector|, px
    magnitude_sum: float          # P, the sum of |v_i|, px
    localised: np.ndarray | None  # (N, 2) fixed-count pins, if a localiser is loaded
    faults: int
    timings_ms: dict = field(default_factory=dict)

    @property
    def direction_deg(self) -> float:
        if self.magnitude == 0.0:
            return 0.0
        return math.degrees(math.atan2(self.shear_y, self.shear_x)) % 360.0

    def summary(self) -> dict:
        """The JSON line ``host analyse`` writes for this frame."""
        return {"frame": self.index, "t": round(self.t_s, 6), "pins": int(len(self.pins)),
                "contact": self.contact, "shear_x": round(self.shear_x, 4),
                "shear_y": round(self.shear_y, 4), "magnitude": round(self.magnitude, 4),
                "magnitude_sum": round(self.magnitude_sum, 3),
                "faults": fault_names(self.faults),
                "timings_ms": {k: round(v, 4) for k, v in self.timings_ms.items()}}


def pixel_values_ok(a: np.ndarray) -> bool:
    """A non-uint8 frame is one a camera could give: numbers (not bool), all finite
    and within 0..255. (uint8 frames are not checked: every value is one.)"""
    if a.dtype == np.bool_ or a.size == 0:
        return False
    if np.issubdtype(a.dtype, np.floating) and not np.isfinite(a).all():
        return False
    return bool(a.min() >= 0 and a.max() <= 255)


class MarkerStream:
    """Per-frame features from a stream of TacTip frames.

    The reference frame is chosen automatically: the first run of
    ``warmup`` still frames (pins move less than ``still_px`` between them);
    of those, the one whose pin count is closest to their median. Until then
    the ``reference_not_set`` fault is raised. :meth:`rezero` picks a new one.
    """

    def __init__(self, profile: PipelineProfile | str = "roboskin", localiser=None,
                 warmup: int = 5, still_px: float = 0.75, reacquire: str = "inline"):
        self.profile = (profile if isinstance(profile, PipelineProfile)
                        else load_pipeline_profile(profile))
        self.localiser = localiser
        self.warmup = max(1, int(warmup))
        self.still_px = float(still_px)
        p = self.profile
        self.tracker = Tracker(max_dist_px=p.match_gate_px, pitch_px=p.pitch_px,
                               reacquire=reacquire)
        self.grid = ContactGrid(p.grid_n, p.grid_gamma, p.grid_contact)
        self.plausibility = FramePlausibility(p.n_pins)
        #: why the last implausible frame failed ('' while frames pass)
        self.implausible = ""
        self.shape: tuple[int, int] | None = None
        self.detector: PinDetector | None = None
        self.dome = None
        self._dome_retry = 0
        self.index = 0
        self.reference: np.ndarray | None = None
        self.reference_index = -1          # the frame the reference was taken from
        self._candidates: list[tuple[np.ndarray, np.ndarray, int]] = []
        self._empty2 = np.zeros((0, 2), np.float32)
        #: the dome's local contrast (gray levels) measured when the reference search
        #: began, and the offset's factor from it (1.0: not scaled); see the module doc
        self.contrast = 0.0
        self.offset_scale = 1.0
        #: the fused frame's context (device.pi.vision.frame), made when first used
        self._frame_core: FrameCore | None = None
        #: take the fused call when it can; False runs (and times) every stage apart,
        #: as host.bench.scaling does to see how each stage grows with the pins
        self.fuse = True

    # -- control ---------------------------------------------------------------
    def rezero(self) -> None:
        """Forget the reference; the next still frames choose a new one."""
        self.reference = None
        self._candidates.clear()
        self.grid.clear_reference()
        self.plausibility.clear()

    def _reset_geometry(self, shape: tuple[int, int]) -> None:
        self.shape = shape
        self.dome = self.profile.dome_px
        self._dome_retry = 0
        self.detector = None
        self.rezero()

    def _ensure_dome(self, gray: np.ndarray) -> bool:
        if self.detector is not None:
            return True
        if self.dome is None:
            if self._dome_retry > 0:
                self._dome_retry -= 1
                return False
            self.dome = find_dome(gray)
            if self.dome is None:
                self._dome_retry = 10          # look again every 10 frames
                return False
        self.detector = PinDetector(self.profile.vision, self.shape, self.dome)
        return True

    def _set_exposure(self, crop: np.ndarray, pins: np.ndarray) -> np.ndarray:
        """Measure the dome's local contrast on this frame, scale the threshold offset
        to it (:func:`offset_scale`) and, when the threshold changes, detect the frame
        again: the pins under the offset from now on."""
        det, vis = self.detector, self.profile.vision
        self.contrast = det.local_contrast()
        self.offset_scale = offset_scale(self.contrast, vis.contrast_ref)
        offset = vis.offset * self.offset_scale
        if math.floor(offset) != math.floor(det.offset):
            det.set_offset(offset)
            pins, _ = det.detect_gray(crop)
        return pins

    def _still(self, pins: np.ndarray) -> bool:
        """Whether ``pins`` moved less than ``still_px`` (median over the pins matched)
        since the last candidate for the reference."""
        prev = self._candidates[-1][0]
        idx = match_pins(prev, pins, self.profile.match_gate_px)
        ok = idx >= 0
        moved = (np.median(np.hypot(*(pins[idx[ok]] - prev[ok]).T)) if ok.sum() >= 3
                 else np.inf)
        return bool(moved <= self.still_px)

    def _maybe_choose_reference(self, pins: np.ndarray, binary: np.ndarray, stats) -> None:
        c = self._candidates                  # a moved frame has cleared them (process)
        c.append((pins.copy(), binary.copy(), self.index - 1, stats))
        if len(c) < self.warmup:
            return
        counts = np.array([len(x[0]) for x in c])
        best = int(np.argmin(np.abs(counts - np.median(counts))))
        ref_pins, ref_binary, ref_index, ref_stats = c[best]
        if len(ref_pins) < self.profile.min_pin_fraction * self.profile.n_pins:
            c.clear()
            return
        self.reference = ref_pins
        self.reference_index = ref_index
        self.tracker.set_reference(ref_pins)
        self.grid.set_reference(ref_binary)
        self.plausibility.set_reference(ref_stats)
        c.clear()

    # -- per frame ---------------------------------------------------------------
    def process(self, frame, t_s: float | None = None, steps: int = 1) -> FrameFeatures:
        """One frame's pins, vectors and contact; ``steps`` > 1 when frames were
        dropped since the last one processed (the tracker predicts further)."""
        clock = time.perf_counter
        timings = {}
        t0 = clock()
        i = self.index
        self.index += 1
        t_s = float(i) if t_s is None or not math.isfinite(t_s) else float(t_s)
        faults = 0
        a = np.asarray(frame)
        shape = image_shape(a)
        if shape is None:
            return self._empty(i, t_s, FAULT_BAD_FRAME | FAULT_NO_DOME, timings)
        if a.ndim == 3 and a.shape[2] == 1:
            a = a[:, :, 0]
        if shape != self.shape:
            if self.shape is not None:
                faults |= FAULT_FRAME_SIZE_CHANGED
            self._reset_geometry(shape)
        if a.dtype != np.uint8 and not pixel_values_ok(a):
            self.implausible = "values"
            self._candidates.clear()
            faults |= FAULT_FRAME | (FAULT_NO_DOME if self.detector is None else 0)
            return self._empty(i, t_s, faults | (FAULT_NO_REFERENCE if self.reference is None
                                                 else 0), timings)
        t1 = clock()
        if self.detector is None:
            # the dome is looked for on the whole frame, once; after that only the
            # dome's box is converted (PinDetector.gray_crop)
            try:
                gray = to_gray(a)
            except (ValueError, TypeError):
                return self._empty(i, t_s, FAULT_BAD_FRAME | FAULT_NO_DOME, timings)
            if not self._ensure_dome(gray):
                timings["gray"] = (clock() - t1) * 1e3
                return self._empty(i, t_s, faults | FAULT_NO_DOME | FAULT_NO_REFERENCE, timings)
        try:
            # the dome box in gray: a view of a gray frame (a camera's luma plane, a
            # file source with gray=True), converted here for a colour one
            crop = self.detector.gray_crop(a)
            t1b = clock()
            timings["gray"] = (t1b - t1) * 1e3
            fused = self._fusable(crop, steps)
            if fused is None:
                pins, _ = self.detector.detect_gray(crop)
        except (ValueError, TypeError):
            return self._empty(i, t_s, faults | FAULT_BAD_FRAME, timings)
        if fused is not None:
            ff = self._fused(i, t_s, faults, crop, steps, timings, t0, t1b, fused)
            if ff is not None:
                return ff
            pins, _ = self.detector.detect_gray(crop)     # tf_frame did not detect
        return self._detected(i, t_s, faults, pins, crop, steps, timings, t0, t1b)

    def _detected(self, i, t_s, faults, pins, crop, steps, timings, t0, t1b) -> FrameFeatures:
        """The sequential path from the detected ``pins`` on: the reference search, the
        plausibility check, tracking, the grid and the features."""
        clock = time.perf_counter
        if self.reference is None and self._candidates and not self._still(pins):
            self._candidates.clear()           # a new run of still frames begins here
        if self.reference is None and not self._candidates and \
                self.profile.vision.contrast_ref is not None:
            pins = self._set_exposure(crop, pins)
        binary = self.detector.binary
        t2 = clock()
        timings["detect"] = (t2 - t1b) * 1e3
        faults |= self._pin_faults(pins)
        det = self.detector
        sums = det.sums
        # the compiled detection took the statistics' sums with the blur; numpy reads them
        stats = (stats_from_sums(*sums(), det.n_blobs) if sums is not None
                 else self.plausibility.stats(det.smooth, det.n_blobs))
        self.implausible = self.plausibility.check(stats)
        if self.implausible:
            return self._implausible(i, t_s, faults, pins, timings)
        if self.reference is None:
            self._maybe_choose_reference(pins, binary, stats)
        if self.reference is None:
            faults |= FAULT_NO_REFERENCE
            vectors, lost = self._empty2, np.zeros(0, bool)
        else:
            vectors, lost = self.tracker.update(pins, steps)
        t3 = clock()
        timings["track"] = (t3 - t2) * 1e3
        return self._tracked(i, t_s, faults, pins, vectors, lost, timings, t0, t3)

    def _pin_faults(self, pins: np.ndarray) -> int:
        return (FAULT_TOO_FEW_PINS if len(pins) < self.profile.min_pin_fraction * self.profile.n_pins
                else 0)

    def _implausible(self, i, t_s, faults, pins, timings) -> FrameFeatures:
        """A frame that failed the plausibility check: counted, not tracked."""
        self._candidates.clear()
        ff = self._empty(i, t_s, faults | FAULT_FRAME | (
            FAULT_NO_REFERENCE if self.reference is None else 0), timings)
        ff.pins = pins
        return ff

    def _tracked(self, i, t_s, faults, pins, vectors, lost, timings, t0, t3,
                 core=None) -> FrameFeatures:
        """The stages after tracking: the localiser, then the contact grid and the
        features, or ``core`` = (grid, shear x, shear y, magnitude sum, contact) when
        the fused call took those."""
        clock = time.perf_counter
        binary = self.detector.binary
        localised = None
        if self.localiser is not None:
            localised, bad = self.localiser.locate(binary, self.dome, box=self.detector.box)
            if bad:
                faults |= FAULT_LOCALISER
        t4 = clock()
        timings["localise"] = (t4 - t3) * 1e3
        if core is None:
            grid, grid_contact = self.grid.update(binary)
            grid = grid.copy()          # the grid object keeps updating its own buffer
            t5 = clock()
            timings["grid"] = (t5 - t4) * 1e3
            sx, sy, msum = shear_and_sum_lost(vectors, lost)
            n_valid = len(lost) - int(np.count_nonzero(lost))
            mean_mag = msum / n_valid if n_valid else 0.0
            contact = bool(self.reference is not None
                           and (grid_contact or mean_mag > self.profile.contact_px))
            timings["features"] = (clock() - t5) * 1e3
        else:
            grid, sx, sy, msum, contact = core
        timings["total"] = (clock() - t0) * 1e3
        return FrameFeatures(i, t_s, pins, vectors, lost, grid, contact, sx, sy,
                             math.hypot(sx, sy), msum, localised, faults, timings)

    # -- the usual frame in one compiled call (device.pi.vision.frame) ---------------
    def _fusable(self, crop, steps):
        """The tracker's ready contexts when this frame can take ``tf_frame``: a
        reference set, and the detection, the tracker's update, the grid and the shear
        all compiled for it; else None (the sequential path)."""
        det = self.detector
        if not self.fuse or self.reference is None or det._compiled is None \
                or self.grid._compiled is None:
            return None
        fn = native.frame_fn()
        if fn is None or native.shear_fn() is None or crop.dtype != np.uint8 \
                or crop.strides[1] != 1 or crop.shape != det._smooth.shape \
                or det.binary.shape != self.grid._ref.shape:
            return None
        fc = self._frame_core
        if fc is None or fc.fn is not fn:
            fc = self._frame_core = FrameCore(fn, self.plausibility.n_pins,
                                              self.profile.contact_px)
        return self.tracker.compiled_args(steps)

    def _fused(self, i, t_s, faults, crop, steps, timings, t0, t1b, args):
        """One ``tf_frame`` call, then the stage it names on the sequential path's
        code; None when it detected nothing (the caller detects as ever)."""
        clock = time.perf_counter
        det, fc, tr = self.detector, self._frame_core, self.tracker
        dc = det._compiled
        ci, cd, idx = args
        status = fc.run(dc, crop, tr, ci, cd, self.grid, self.plausibility, det.binary)
        if status == frame.DETECT or status == frame.REFUSED:
            return None
        t2 = clock()
        timings["core"] = (t2 - t1b) * 1e3
        pins = dc.xy[:fc.pins].copy()
        det.n_blobs = dc.n_blobs             # as detect_gray leaves the detector
        det.sums = dc.sums
        faults |= self._pin_faults(pins)
        if status == frame.IMPLAUS:
            self.implausible = fc.reason
            return self._implausible(i, t_s, faults, pins, timings)
        self.implausible = ""
        if status == frame.TRACK:
            # tf_track handed the frame back: a jump or unusable pins (numpy takes
            # it, no second tf_track), or more pins than its scratch holds (the
            # compiled update grows the scratch and takes it)
            vectors, lost = tr.update(pins, steps, compiled=len(pins) > tr._tcap)
            t3 = clock()
            timings["track"] = (t3 - t2) * 1e3
            return self._tracked(i, t_s, faults, pins, vectors, lost, timings, t0, t3)
        vectors, lost = tr.compiled_done(idx)
        if status == frame.GRID:
            return self._tracked(i, t_s, faults, pins, vectors, lost, timings, t0, clock())
        self.grid.bad_input = False
        sx, sy, msum, contact = fc.features()
        return self._tracked(i, t_s, faults, pins, vectors, lost, timings, t0, clock(),
                             (self.grid.grid.copy(), sx, sy, msum, contact))

    def _empty(self, i, t_s, faults, timings) -> FrameFeatures:
        g = self.grid.update(None)[0]
        m = 0 if self.reference is None else len(self.reference)
        return FrameFeatures(i, t_s, self._empty2, np.zeros((m, 2), np.float32),
                             np.ones(m, bool), g, False, 0.0, 0.0, 0.0, 0.0, None,
                             faults, timings)
