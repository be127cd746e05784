"""A CSV manifest data spec: ``path,label[,start_frame,end_frame][,imu]``, each row a
video, a folder of images, ``sim://SCENE`` or an ``.npz``, paths relative to the
manifest. Frames go through the Pi's pipeline from the first frame of each
recording (the reference is the recording's rest frame, as on the Pi); a frame
range only chooses which windows are cut."""
from __future__ import annotations

import csv
import io
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import parse_qsl, urlsplit

import numpy as np

from device.pi.sources.camera import CameraError, open_camera
from host.data.extract import ClipFeatures, extract_features
from host.data.recordings import file_recording, source_recording
from host.data.spec_npz import load_npz
from host.data.windows import (IMU_CHANNELS, DataError, TrialPart, WindowSet, check_labels,
                               finalise, keep_contact, stack_parts, window_ends, window_labels)

_log = logging.getLogger(__name__)

MANIFEST_COLUMNS = ("path", "label", "start_frame", "end_frame", "imu")


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
    # newline="": a quoted field keeps its line break (and the label rule refuses
    # it) instead of the two lines being glued into another name
    reader = csv.reader(io.StringIO(text, newline=""))
    header = None
    rows: list[_Row] = []
    base = path.parent
    for rec in reader:
        lineno = reader.line_num            # the record's last line
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
        if label:
            check_labels(task, label, f"{where}, column label")
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
        try:
            clip = extract_features(cam, profile, frame_size, n_frames=n, progress=progress,
                                    desc=Path(key).name if "://" not in key else key,
                                    fps=cam.fps)
        except CameraError as exc:      # a frame that cannot be read, e.g. a broken image
            where = (f"{exc.filename}: {exc.strerror}" if exc.filename and exc.strerror
                     else str(exc))
            raise DataError(f"{key}: cannot read a frame: {where}") from None
        if key.startswith("sim://"):
            imu = np.asarray(cam.truth["imu"], np.float64)
            clip.imu = imu[:clip.n_frames]
    cache[("clip", key, profile, frame_size)] = (clip, end)
    return clip


def load_manifest(path: Path, task: str, T: int, stride: int, contact_only: bool,
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
    parts: list[TrialPart] = []
    trials: dict = {}
    imu_missing, dropped_ref = [], 0
    for r in clip_rows:
        k = _clip_key(r)
        clip = clips[k]
        end = clip.n_frames if r.end is None else r.end
        ends, nref = window_ends(clip.ready, r.start, end, T, stride)
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
            labels = window_labels(task, np.full(len(ends), r.label, object), contact)
        if k not in trials:
            rec = source_recording(k) if r.kind == "sim" else file_recording(k)
            trials[k] = {"kind": r.kind, "path": r.path, "span_start": spans[k][0],
                         "frames": spans[k][1] - spans[k][0], "fps": clip.fps, "rows": [],
                         "recording": rec}
        trials[k]["rows"].append(r.line - 1)
        parts.append(TrialPart(clip, ends, labels, targets, contact, imu, k, spans[k][0],
                               spans[k][1] - spans[k][0], trials[k]["recording"]["id"]))
    notes = []
    if dropped_ref:
        notes.append(f"{dropped_ref} windows dropped: they start before the reference frame")
    parts, cut, kept = keep_contact(parts, contact_only)
    arrays = stack_parts(parts, task, T, trials) if parts else None
    sets = []
    if arrays is not None:
        if imu_missing and arrays["imu"] is None and len(imu_missing) < len(clip_rows):
            msg = (f"{path}: imu dropped for every window: rows {imu_missing} have no imu "
                   f"(give every row an imu .npy, or none)")
            _log.warning("%s", msg)           # one log line, not a UserWarning
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
            sets.append(load_npz(Path(r.path), task, T, contact_only, profile,
                                  label=r.label or None, where=r.where(path, "path"),
                                  min_classes=1))
    ws = WindowSet.concat(sets)      # rows is never empty, so neither is sets
    ws.source["specs"] = [str(path)]
    return finalise(ws, min_classes, str(path))


# ----------------------------------------------------------------------------
# A dataset folder
