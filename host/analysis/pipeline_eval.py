"""Accuracy of the marker pipeline on simulated scenes with ground truth, and
on the real clips against independent references."""
from __future__ import annotations

import math

import cv2
import numpy as np

from device.checks import whole_number
from device.pi.vision.extract import dome_mask, to_gray
from device.pi.vision.pipeline import MarkerStream
from device.pi.vision.matching import match_pins
from device.sim import Simulator, load_scene
from host.analysis.recall import pin_hits
from host.learn.metrics import classification_metrics

DRAGS = tuple(f"drag-{d}" for d in range(0, 360, 45))
PRESSES = ("press-hard", "press-soft", "press-wet")
#: contact detection scored as a two-class classifier (host.learn.metrics)
CONTACT_CLASSES = ["no contact", "contact"]


def _angle_err(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


def evaluate_scene(scene_name: str, effects=("glare", "camera_noise"), seed: int = 0,
                   profile: str = "roboskin", gate_px: float = 2.0,
                   min_shear_px: float = 1.0, stride: int = 1) -> dict:
    """Run the pipeline over one simulated scene and score it against truth.

    ``stride`` > 1 skips frames once the pipeline has its reference (every
    ``stride``-th frame is processed), as when the runtime falls behind and the
    newest frame wins: pins then move further between the frames it sees.

    * recall / precision: true visible pins with a detected pin within
      ``gate_px`` / detected pins with a true pin within it;
    * centroid error: distance from each matched detection to its true pin;
    * identity switches: tracked reference pins whose current pin is not the
      same physical pin (by truth) as at the reference, as a share of the
      tracked pins per frame;
    * direction error: average-vector angle against the true shear angle, on
      frames whose true patch shear exceeds ``min_shear_px``;
    * contact: the pipeline's flag against the true contact flag.
    """
    sim = Simulator(load_scene(scene_name).with_effects(*effects), seed=seed)
    tr = sim.truth
    stream = MarkerStream(profile)
    hits = n_true = n_found = found_ok = 0
    cerr, switch_rates, dir_err = [], [], []
    pred_c, true_c = [], []
    ref_ids = None
    stride = whole_number("stride", stride, 1)
    i, processed, reacquired = 0, 0, 0
    step = 1
    while i < sim.n_frames:
        out = stream.process(sim.render(i), steps=step)
        processed += 1
        reacquired += int(stream.tracker.reacquired)
        truth = tr["pins_px"][i]
        vis = np.flatnonzero(tr["visible"][i])
        found = out.pins
        truth_hit, found_hit, found_err = pin_hits(found, truth[vis], gate_px)
        hits += int(truth_hit.sum())
        found_ok += int(found_hit.sum())
        cerr.extend(found_err[found_hit].tolist())
        n_true += len(vis)
        n_found += len(found)
        # identity of each reference pin = the true pin nearest to it at the reference
        if stream.reference is not None and ref_ids is None:
            k = stream.reference_index
            ref_ids = _nearest_ids(stream.reference, tr["pins_px"][k], tr["visible"][k])
        if ref_ids is not None and len(out.lost):
            cur = stream.reference + out.vectors
            ok = ~out.lost & (ref_ids >= 0)
            if ok.any():
                cur_ids = _nearest_ids(cur[ok], truth, tr["visible"][i])
                switch_rates.append(float(np.mean(cur_ids != ref_ids[ok])))
        s = tr["shear_px"][i]
        if tr["contact"][i] and math.hypot(*s) > min_shear_px and out.magnitude > 0:
            dir_err.append(_angle_err(math.degrees(math.atan2(out.shear_y, out.shear_x)),
                                      math.degrees(math.atan2(s[1], s[0]))))
        pred_c.append(out.contact)
        true_c.append(bool(tr["contact"][i]))
        step = 1 if stream.reference is None else stride
        i += step
    pred_c, true_c = np.array(pred_c, bool), np.array(true_c, bool)
    if true_c.any() or pred_c.any():
        f1 = classification_metrics(true_c.astype(int), pred_c.astype(int), CONTACT_CLASSES)[
            "per_class"]["contact"]["f1"]
    else:
        f1 = 1.0                                # no contact at all, none claimed
    return {"scene": scene_name, "frames": sim.n_frames, "stride": stride,
            "frames_processed": processed, "reacquisitions": reacquired,
            "recall": hits / max(1, n_true), "precision": found_ok / max(1, n_found),
            "centroid_err_px_median": float(np.median(cerr)) if cerr else float("inf"),
            "id_switch_rate_mean": float(np.mean(switch_rates)) if switch_rates else 0.0,
            "id_switch_rate_max": float(np.max(switch_rates)) if switch_rates else 0.0,
            "direction_err_deg_median": float(np.median(dir_err)) if dir_err else None,
            "direction_frames": len(dir_err), "contact_f1": float(f1),
            "contact_true_frames": int(true_c.sum()), "contact_pred_frames": int(pred_c.sum())}


def _nearest_ids(points: np.ndarray, truth: np.ndarray, visible: np.ndarray) -> np.ndarray:
    vis = np.flatnonzero(visible)
    d = np.linalg.norm(points[:, None] - truth[vis][None], axis=-1)
    return vis[d.argmin(axis=1)]


def evaluate_sim(scenes=DRAGS + PRESSES, effects=("glare", "camera_noise"), seed: int = 0) -> dict:
    rows = [evaluate_scene(s, effects, seed) for s in scenes]
    drags = [r for r in rows if r["scene"].startswith("drag-")]
    dir_errs = [r["direction_err_deg_median"] for r in drags
                if r["direction_err_deg_median"] is not None]
    tp_rows = rows
    summary = {
        "recall_min": min(r["recall"] for r in rows),
        "precision_min": min(r["precision"] for r in rows),
        "centroid_err_px_median_max": max(r["centroid_err_px_median"] for r in rows),
        "id_switch_rate_max_mean": max(r["id_switch_rate_mean"] for r in drags) if drags else 0,
        "direction_err_deg_median_max": max(dir_errs) if dir_errs else None,
        "contact_f1_min": min(r["contact_f1"] for r in tp_rows),
    }
    summary["goals"] = {
        "recall>=0.98": summary["recall_min"] >= 0.98,
        "precision>=0.98": summary["precision_min"] >= 0.98,
        "centroid_median<=0.5px": summary["centroid_err_px_median_max"] <= 0.5,
        "id_switches<=0.5%": summary["id_switch_rate_max_mean"] <= 0.005,
        "direction_median<=5deg": (summary["direction_err_deg_median_max"] or 0) <= 5.0,
        "contact_f1>=0.98": summary["contact_f1_min"] >= 0.98,
    }
    return {"scenes": rows, "summary": summary, "effects": list(effects)}


#: Farneback settings for the direction check: pyramid 0.5, 5 levels, window 31,
#: 3 iterations, poly_n 5, sigma 1.1. Pins move up to about one pin pitch (12 px)
#: against the reference; smaller windows or fewer levels lock onto the wrong
#: pin of the lattice
FARNEBACK = (0.5, 5, 31, 3, 5, 1.1, 0)


def _dome_box(stream, shape, margin_px: int):
    """The slices and origin of the dome's bounding box plus a margin."""
    cx, cy, r = stream.dome
    rr = r * stream.profile.vision.roi_shrink + margin_px
    y0, x0 = max(0, int(cy - rr)), max(0, int(cx - rr))
    box = (slice(y0, min(shape[0], int(cy + rr) + 1)), slice(x0, min(shape[1], int(cx + rr) + 1)))
    return box, np.array([x0, y0], np.float64)


class _FromReference:
    """Run the pipeline over a clip; iterating yields (stream, gray frame,
    FrameFeatures, gray reference frame) from the frame where the reference is set
    on. ``frames`` counts every frame read (``limit``: stop after that many)."""

    def __init__(self, clip_path, profile: str, limit: int | None = None):
        self.clip_path, self.profile, self.limit = clip_path, profile, limit
        self.frames = 0

    def __iter__(self):
        stream = MarkerStream(self.profile)
        cap = cv2.VideoCapture(str(self.clip_path))
        recent: dict[int, np.ndarray] = {}
        ref_gray = None
        try:
            while self.limit is None or self.frames < self.limit:
                ok, frame = cap.read()
                if not ok:
                    break
                self.frames += 1
                g = to_gray(frame)
                out = stream.process(g)
                if stream.reference is None:
                    recent[out.index] = g.copy()
                    continue
                if ref_gray is None:
                    ref_gray = recent.get(stream.reference_index, g)
                    recent.clear()
                yield stream, g, out, ref_gray
        finally:
            cap.release()


def _result(clip_path, n: int, errs: list) -> dict:
    return {"clip": str(clip_path), "frames": n, "compared_frames": len(errs),
            "median_angle_err_deg": float(np.median(errs)) if errs else None,
            "p90_angle_err_deg": float(np.percentile(errs, 90)) if errs else None}


def farneback_direction_check(clip_path, profile: str = "roboskin", min_flow_px: float = 1.0,
                              limit: int | None = None, step: int = 1,
                              margin_px: int = 48) -> dict:
    """Average-vector direction against an independent reference: the mean of
    OpenCV's dense Farneback flow over the dome, against the same reference
    frame, on contact frames whose mean flow exceeds ``min_flow_px``. Every
    ``step``-th frame is compared (the pipeline sees every frame)."""
    errs = []
    ref_box = mask = box = None
    clip = _FromReference(clip_path, profile, limit)
    for stream, g, out, ref_gray in clip:
        if ref_box is None:
            # flow is computed on the dome's bounding box only: the same field, less work
            box, _ = _dome_box(stream, g.shape, margin_px)
            ref_box = ref_gray[box].copy()
            mask = (dome_mask(g.shape, stream.dome, stream.profile.vision.roi_shrink) > 0)[box]
        if not out.contact or out.index % step:
            continue
        flow = cv2.calcOpticalFlowFarneback(ref_box, g[box], None, *FARNEBACK)
        fx, fy = float(flow[..., 0][mask].mean()), float(flow[..., 1][mask].mean())
        if math.hypot(fx, fy) <= min_flow_px or out.magnitude == 0:
            continue
        errs.append(_angle_err(math.degrees(math.atan2(out.shear_y, out.shear_x)),
                               math.degrees(math.atan2(fy, fx))))
    return _result(clip_path, clip.frames, errs)


def chained_flow_direction_check(clip_path, profile: str = "roboskin",
                                 min_flow_px: float = 1.0, step: int = 1,
                                 snap_px: float = 2.0, margin_px: int = 48) -> dict:
    """Average-vector direction against Farneback flow chained frame to frame.

    From the reference frame on, each reference pin is carried along by the
    flow between consecutive frames (sampled at the pin) and snapped to a
    detected pin within ``snap_px``. Unlike flow straight from the reference,
    this follows pins that have moved about half a pitch or more, where the pin
    lattice makes the direct flow pick the wrong neighbour."""
    errs = []
    prev = pos = ref = box = origin = None
    clip = _FromReference(clip_path, profile)
    for stream, g, out, ref_gray in clip:
        if pos is None:
            box, origin = _dome_box(stream, g.shape, margin_px)
            ref = stream.reference.astype(np.float64)
            pos = ref.copy()
            prev = ref_gray[box].copy()
        cur = g[box]
        flow = cv2.calcOpticalFlowFarneback(prev, cur, None, *FARNEBACK)
        local = (pos - origin).astype(np.float32)
        f = cv2.remap(flow, local[:, 0].reshape(-1, 1), local[:, 1].reshape(-1, 1),
                      cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(-1, 2)
        pos += f
        idx = match_pins(pos, out.pins, snap_px)
        hit = idx >= 0
        pos[hit] = out.pins[idx[hit]]
        prev = cur.copy()
        if not out.contact or out.index % step or out.magnitude == 0:
            continue
        ch = (pos - ref).mean(axis=0)
        if math.hypot(*ch) <= min_flow_px:
            continue
        errs.append(_angle_err(math.degrees(math.atan2(out.shear_y, out.shear_x)),
                               math.degrees(math.atan2(ch[1], ch[0]))))
    return _result(clip_path, clip.frames, errs)
