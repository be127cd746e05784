"""Data in for the learning toolkit: a data SPEC -> windows of T frames of features.

A SPEC (``host train --data SPEC``) is one of (docs/datasets.md, "Data specs"):

* a CSV manifest ``path,label[,start_frame,end_frame][,imu]``: each row a video, a
  folder of images, ``sim://SCENE`` or an ``.npz`` (below), paths relative to the
  manifest;
* a dataset folder written by ``host simulate`` (labels per frame from the truth);
* an ``.npz`` of marker vectors: ``vectors`` (N, T, M, 2), ``labels`` (N,) or
  ``targets`` (N,), optional ``imu`` (N, T, 6), ``contact`` (N,), ``lost``
  (N, T, M), ``groups`` (N,).

Frames go through the Pi's own :class:`device.pi.vision.pipeline.MarkerStream`, from the
first frame of each recording (so the reference is the recording's rest frame, as on
the Pi); a frame range only chooses which windows are cut. The per-reference-pin
vectors are put on the profile's fixed pin layout by :class:`LayoutMapper` (to be
swapped for the fixed-count localiser). A window is cut wherever all its T frames
have a reference; its label, contact flag and target are those of its last frame,
where the decision is made.

A *trial* is one recording: a clip file, a ``sim://`` scene with its seed, a trial of
a dataset folder, or a group of an ``.npz``. ``groups`` holds its id, so splits can
keep trials apart (:func:`split_grouped`, :func:`group_kfold`), and ``t_index`` /
``trial_len`` place each window in it (:func:`split_time`).
"""
from __future__ import annotations

import csv
import math
import sys
import time
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Iterable, Iterator
from urllib.parse import parse_qsl, urlsplit

import cv2
import numpy as np

__all__ = [
    "TASKS", "CLASS_TASKS", "NO_TOUCH", "SLIP_LABELS", "MANIFEST_COLUMNS",
    "DataError", "WindowSet", "ClipFeatures", "LayoutMapper", "layout_assignment",
    "to_layout", "extract_features", "load_spec", "load_specs", "split_grouped",
    "split_time", "group_kfold",
]

TASKS = ("surface", "texture", "slip", "pressure")
CLASS_TASKS = ("surface", "texture", "slip")
NO_TOUCH = "no-touch"
SLIP_LABELS = ("no-slip", "slip")          # slip task labels from a dataset folder
MANIFEST_COLUMNS = ("path", "label", "start_frame", "end_frame", "imu")
IMU_CHANNELS = 6                            # ax, ay, az [g], gx, gy, gz [deg/s]
DEFAULT_FRAME_SIZE = 32


class DataError(ValueError):
    """A bad data spec; the message names the file, row, column or key and the value."""


# ----------------------------------------------------------------------------
# The window set
# ----------------------------------------------------------------------------

_PER_WINDOW = ("vectors", "lost", "imu", "grids", "frames", "contact", "labels", "targets",
               "groups", "t_index", "trial_len")


