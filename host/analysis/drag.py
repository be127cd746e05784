"""Pin displacement over a drag, measured the same way on real and simulated frames.

Pins are detected by the Pi's :class:`device.pi.vision.extract.PinDetector` and
followed from the first frame; hard cases give finite numbers and a message in
``faults``.
"""

from __future__ import annotations

from typing import Iterable

import numpy as np

from device.pi.vision.extract import PinDetector, VisionParams
from device.pi.vision.tracking import Tracker
from host.analysis.frames import finite, frame_list, locate_dome, stat

__all__ = ["track_pins", "measure_drag_displacement"]


def track_pins(frames: Iterable[np.ndarray], params: VisionParams,
               dome: tuple[float, float, float] | None = None,
               max_jump_px: float | None = None) -> dict:
    """Pin tracking from the first frame with the Pi's tracker.

    The first frame's pins are the reference of a
    :class:`device.pi.vision.tracking.Tracker` (gate ``max_jump_px``, default
    0.4 times the reference's pin pitch), which follows them frame to frame
    (constant-velocity prediction, one-to-one matching, neighbour prediction
    for lost pins, coarse re-acquisition after a jump). Lost pins keep their
    predicted position and are counted as unmatched.

    Returns ``ref_xy`` (n,2), ``xy`` (T,n,2) tracked positions, ``matched``
    (T,n) bool, and ``dome``.
    """
    fl = frame_list(frames)
    if dome is None:
        dome = locate_dome(fl)
    det = PinDetector(params, fl[0].shape[:2], dome)
    ref, _ = det.detect(fl[0])
    ref = ref.astype(np.float64)
    n = len(ref)
    T = len(fl)
    xy = np.zeros((T, n, 2), np.float64)
    matched = np.zeros((T, n), bool)
    xy[0] = ref
    matched[0] = True
    if n == 0:
        return {"ref_xy": ref, "xy": xy, "matched": matched, "dome": dome}
    tracker = Tracker(max_dist_px=max_jump_px)
    tracker.set_reference(ref)
    for t in range(1, T):
        found, _ = det.detect(fl[t])
        vectors, lost = tracker.update(found)
        xy[t] = ref + vectors
        matched[t] = ~lost
    return {"ref_xy": ref, "xy": xy, "matched": matched, "dome": dome}


def measure_drag_displacement(frames: Iterable[np.ndarray], params: VisionParams,
                              dome: tuple[float, float, float] | None = None,
                              max_jump_px: float | None = None) -> dict:
    """Pin displacement relative to the first frame, px.

    Per frame: the median over tracked pins (matched in that frame) of
    |position - first position|. Over frames: ``displacement_px_p90`` (the
    typical maximum), ``displacement_px_max``, ``displacement_px_median``.
    Also the per-frame series, the median displacement vector (dx, dy) at the
    frame of largest displacement, and the median share of pins matched.
    """
    fl = frame_list(frames)
    tr = track_pins(fl, params, dome, max_jump_px)
    xy, matched, ref = tr["xy"], tr["matched"], tr["ref_xy"]
    faults: list[str] = []
    per_frame = np.zeros(len(fl), np.float64)
    if len(ref) == 0:
        faults.append("no pins in the first frame")
    else:
        mag = np.hypot(*(xy - ref[None]).transpose(2, 0, 1))
        for t in range(len(fl)):
            m = matched[t]
            per_frame[t] = float(np.median(mag[t, m])) if m.any() else (per_frame[t - 1] if t else 0.0)
    frac = matched.mean(axis=1) if len(ref) else np.zeros(len(fl))
    peak_vec = [0.0, 0.0]
    if len(ref):
        t_pk = int(np.argmax(per_frame))
        m = matched[t_pk] if matched[t_pk].any() else np.ones(len(ref), bool)
        peak_vec = [round(finite(v), 3) for v in np.median(xy[t_pk, m] - ref[m], axis=0)]
    return {
        "n_frames": len(fl),
        "n_pins_ref": int(len(ref)),
        "displacement_px_per_frame": [round(finite(v), 3) for v in per_frame],
        "displacement_px_p90": stat(per_frame, lambda v: np.percentile(v, 90)),
        "displacement_px_max": stat(per_frame, np.max),
        "displacement_px_median": stat(per_frame, np.median),
        "displacement_vector_px_at_max": peak_vec,
        "tracked_fraction_median": stat(frac, np.median),
        "faults": faults,
    }