@dataclass
class WindowSet:
    """N windows of T frames. Plain numpy arrays, one row per window.

    ``t_index`` is the window's last frame counted from its trial's first frame and
    ``trial_len`` the trial's length in frames; both are -1 for ``.npz`` windows,
    which carry no time order. ``source`` says where the windows came from
    (``trials``: one entry per group), how many windows were cut and kept
    (``kept_fraction``) and what was dropped.
    """

    task: str
    window: int                       # T, frames per window
    vectors: np.ndarray               # (N, T, M, 2) float32, pin displacement px
    lost: np.ndarray                  # (N, T, M) bool
    imu: np.ndarray | None            # (N, T, 6) float32
    grids: np.ndarray | None          # (N, T, g, g) float32 contact grid
    frames: np.ndarray | None         # (N, T, S, S) uint8 binary dome crop, downscaled
    contact: np.ndarray               # (N,) bool, last frame
    labels: np.ndarray | None         # (N,) str (object), classification tasks
    targets: np.ndarray | None        # (N,) float64, pressure task
    groups: np.ndarray                # (N,) int64 trial id
    t_index: np.ndarray               # (N,) int64
    trial_len: np.ndarray             # (N,) int64
    classes: list = field(default_factory=list)
    source: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.vectors.shape[0])

    @property
    def n_pins(self) -> int:
        return int(self.vectors.shape[2])

    @property
    def kept_fraction(self) -> float:
        return float(self.source.get("kept_fraction", 1.0))

    def subset(self, idx) -> "WindowSet":
        """The windows ``idx`` (indices or a boolean mask); classes stay as they are."""
        idx = np.asarray(idx)
        if idx.dtype == bool:
            if idx.shape != (len(self),):
                raise ValueError(f"subset mask must have shape ({len(self)},), got {idx.shape}")
            idx = np.flatnonzero(idx)
        idx = idx.astype(np.int64, copy=False)
        if idx.size and (idx.min() < -len(self) or idx.max() >= len(self)):
            raise ValueError(f"subset index out of range for {len(self)} windows")
        arrays = {k: (None if getattr(self, k) is None else getattr(self, k)[idx])
                  for k in _PER_WINDOW}
        return replace(self, **arrays, classes=list(self.classes),
                       source=dict(self.source, subset_of=len(self)))

    @classmethod
    def concat(cls, sets: Iterable["WindowSet"]) -> "WindowSet":
        """One set from several (e.g. one per ``--data``). Their groups are kept apart:
        each input's trials get new ids. An optional array (imu, grids, frames) is kept
        only when every input has it."""
        sets = list(sets)
        if not sets:
            raise ValueError("concat needs at least one WindowSet")
        if len(sets) == 1:
            return sets[0]
        first = sets[0]
        for k, s in enumerate(sets[1:], 1):
            if s.task != first.task:
                raise DataError(f"concat: set {k} is for task {s.task!r}, set 0 for {first.task!r}")
            if s.window != first.window:
                raise DataError(f"concat: set {k} has window T={s.window}, set 0 T={first.window}")
            if s.n_pins != first.n_pins:
                raise DataError(f"concat: set {k} has {s.n_pins} pins per frame, set 0 has "
                                f"{first.n_pins}; use one profile / pin layout")
        notes = []
        out = {}
        for k in ("imu", "grids", "frames"):
            have = [getattr(s, k) is not None for s in sets]
            if all(have):
                shapes = {getattr(s, k).shape[2:] for s in sets}
                if len(shapes) > 1:
                    raise DataError(f"concat: {k} shapes differ between sets: {sorted(shapes)}")
                out[k] = np.concatenate([getattr(s, k) for s in sets])
            else:
                out[k] = None
                if any(have):
                    notes.append(f"{k} dropped: sets {[i for i, h in enumerate(have) if not h]} "
                                 f"have none")
        for k in ("labels", "targets"):
            have = [getattr(s, k) is not None for s in sets]
            out[k] = np.concatenate([getattr(s, k) for s in sets]) if all(have) else None
        groups, trials, offset = [], [], 0
        for s in sets:
            uniq, inv = np.unique(s.groups, return_inverse=True)
            groups.append(inv.astype(np.int64) + offset)
            remap = {int(g): int(i) + offset for i, g in enumerate(uniq)}
            for tr in s.source.get("trials", []):
                if tr.get("group") in remap:
                    trials.append(dict(tr, group=remap[tr["group"]]))
            offset += len(uniq)
        cut = sum(int(s.source.get("windows_cut", len(s))) for s in sets)
        kept = sum(len(s) for s in sets)
        source = {"specs": [sp for s in sets for sp in s.source.get("specs", [])],
                  "trials": trials, "windows_cut": cut, "windows_kept": kept,
                  "kept_fraction": kept / cut if cut else 1.0,
                  "contact_from": sorted({c for s in sets
                                          for c in _as_list(s.source.get("contact_from"))}),
                  "notes": [n for s in sets for n in s.source.get("notes", [])] + notes}
        for k in ("extract_frames", "extract_s"):
            source[k] = sum(s.source.get(k, 0) for s in sets)
        classes = sorted(set().union(*[set(s.classes) for s in sets]))
        return cls(task=first.task, window=first.window,
                   vectors=np.concatenate([s.vectors for s in sets]),
                   lost=np.concatenate([s.lost for s in sets]),
                   contact=np.concatenate([s.contact for s in sets]),
                   groups=np.concatenate(groups),
                   t_index=np.concatenate([s.t_index for s in sets]),
                   trial_len=np.concatenate([s.trial_len for s in sets]),
                   classes=classes, source=source, **out)

    def summary(self) -> dict:
        """A JSON-able summary (for manifests and ``--json`` output)."""
        d = {"task": self.task, "window": self.window, "windows": len(self),
             "trials": int(len(np.unique(self.groups))), "pins": self.n_pins,
             "imu": self.imu is not None, "kept_fraction": round(self.kept_fraction, 6),
             "classes": list(self.classes)}
        if self.labels is not None:
            names, counts = np.unique(self.labels.astype(str), return_counts=True)
            d["class_counts"] = {str(n): int(c) for n, c in zip(names, counts)}
        if self.targets is not None and len(self):
            d["target_range"] = [float(self.targets.min()), float(self.targets.max())]
        return d


def _as_list(v) -> list:
    if v is None:
        return []
    return list(v) if isinstance(v, (list, tuple)) else [v]


# ----------------------------------------------------------------------------
# Reference pins -> the profile's fixed pin layout
# ----------------------------------------------------------------------------

from device.pi.vision.layout import LayoutError, LayoutMapper  # noqa: E402
from device.pi.vision.layout import layout_for_profile as _layout_for_profile  # noqa: E402


def layout_for_profile(profile: str) -> np.ndarray:
    """The fixed pin layout (M, 2) px of a sensor profile (:mod:`device.pi.vision.layout`)."""
    try:
        return _layout_for_profile(profile)
    except LayoutError as exc:
        raise DataError(str(exc)) from None


# ----------------------------------------------------------------------------
# Per-frame features of one recording
# ----------------------------------------------------------------------------

@dataclass
class ClipFeatures:
    """Per-frame features of one recording, frame 0 .. n_frames-1."""

    vectors: np.ndarray           # (F, M, 2) float32 on the fixed layout
    lost: np.ndarray              # (F, M) bool
    grids: np.ndarray             # (F, g, g) float32
    frames: np.ndarray | None     # (F, S, S) uint8
    contact: np.ndarray           # (F,) bool, the pipeline's contact flag
    ready: np.ndarray             # (F,) bool, a reference frame was set
    faults: np.ndarray            # (F,) int32 fault bits
    fps: float | None
    seconds: float = 0.0          # time spent extracting
    imu: np.ndarray | None = None  # (F, 6) from the simulator's truth, sim:// only

    @property
    def n_frames(self) -> int:
        return int(self.vectors.shape[0])


def extract_features(frames: Iterable, profile: str = "roboskin", frame_size: int | None = 32,
                     n_frames: int | None = None, progress: bool = True, desc: str = "",
                     fps: float | None = None, mapper: LayoutMapper | None = None
                     ) -> ClipFeatures:
    """Run the Pi's :class:`MarkerStream` over ``frames`` (images, or objects with
    ``.image`` and ``.t_s`` such as camera ``Frame``) and collect per-frame features
    on the profile's fixed pin layout."""
    from tqdm import tqdm

    from device.pi.vision.encoder import FrameEncoder
    from device.pi.faults import FAULT_NO_REFERENCE

    enc = FrameEncoder(profile, crop_px=frame_size or None,
                       layout_px=None if mapper is None else mapper.layout_px)
    stream = enc.stream
    vecs, losts, grids, crops, contact, ready, faults = [], [], [], [], [], [], []
    t0 = time.perf_counter()
    with tqdm(total=n_frames, desc=desc or "features", unit="frame", file=sys.stderr,
              disable=(not progress) or None, leave=False) as bar:   # None: off if no tty
        for fr in frames:
            image = getattr(fr, "image", fr)
            t_s = getattr(fr, "t_s", None)
            ef = enc.encode(image, t_s)
            ff = ef.features
            vecs.append(ef.vectors.copy())
            losts.append(ef.lost.copy())
            grids.append(np.asarray(ff.grid, np.float32))
            if ef.crop is not None:
                crops.append(ef.crop)
            contact.append(bool(ff.contact))
            ready.append(not (ff.faults & FAULT_NO_REFERENCE) and stream.reference is not None)
            faults.append(int(ff.faults))
            bar.update(1)
    seconds = time.perf_counter() - t0
    M, g = enc.n_pins, stream.profile.grid_n
    F = len(vecs)

    def stack(lst, shape, dtype):
        return np.stack(lst).astype(dtype, copy=False) if lst else np.zeros((0, *shape), dtype)

    return ClipFeatures(
        vectors=stack(vecs, (M, 2), np.float32), lost=stack(losts, (M,), bool),
        grids=stack(grids, (g, g), np.float32),
        frames=stack(crops, (frame_size, frame_size), np.uint8) if frame_size else None,
        contact=np.array(contact, bool).reshape(F), ready=np.array(ready, bool).reshape(F),
        faults=np.array(faults, np.int32).reshape(F), fps=fps, seconds=seconds)


# ----------------------------------------------------------------------------
# Cutting windows
# ----------------------------------------------------------------------------

def _window_ends(ready: np.ndarray, start: int, end: int, T: int, stride: int
                 ) -> tuple[np.ndarray, int]:
    """Last-frame indices of the windows in frames [start, end) whose T frames all have
    a reference; and how many windows were dropped for lacking one."""
    ends = np.arange(start + T - 1, end, stride, dtype=np.int64)
    if not len(ends):
        return ends, 0
    not_ready = np.concatenate([[0], np.cumsum(~ready[:end])])
    bad = (not_ready[ends + 1] - not_ready[ends + 1 - T]) > 0
    return ends[~bad], int(bad.sum())


@dataclass
class _Part:
    """Windows of one trial, before they become a WindowSet."""

    clip: ClipFeatures
    ends: np.ndarray          # last-frame index of each window, in the clip
    labels: np.ndarray | None
    targets: np.ndarray | None
    contact: np.ndarray
    imu: np.ndarray | None    # (F, 6) per clip frame
    trial: tuple              # key of the recording: one group per key
    span_start: int
    span_len: int


def _windows_from_parts(parts: list[_Part], task: str, T: int, trials: dict) -> dict:
    """Stack the windows of ``parts`` into per-window arrays."""
    offs = np.arange(-T + 1, 1, dtype=np.int64)
    keys = list(trials)
    out = {k: [] for k in ("vectors", "lost", "grids", "frames", "imu", "contact", "labels",
                           "targets", "groups", "t_index", "trial_len")}
    for p in parts:
        ix = p.ends[:, None] + offs[None, :]
        out["vectors"].append(p.clip.vectors[ix])
        out["lost"].append(p.clip.lost[ix])
        out["grids"].append(p.clip.grids[ix])
        out["frames"].append(None if p.clip.frames is None else p.clip.frames[ix])
        out["imu"].append(None if p.imu is None else p.imu[ix].astype(np.float32))
        out["contact"].append(p.contact)
        out["labels"].append(p.labels)
        out["targets"].append(p.targets)
        n = len(p.ends)
        out["groups"].append(np.full(n, keys.index(p.trial), np.int64))
        out["t_index"].append(p.ends - p.span_start)
        out["trial_len"].append(np.full(n, p.span_len, np.int64))
    res = {}
    for k, lst in out.items():
        if any(x is None for x in lst):
            res[k] = None
        else:
            res[k] = np.concatenate(lst) if lst else None
    return res


# ----------------------------------------------------------------------------
# Checks
# ----------------------------------------------------------------------------

def _check_task(task) -> str:
    if task not in TASKS:
        raise DataError(f"task must be one of {list(TASKS)}, got task={task!r}")
    return task


def _check_int(name: str, value, lo: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < lo:
        raise DataError(f"{name} must be a whole number >= {lo}, got {name}={value!r}")
    return int(value)


def _finalise(ws: WindowSet, min_classes: int, spec: str) -> WindowSet:
    if len(ws) == 0:
        why = ""
        if ws.source.get("windows_cut", 0):
            why = (f" ({ws.source['windows_cut']} cut, none kept"
                   + (": none has contact" if ws.source.get("contact_only") else "") + ")")
        raise DataError(f"{spec}: no windows of T={ws.window} frames{why}")
    if ws.labels is not None:
        ws.classes = sorted({str(x) for x in ws.labels})
        if len(ws.classes) < min_classes:
            raise DataError(
                f"{spec}: task {ws.task!r} needs at least {min_classes} classes, the data hold "
                f"{len(ws.classes)}: {ws.classes} (pass min_classes=1 to load one class, "
                f"e.g. for evaluation)")
    if ws.targets is not None and not np.isfinite(ws.targets).all():
        raise DataError(f"{spec}: {int((~np.isfinite(ws.targets)).sum())} targets are not finite")
    return ws


def _window_labels(task: str, label_frames: np.ndarray | None, contact: np.ndarray,
                   ) -> np.ndarray | None:
    """Per-window labels: no-touch where the last frame has no contact (surface,
    texture)."""
    if label_frames is None:
        return None
    lab = np.asarray(label_frames, object).copy()
    if task in ("surface", "texture"):
        lab[~contact] = NO_TOUCH
    return lab


def _keep(parts: list[_Part], contact_only: bool) -> tuple[list[_Part], int, int]:
    cut = sum(len(p.ends) for p in parts)
    if contact_only:
        new = []
        for p in parts:
            k = p.contact
            new.append(replace(p, ends=p.ends[k], contact=p.contact[k],
                               labels=None if p.labels is None else p.labels[k],
                               targets=None if p.targets is None else p.targets[k]))
        parts = new
    return parts, cut, sum(len(p.ends) for p in parts)


# ----------------------------------------------------------------------------
# The CSV manifest
# ----------------------------------------------------------------------------

@dataclass
class _Row:
    line: int
    kind: str                 # "clip" | "sim" | "npz"
    path: str                 # resolved path or sim URL
    label: str
    start: int
    end: int | None
    imu_path: Path | None

    def where(self, manifest: Path, column: str | None = None) -> str:
        col = f", column {column}" if column else ""
        return f"{manifest} row {self.line - 1} (line {self.line}){col}"


def _parse_manifest(path: Path, task: str) -> list[_Row]:
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise DataError(f"no such manifest: {path}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: cannot read the manifest: {exc}") from None
    lines = text.splitlines()
    reader = csv.reader(lines)
    header = None
    rows: list[_Row] = []
    base = path.parent
    for lineno, rec in enumerate(reader, 1):
        if not rec or all(not c.strip() for c in rec) or rec[0].lstrip().startswith("#"):
            continue
        rec = [c.strip() for c in rec]
        if header is None:
            header = rec
            unknown = [c for c in header if c not in MANIFEST_COLUMNS]
            if unknown:
                raise DataError(f"{path} line {lineno}: unknown column {unknown[0]!r}; the "
                                f"columns are path,label[,start_frame,end_frame][,imu]")
            for need in ("path", "label"):
                if need not in header:
                    raise DataError(f"{path} line {lineno}: the header has no {need!r} column "
                                    f"(got {','.join(header)}); the columns are "
                                    f"path,label[,start_frame,end_frame][,imu]")
            if len(set(header)) != len(header):
                raise DataError(f"{path} line {lineno}: a column is named twice: "
                                f"{','.join(header)}")
            continue
        where = f"{path} row {len(rows) + 1} (line {lineno})"
        if len(rec) > len(header):
            raise DataError(f"{where}: {len(rec)} fields, the header has {len(header)}")
        cells = dict(zip(header, rec + [""] * (len(header) - len(rec))))
        p = cells["path"]
        if not p:
            raise DataError(f"{where}, column path: empty")
        label = cells["label"]

        def integer(col):
            s = cells.get(col, "")
            if s == "":
                return None
            try:
                v = int(s)
            except ValueError:
                raise DataError(f"{where}, column {col}: {s!r} is not a whole number") from None
            if v < 0:
                raise DataError(f"{where}, column {col}: {v} is negative")
            return v

        start, end = integer("start_frame"), integer("end_frame")
        if start is not None and end is not None and end <= start:
            raise DataError(f"{where}, column end_frame: {end} is not after start_frame {start}")
        if p.lower().startswith("sim://"):
            kind, resolved = "sim", _resolve_sim(p, base)
        else:
            local = Path(p).expanduser()
            local = local if local.is_absolute() else base / local
            if not local.exists():
                raise DataError(f"{where}, column path: no such file or folder: {local}")
            kind = "npz" if local.suffix.lower() == ".npz" else "clip"
            resolved = str(local)
        if kind == "npz":
            for col in ("start_frame", "end_frame", "imu"):
                if cells.get(col, ""):
                    raise DataError(f"{where}, column {col}: {cells[col]!r} given for an .npz "
                                    f"row; an .npz holds whole windows (put imu inside it)")
        elif not label:
            raise DataError(f"{where}, column label: empty")
        if label and task == "pressure":
            try:
                if not math.isfinite(float(label)):
                    raise ValueError
            except ValueError:
                raise DataError(f"{where}, column label: {label!r} is not a finite number "
                                f"(task pressure needs a target per row)") from None
        imu_path = None
        if cells.get("imu", ""):
            ip = Path(cells["imu"]).expanduser()
            imu_path = ip if ip.is_absolute() else base / ip
            if not imu_path.is_file():
                raise DataError(f"{where}, column imu: no such file: {imu_path}")
        rows.append(_Row(lineno, kind, resolved, label, start or 0, end, imu_path))
    if header is None:
        raise DataError(f"{path}: empty manifest (needs a header path,label[,...] and rows)")
    if not rows:
        raise DataError(f"{path}: the manifest has a header but no rows")
    return rows


def _resolve_sim(url: str, base: Path) -> str:
    """``sim://SCENE?seed=N``, with a relative scene .toml resolved beside the manifest."""
    parts = urlsplit(url)
    scene = parts.netloc + parts.path
    if scene.endswith(".toml") and not Path(scene).is_absolute():
        cand = base / scene
        if cand.exists():
            scene = str(cand.resolve())
    query = dict(parse_qsl(parts.query, keep_blank_values=True))
    query.setdefault("seed", "0")          # sim://x and sim://x?seed=0 are one recording
    q = "&".join(f"{k}={v}" for k, v in sorted(query.items()))
    return f"sim://{scene}" + (f"?{q}" if q else "")


def _load_imu_npy(path: Path, where: str) -> np.ndarray:
    try:
        a = np.load(path, allow_pickle=False)
    except Exception as exc:
        raise DataError(f"{where}: cannot read {path}: {exc}") from None
    if a.ndim != 2 or a.shape[1] != IMU_CHANNELS:
        raise DataError(f"{where}: {path} has shape {a.shape}, expected (frames, 6): "
                        f"ax, ay, az [g], gx, gy, gz [deg/s]")
    a = np.asarray(a, np.float64)
    if not np.isfinite(a).all():
        raise DataError(f"{where}: {path} has {int((~np.isfinite(a)).any(axis=1).sum())} rows "
                        f"with NaN or inf")
    return a


def _clip_key(row: _Row) -> str:
    return row.path if row.kind == "sim" else str(Path(row.path).resolve())


def _extract_clip(key: str, end: int | None, profile: str, frame_size, progress: bool,
                  cache: dict) -> ClipFeatures:
    """Features of frames 0 .. end-1 (None: all) of a clip, cached per clip."""
    from device.pi.sources.camera import CameraError, open_camera

    hit = cache.get(("clip", key, profile, frame_size))
    if hit is not None and (hit[1] is None or (end is not None and hit[1] >= end)):
        return hit[0]
    opts = {} if end is None else {"end_frame": end}
    try:
        cam = open_camera(key, **opts)
    except (CameraError, OSError, ValueError) as exc:
        raise DataError(f"{key}: cannot open: {exc}") from None
    with cam:
        n = cam.n_frames
        clip = extract_features(cam, profile, frame_size, n_frames=n, progress=progress,
                                desc=Path(key).name if "://" not in key else key, fps=cam.fps)
        if key.startswith("sim://"):
            imu = np.asarray(cam.truth["imu"], np.float64)
            clip.imu = imu[:clip.n_frames]
    cache[("clip", key, profile, frame_size)] = (clip, end)
    return clip


def _load_manifest(path: Path, task: str, T: int, stride: int, contact_only: bool,
                   profile: str, frame_size, progress: bool, cache: dict,
                   min_classes: int) -> WindowSet:
    rows = _parse_manifest(path, task)
    clip_rows = [r for r in rows if r.kind != "npz"]
    # one pass per recording, up to the last frame any row needs
    need: dict[str, int | None] = {}
    for r in clip_rows:
        k = _clip_key(r)
        if k in need:
            need[k] = None if need[k] is None or r.end is None else max(need[k], r.end)
        else:
            need[k] = r.end
    clips = {k: _extract_clip(k, e, profile, frame_size, progress, cache) for k, e in need.items()}
    # the span of each recording the rows use
    spans: dict[str, list[int]] = {}
    for r in clip_rows:
        k = _clip_key(r)
        n = clips[k].n_frames
        end = n if r.end is None else r.end
        if r.end is not None and r.end > n:
            raise DataError(f"{r.where(path, 'end_frame')}: {r.end} is past the end of "
                            f"{r.path} ({n} frames)")
        if r.start >= n:
            raise DataError(f"{r.where(path, 'start_frame')}: {r.start} is past the end of "
                            f"{r.path} ({n} frames)")
        if end - r.start < T:
            raise DataError(f"{r.where(path)}: window T={T} frames is longer than the clip "
                            f"part {r.path} frames {r.start}..{end} ({end - r.start} frames)")
        lo, hi = spans.get(k, [r.start, end])
        spans[k] = [min(lo, r.start), max(hi, end)]
    parts: list[_Part] = []
    trials: dict = {}
    imu_missing, dropped_ref = [], 0
    for r in clip_rows:
        k = _clip_key(r)
        clip = clips[k]
        end = clip.n_frames if r.end is None else r.end
        ends, nref = _window_ends(clip.ready, r.start, end, T, stride)
        dropped_ref += nref
        imu = None
        if r.imu_path is not None:
            imu = _load_imu_npy(r.imu_path, r.where(path, "imu"))
            if len(imu) < end:
                raise DataError(f"{r.where(path, 'imu')}: {r.imu_path} has {len(imu)} rows, the "
                                f"clip part needs {end} (one per frame from frame 0)")
        elif clip.imu is not None:
            imu = clip.imu
        if imu is None:
            imu_missing.append(r.line - 1)
        contact = clip.contact[ends]
        labels = targets = None
        if task == "pressure":
            targets = np.full(len(ends), float(r.label))
        else:
            labels = _window_labels(task, np.full(len(ends), r.label, object), contact)
        trials.setdefault(k, {"kind": r.kind, "path": r.path, "span_start": spans[k][0],
                              "frames": spans[k][1] - spans[k][0], "fps": clip.fps, "rows": []})
        trials[k]["rows"].append(r.line - 1)
        parts.append(_Part(clip, ends, labels, targets, contact, imu, k, spans[k][0],
                           spans[k][1] - spans[k][0]))
    notes = []
    if dropped_ref:
        notes.append(f"{dropped_ref} windows dropped: they start before the reference frame")
    parts, cut, kept = _keep(parts, contact_only)
    arrays = _windows_from_parts(parts, task, T, trials) if parts else None
    sets = []
    if arrays is not None:
        if imu_missing and arrays["imu"] is None and len(imu_missing) < len(clip_rows):
            msg = (f"{path}: imu dropped for every window: rows {imu_missing} have no imu "
                   f"(give every row an imu .npy, or none)")
            warnings.warn(msg, stacklevel=3)
            notes.append(msg)
        src = {"specs": [str(path)], "trials": [dict(v, group=i) for i, v in
                                                enumerate(trials.values())],
               "windows_cut": cut, "windows_kept": kept, "contact_only": contact_only,
               "kept_fraction": kept / cut if cut else 1.0, "contact_from": "pipeline",
               "notes": notes,
               "extract_frames": sum(c.n_frames for c in clips.values()),
               "extract_s": sum(c.seconds for c in clips.values())}
        sets.append(WindowSet(task=task, window=T, classes=[], source=src, **arrays))
    for r in rows:
        if r.kind == "npz":
            sets.append(_load_npz(Path(r.path), task, T, contact_only, profile,
                                  label=r.label or None, where=r.where(path, "path"),
                                  min_classes=1))
    ws = WindowSet.concat(sets)      # rows is never empty, so neither is sets
    ws.source["specs"] = [str(path)]
    return _finalise(ws, min_classes, str(path))


# ----------------------------------------------------------------------------
# A dataset folder
# ----------------------------------------------------------------------------

def _load_dataset(path: Path, task: str, T: int, stride: int, contact_only: bool,
                  profile: str, frame_size, progress: bool, cache: dict,
                  min_classes: int) -> WindowSet:
    from host.data.dataset import DatasetError, load_trial, read_index

    try:
        index = read_index(path)
    except DatasetError as exc:
        raise DataError(str(exc)) from None
    entries = index.get("trials", [])
    if not entries:
        raise DataError(f"{path}: the dataset has no trials")
    names = {"surface": index.get("surface_labels"), "texture": index.get("texture_labels")}
    if task in names and not names[task]:
        raise DataError(f"{path}: dataset.json has no {task}_labels")
    parts, trials, dropped_ref = [], {}, 0
    for i, entry in enumerate(entries):
        fname = entry.get("file", f"trial {i}")
        if entry.get("profile") not in (None, profile) and not str(profile).endswith(".toml"):
            raise DataError(f"{path / fname}: recorded with profile {entry.get('profile')!r}, "
                            f"features asked for profile {profile!r}")
        if int(entry.get("frames", T)) < T:
            raise DataError(f"{path / fname}: window T={T} frames is longer than the trial "
                            f"({entry.get('frames')} frames)")
        key = ("trial", str(path.resolve()), i, profile, frame_size)
        tr = None
        if key in cache:
            clip, truth = cache[key]
        else:
            try:
                tr = load_trial(path, i)
            except (OSError, ValueError, KeyError) as exc:
                raise DataError(f"{path / fname}: cannot read the trial: {exc}") from None
            frames = tr["frames"]
            clip = extract_features(frames, profile, frame_size, n_frames=len(frames),
                                    progress=progress, desc=f"{path.name}/{fname}",
                                    fps=float(entry.get("fps") or 0) or None)
            truth = {k: tr[k] for k in ("contact", "surface", "texture", "slip", "load_n", "imu")
                     if k in tr}
            cache[key] = (clip, truth)
        F = clip.n_frames
        for k in ("contact", "surface", "texture", "slip", "load_n"):
            if k not in truth or len(truth[k]) != F:
                raise DataError(f"{path / fname}: truth array {k!r} is missing or not one per "
                                f"frame ({F} frames)")
        ends, nref = _window_ends(clip.ready, 0, F, T, stride)
        dropped_ref += nref
        contact = np.asarray(truth["contact"], bool)[ends]
        labels = targets = None
        if task in ("surface", "texture"):
            codes = np.asarray(truth[task], np.int64)[ends]
            nm = list(names[task])
            if codes.size and (codes.min() < 0 or codes.max() >= len(nm)):
                raise DataError(f"{path / fname}: {task} code {int(codes.max())} has no name in "
                                f"{task}_labels {nm}")
            labels = _window_labels(task, np.array(nm, object)[codes], contact)
        elif task == "slip":
            labels = np.array(SLIP_LABELS, object)[np.asarray(truth["slip"], bool)[ends]
                                                   .astype(int)]
        else:
            targets = np.asarray(truth["load_n"], np.float64)[ends]
        imu = truth.get("imu")
        if imu is not None:
            imu = np.asarray(imu, np.float64)
            if imu.shape != (F, IMU_CHANNELS):
                raise DataError(f"{path / fname}: imu has shape {imu.shape}, expected ({F}, 6)")
        trials[i] = {"kind": "dataset", "path": str(path / fname), "span_start": 0,
                     "frames": F, "fps": clip.fps, "scene": entry.get("scene"),
                     "seed": entry.get("seed")}
        parts.append(_Part(clip, ends, labels, targets, contact, imu, i, 0, F))
    parts, cut, kept = _keep(parts, contact_only)
    arrays = _windows_from_parts(parts, task, T, trials)
    notes = [f"{dropped_ref} windows dropped: they start before the reference frame"] \
        if dropped_ref else []
    src = {"specs": [str(path)], "trials": [dict(v, group=i) for i, v in enumerate(trials.values())],
           "windows_cut": cut, "windows_kept": kept, "contact_only": contact_only,
           "kept_fraction": kept / cut if cut else 1.0, "contact_from": "truth", "notes": notes,
           "extract_frames": sum(p.clip.n_frames for p in parts),
           "extract_s": sum(p.clip.seconds for p in parts)}
    return _finalise(WindowSet(task=task, window=T, classes=[], source=src, **arrays),
                     min_classes, str(path))


# ----------------------------------------------------------------------------
# An .npz of marker vectors
# ----------------------------------------------------------------------------

def _load_npz(path: Path, task: str, T: int, contact_only: bool, profile: str,
              label: str | None = None, where: str | None = None,
              min_classes: int = 2) -> WindowSet:
    where = where or str(path)
    try:
        z = np.load(path, allow_pickle=False)
        data = {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise DataError(f"no such file: {path}") from None
    except Exception as exc:
        raise DataError(f"{where}: cannot read {path} as an .npz without pickle: {exc}") from None
    if "vectors" not in data:
        raise DataError(f"{path}: no 'vectors' array (N, T, M, 2); keys are {sorted(data)}")
    v = np.asarray(data["vectors"])
    if v.ndim != 4 or v.shape[3] != 2 or not np.issubdtype(v.dtype, np.number):
        raise DataError(f"{path}: vectors must be numeric (N, T, M, 2), got shape {v.shape} "
                        f"dtype {v.dtype}")
    N, Tn, M, _ = v.shape
    if N == 0:
        raise DataError(f"{path}: vectors hold no windows (N=0)")
    if Tn < T:
        raise DataError(f"{path}: window T={T} frames is longer than the npz windows "
                        f"({Tn} frames)")
    sl = slice(Tn - T, Tn)      # the last T frames of longer windows
    v = v[:, sl].astype(np.float32)

    def per_window(key, shape_tail, kind):
        if key not in data:
            return None
        a = np.asarray(data[key])
        if a.shape[:1] != (N,) or (shape_tail is not None and a.shape[1:] != shape_tail):
            want = f"({N}{''.join(', ' + str(s) for s in shape_tail or ())})"
            raise DataError(f"{path}: {key} has shape {a.shape}, expected {want}")
        if kind == "num" and not np.issubdtype(a.dtype, np.number) and a.dtype != bool:
            raise DataError(f"{path}: {key} must be numeric, got dtype {a.dtype}")
        return a

    lost = per_window("lost", (Tn, M), None)
    lost = np.zeros((N, T, M), bool) if lost is None else lost[:, sl].astype(bool)
    bad = ~np.isfinite(v).all(axis=3)
    lost |= bad
    v[lost] = 0.0
    imu = per_window("imu", (Tn, IMU_CHANNELS), "num")
    if imu is not None:
        imu = imu[:, sl].astype(np.float32)
        if not np.isfinite(imu).all():
            raise DataError(f"{path}: imu has NaN or inf values")
    labels = targets = None
    if task == "pressure":
        if label is not None:
            targets = np.full(N, float(label))
        else:
            t = per_window("targets", (), "num")
            if t is None:
                raise DataError(f"{path}: task pressure needs 'targets' (N,) floats; keys are "
                                f"{sorted(data)}")
            targets = t.astype(np.float64)
            if not np.isfinite(targets).all():
                raise DataError(f"{path}: targets has {int((~np.isfinite(targets)).sum())} "
                                f"NaN or inf values")
    else:
        if label is not None:
            labels = np.full(N, label, object)
        else:
            lab = per_window("labels", (), None)
            if lab is None:
                raise DataError(f"{path}: task {task} needs 'labels' (N,) strings; keys are "
                                f"{sorted(data)}")
            if lab.dtype.kind not in "US":
                raise DataError(f"{path}: labels must be strings, got dtype {lab.dtype}")
            labels = lab.astype(str).astype(object)
    c = per_window("contact", (), None)
    if c is not None:
        contact, contact_from = c.astype(bool), "npz"
    else:
        from device.profile import load_pipeline_profile

        thr = load_pipeline_profile(profile).contact_px
        last = v[:, -1]
        ok = ~lost[:, -1]
        n_ok = ok.sum(axis=1)
        mean_mag = np.where(n_ok > 0, (np.hypot(last[..., 0], last[..., 1]) * ok).sum(axis=1)
                            / np.maximum(n_ok, 1), 0.0)
        contact, contact_from = mean_mag > thr, "vectors"
    g = per_window("groups", (), "num")
    if g is None:
        groups = np.arange(N, dtype=np.int64)
    else:
        _, groups = np.unique(g, return_inverse=True)
        groups = groups.astype(np.int64)
    keep = contact if contact_only else np.ones(N, bool)
    trials = [{"kind": "npz", "path": str(path), "group": int(i)}
              for i in range(int(groups.max()) + 1)]
    ws = WindowSet(task=task, window=T, vectors=v, lost=lost, imu=imu, grids=None, frames=None,
                   contact=contact, labels=labels, targets=targets, groups=groups,
                   t_index=np.full(N, -1, np.int64), trial_len=np.full(N, -1, np.int64),
                   source={"specs": [str(path)], "trials": trials, "windows_cut": N,
                           "windows_kept": int(keep.sum()), "contact_only": contact_only,
                           "kept_fraction": float(keep.mean()), "contact_from": contact_from,
                           "notes": []})
    if contact_only:
        src = ws.source
        ws = ws.subset(np.flatnonzero(keep))
        ws.source = src
    return _finalise(ws, min_classes, str(path))


# ----------------------------------------------------------------------------
# The entry point
# ----------------------------------------------------------------------------

def load_spec(spec: str, task: str, window: int, contact_only: bool = False,
              profile: str = "roboskin", progress: bool = True, *, stride: int = 1,
              frame_size: int | None = DEFAULT_FRAME_SIZE, min_classes: int = 2,
              cache: dict | None = None) -> WindowSet:
    """Windows of ``window`` frames for ``task`` from one data SPEC.

    ``spec``: a CSV manifest (``.csv``), a dataset folder (has ``dataset.json``) or an
    ``.npz`` of vectors. ``contact_only`` drops windows whose last frame has no
    contact (otherwise, for surface and texture, they are labelled ``no-touch``).
    ``stride``: frames between the last frames of consecutive windows.
    ``frame_size``: side S of the downscaled binary crops (None or 0: no crops).
    ``min_classes``: fewer classes than this is an error (1 for evaluation data).
    ``cache``: a dict to share extracted clip features between calls.
    """
    _check_task(task)
    T = _check_int("window", window, 1)
    stride = _check_int("stride", stride, 1)
    min_classes = _check_int("min_classes", min_classes, 1)
    if frame_size:
        frame_size = _check_int("frame_size", frame_size, 1)
    else:
        frame_size = None
    if not isinstance(spec, (str, Path)) or not str(spec).strip():
        raise DataError(f"data spec must be a path, got spec={spec!r}")
    cache = {} if cache is None else cache
    p = Path(spec).expanduser()
    suffix = p.suffix.lower()
    if suffix == ".csv":
        return _load_manifest(p, task, T, stride, contact_only, profile, frame_size, progress,
                              cache, min_classes)
    if suffix == ".npz":
        if not p.is_file():
            raise DataError(f"no such file: {p}")
        return _load_npz(p, task, T, contact_only, profile, min_classes=min_classes)
    if p.is_dir():
        if not (p / "dataset.json").is_file():
            raise DataError(f"{p}: a folder spec must be a dataset folder (with dataset.json); "
                            f"to use a folder of images, list it in a CSV manifest")
        return _load_dataset(p, task, T, stride, contact_only, profile, frame_size, progress,
                             cache, min_classes)
    if not p.exists():
        raise DataError(f"no such data spec: {p} (a .csv manifest, a dataset folder or an .npz)")
    raise DataError(f"data spec {p}: not a .csv manifest, a dataset folder or an .npz")


def load_specs(specs: Iterable[str], task: str, window: int, contact_only: bool = False,
               profile: str = "roboskin", progress: bool = True, **kw) -> WindowSet:
    """:func:`load_spec` for each of several specs (``--data A --data B``), concatenated,
    with one feature cache."""
    specs = list(specs)
    if not specs:
        raise DataError("no data specs given")
    cache = kw.pop("cache", None)
    cache = {} if cache is None else cache
    min_classes = kw.pop("min_classes", 2)
    sets = [load_spec(s, task, window, contact_only, profile, progress, cache=cache,
                      min_classes=1, **kw) for s in specs]
    ws = WindowSet.concat(sets)
    return _finalise(ws, min_classes, " + ".join(str(s) for s in specs))


# ----------------------------------------------------------------------------
# Splits that never leak
# ----------------------------------------------------------------------------

def _group_labels(ws: WindowSet, uniq: np.ndarray, inv: np.ndarray) -> np.ndarray:
    """The most common label of each group ('' for regression)."""
    if ws.labels is None:
        return np.array([""] * len(uniq), object)
    out = []
    lab = ws.labels.astype(str)
    for g in range(len(uniq)):
        names, counts = np.unique(lab[inv == g], return_counts=True)
        out.append(names[np.argmax(counts)])
    return np.array(out, object)


def split_grouped(ws: WindowSet, test_frac: float = 0.3, seed: int = 0
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(train_idx, test_idx): whole trials to one side, about ``test_frac`` of the
    trials to test, spread over the trials' majority labels."""
    if not (isinstance(test_frac, (int, float)) and 0.0 < test_frac < 1.0):
        raise DataError(f"test_frac must be between 0 and 1, got test_frac={test_frac!r}")
    uniq, inv = np.unique(ws.groups, return_inverse=True)
    n = len(uniq)
    if n < 2:
        raise DataError(f"split_grouped needs at least 2 groups (trials), the data have {n}; "
                        f"use split_time to split within a trial")
    rng = np.random.default_rng(seed)
    order = rng.permutation(n)
    glab = _group_labels(ws, uniq, inv)
    order = order[np.argsort(glab[order].astype(str), kind="stable")]
    pos = np.arange(n)
    u = rng.random()             # systematic sampling: test_frac of each label's trials
    pick = np.floor((pos + 1) * test_frac + u) > np.floor(pos * test_frac + u)
    test_groups = order[pick]
    if len(test_groups) == 0:
        test_groups = order[:1]
    if len(test_groups) == n:
        test_groups = order[1:]
    is_test = np.isin(inv, test_groups)
    return np.flatnonzero(~is_test), np.flatnonzero(is_test)


def split_time(ws: WindowSet, train_frac: float = 0.7, gap: int | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
    """(train_idx, test_idx) within each trial: windows that end in the first
    ``train_frac`` of its frames to train, windows that start at least ``gap`` frames
    (default T) after that to test. No window overlaps both sides."""
    if not (isinstance(train_frac, (int, float)) and 0.0 < train_frac < 1.0):
        raise DataError(f"train_frac must be between 0 and 1, got train_frac={train_frac!r}")
    T = ws.window
    gap = T if gap is None else gap
    if isinstance(gap, bool) or not isinstance(gap, (int, np.integer)) or gap < 0:
        raise DataError(f"gap must be a whole number of frames >= 0, got gap={gap!r}")
    if (ws.t_index < 0).any():
        raise DataError("split_time: some windows have no time order (from an .npz); "
                        "use split_grouped")
    boundary = np.floor(train_frac * ws.trial_len).astype(np.int64)
    first = ws.t_index - T + 1
    train = ws.t_index < boundary
    test = first >= boundary + gap
    if not train.any() or not test.any():
        raise DataError(f"split_time: train_frac={train_frac} with gap={gap} leaves "
                        f"{int(train.sum())} train and {int(test.sum())} test windows; "
                        f"the trials are too short for T={T}")
    return np.flatnonzero(train), np.flatnonzero(test)


def group_kfold(ws: WindowSet, k: int, seed: int = 0
                ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """K folds of whole trials: yields (train_idx, test_idx) ``k`` times. Each trial
    is in exactly one test fold; folds are balanced by window count."""
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 2:
        raise DataError(f"k must be a whole number >= 2, got k={k!r}")
    uniq, inv = np.unique(ws.groups, return_inverse=True)
    if len(uniq) < k:
        raise DataError(f"too few groups for {k} folds: the data have {len(uniq)} trials "
                        f"(groups); use k <= {len(uniq)} or more trials")
    sizes = np.bincount(inv, minlength=len(uniq))
    rng = np.random.default_rng(seed)
    order = rng.permutation(len(uniq))
    order = order[np.argsort(-sizes[order], kind="stable")]
    fold_of = np.empty(len(uniq), np.int64)
    load = np.zeros(k, np.int64)
    for i, g in enumerate(order):
        f = i if i < k else int(np.argmin(load))   # every fold gets a trial first
        fold_of[g] = f
        load[f] += sizes[g]
    win_fold = fold_of[inv]

    def gen():
        for f in range(k):
            yield np.flatnonzero(win_fold != f), np.flatnonzero(win_fold == f)

    return gen()
