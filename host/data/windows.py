"""Windows of T frames: the :class:`WindowSet` every data spec loads into, and
cutting the windows of one trial's per-frame features.

A *trial* is one recording: a clip file, a ``sim://`` scene with its seed, a trial of
a dataset folder, or a group of an ``.npz``. ``groups`` holds its id, so splits can
keep trials apart (:mod:`host.data.splits`), and ``t_index`` / ``trial_len`` place
each window in it. A window is cut wherever all its T frames have a reference; its
label, contact flag and target are those of its last frame, where the decision is
made.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Iterable

import numpy as np

from device.checks import whole_number
from device.pi.protocol import SURFACE_CLASSES
from host.data.errors import DataError  # re-exported: the old home of DataError

if TYPE_CHECKING:
    from host.data.extract import ClipFeatures

TASKS = ("surface", "texture", "slip", "pressure")
CLASS_TASKS = ("surface", "texture", "slip")
NO_TOUCH = "no-touch"
SLIP_LABELS = ("no-slip", "slip")          # slip task labels from a dataset folder
#: the tasks whose classes are fixed (the surface link's classes; slip or not); texture
#: labels are the user's own names
FIXED_CLASSES = {"surface": SURFACE_CLASSES, "slip": SLIP_LABELS}
#: a label of the user's own (a texture class, ``host record --label``): 1-64 letters,
#: digits, '-', '_' and '.', starting with a letter or digit
LABEL_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")
#: names the loader and the simulator give frames without contact; never a class name
RESERVED_LABELS = ("none", NO_TOUCH)
IMU_CHANNELS = 6                            # ax, ay, az [g], gx, gy, gz [deg/s]
DEFAULT_FRAME_SIZE = 32


# ----------------------------------------------------------------------------
# The window set
# ----------------------------------------------------------------------------

_PER_WINDOW = ("vectors", "lost", "imu", "grids", "frames", "contact", "labels", "targets",
               "groups", "t_index", "trial_len", "recordings", "frame_index", "session")


@dataclass
class WindowSet:
    """N windows of T frames. Plain numpy arrays, one row per window.

    ``t_index`` is the window's last frame counted from its trial's first frame and
    ``trial_len`` the trial's length in frames; both are -1 for ``.npz`` windows,
    which carry no time order. ``recordings`` holds each window's recording id
    (:mod:`host.data.recordings`; several trials can share one, e.g. two parts of a
    clip) and ``frame_index`` its last frame counted in that recording (-1 when
    unknown); both are None when the loader knows no recordings, and
    :meth:`recording_ids` then gives one recording per trial. ``source`` says where the windows came from
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
    recordings: np.ndarray | None = None   # (N,) str (object) recording id
    frame_index: np.ndarray | None = None  # (N,) int64, last frame in the recording
    #: (N, T, 3) float32 per-frame session statistics (host.data.extract.SESSION_STATS:
    #: brightness, contrast, interval between frames), None when the loader has none
    session: np.ndarray | None = None

    def recording_ids(self) -> np.ndarray:
        """(N,) recording id of each window; without ``recordings``, one per trial
        (``"trial:G"``)."""
        if self.recordings is not None:
            return self.recordings
        return np.array([f"trial:{int(g)}" for g in self.groups], object)

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
        for k in ("imu", "grids", "frames", "session"):
            have = [getattr(s, k) is not None for s in sets]
            if all(have):
                shapes = {getattr(s, k).shape[2:] for s in sets}
                if len(shapes) > 1:
                    raise DataError(f"concat: {k} shapes differ between sets: {sorted(shapes)}")
                out[k] = np.concatenate([getattr(s, k) for s in sets])
            else:
                out[k] = None
                if any(have) and k != "session":
                    notes.append(f"{k} dropped: sets {[i for i, h in enumerate(have) if not h]} "
                                 f"have none")
        for k in ("labels", "targets"):
            have = [getattr(s, k) is not None for s in sets]
            out[k] = np.concatenate([getattr(s, k) for s in sets]) if all(have) else None
        groups, trials, recs, offset = [], [], [], 0
        for s in sets:
            uniq, inv = np.unique(s.groups, return_inverse=True)
            groups.append(inv.astype(np.int64) + offset)
            recs.append(s.recordings if s.recordings is not None else
                        np.array([f"trial:{int(g) + offset}" for g in inv], object))
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
                                          for c in as_list(s.source.get("contact_from"))}),
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
                   classes=classes, source=source,
                   recordings=(np.concatenate(recs) if any(s.recordings is not None
                                                            for s in sets) else None),
                   frame_index=np.concatenate([s.frame_index if s.frame_index is not None
                                               else np.full(len(s), -1, np.int64)
                                               for s in sets]), **out)

    def summary(self) -> dict:
        """A JSON-able summary (for manifests and ``--json`` output)."""
        d = {"task": self.task, "window": self.window, "windows": len(self),
             "trials": int(len(np.unique(self.groups))), "pins": self.n_pins,
             "imu": self.imu is not None, "kept_fraction": round(self.kept_fraction, 6),
             "classes": list(self.classes)}
        rid, counts = np.unique(self.recording_ids().astype(str), return_counts=True)
        d["recordings"] = {str(r): int(c) for r, c in zip(rid, counts)}
        if self.labels is not None:
            names, counts = np.unique(self.labels.astype(str), return_counts=True)
            d["class_counts"] = {str(n): int(c) for n, c in zip(names, counts)}
        if self.targets is not None and len(self):
            d["target_range"] = [float(self.targets.min()), float(self.targets.max())]
        return d


def as_list(v) -> list:
    if v is None:
        return []
    return list(v) if isinstance(v, (list, tuple)) else [v]


# ----------------------------------------------------------------------------
# Cutting windows
# ----------------------------------------------------------------------------

def window_ends(ready: np.ndarray, start: int, end: int, T: int, stride: int
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
class TrialPart:
    """Windows of one trial, before they become a WindowSet."""

    clip: ClipFeatures
    ends: np.ndarray          # last-frame index of each window, in the clip
    labels: np.ndarray | None
    targets: np.ndarray | None
    contact: np.ndarray
    imu: np.ndarray | None    # (F, 6) per clip frame
    trial: tuple              # key of the trial: one group per key
    span_start: int
    span_len: int
    recording: str = ""       # the recording's id ("": one per trial)
    frame_offset: int = 0     # the clip's frame 0 is this frame of the recording


def stack_parts(parts: list[TrialPart], task: str, T: int, trials: dict) -> dict:
    """Stack the windows of ``parts`` into per-window arrays."""
    offs = np.arange(-T + 1, 1, dtype=np.int64)
    keys = list(trials)
    out = {k: [] for k in ("vectors", "lost", "grids", "frames", "imu", "contact", "labels",
                           "targets", "groups", "t_index", "trial_len", "recordings",
                           "frame_index", "session")}
    for p in parts:
        ix = p.ends[:, None] + offs[None, :]
        out["vectors"].append(p.clip.vectors[ix])
        out["lost"].append(p.clip.lost[ix])
        out["grids"].append(p.clip.grids[ix])
        out["frames"].append(None if p.clip.frames is None else p.clip.frames[ix])
        sess = getattr(p.clip, "session", None)
        out["session"].append(None if sess is None else sess[ix])
        out["imu"].append(None if p.imu is None else p.imu[ix].astype(np.float32))
        out["contact"].append(p.contact)
        out["labels"].append(p.labels)
        out["targets"].append(p.targets)
        n = len(p.ends)
        out["groups"].append(np.full(n, keys.index(p.trial), np.int64))
        out["t_index"].append(p.ends - p.span_start)
        out["trial_len"].append(np.full(n, p.span_len, np.int64))
        rec = p.recording or f"trial:{keys.index(p.trial)}"
        out["recordings"].append(np.full(n, rec, object))
        out["frame_index"].append(p.ends.astype(np.int64) + int(p.frame_offset))
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

def check_task(task) -> str:
    if task not in TASKS:
        raise DataError(f"task must be one of {list(TASKS)}, got task={task!r}")
    return task


def check_int(name: str, value, lo: int) -> int:
    return whole_number(name, value, lo, error=DataError)


def finalise(ws: WindowSet, min_classes: int, spec: str) -> WindowSet:
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


def check_label_name(label, where: str, error: type[ValueError] = DataError,
                     allow: tuple[str, ...] = ()) -> None:
    """``error`` naming ``where`` unless ``label`` is a name of the user's own class
    (:data:`LABEL_RE`, not one of :data:`RESERVED_LABELS` except those in ``allow``):
    ``no-touch`` would merge with the windows without contact, and a newline or a
    5,000-character name has no place in a manifest, a plot or a log line. The one
    rule for ``host record --label`` and the texture labels ``host train`` reads."""
    if isinstance(label, str) and label in allow:
        return
    if not isinstance(label, str) or not LABEL_RE.fullmatch(label) or label in RESERVED_LABELS:
        raise error(f"{where} must be 1-64 letters, digits, '-', '_' or '.', starting with a "
                    f"letter or digit, and not {' or '.join(RESERVED_LABELS)}; got "
                    f"{label!r:.80}")


def check_labels(task: str, labels, where: str, indexed: bool = False,
                 allow_no_touch: bool = False) -> None:
    """A DataError naming ``where`` (the row, trial or file) when a fixed-class task
    (:data:`FIXED_CLASSES`) gets a label that is not one of its classes: a typo such as
    ``lava`` must not become a class of its own; or when a texture label breaks the
    rule of :func:`check_label_name` (``allow_no_touch``: windows already labelled
    no-touch, as an ``.npz`` marks its windows without contact, pass). ``labels`` is
    one label, or an array when ``indexed`` (the message then names the first bad
    entry)."""
    known = FIXED_CLASSES.get(task)
    if (known is None and task != "texture") or labels is None:
        return
    if not indexed:
        labels, where_i = [labels], (lambda i: where)
    else:
        def where_i(i):
            return f"{where}[{i}]"
    if known is None:               # texture: the user's own names, each checked once
        seen: set = set()
        for i, x in enumerate(labels):
            if x not in seen:
                seen.add(x)
                check_label_name(x, f"{where_i(i)}: a texture label",
                                 allow=(NO_TOUCH,) if allow_no_touch else ())
        return
    for i, x in enumerate(labels):
        if x not in known:
            raise DataError(f"{where_i(i)}: {x!r} is not a {task} class; the {task} classes "
                            f"are {', '.join(known)}")


def window_labels(task: str, label_frames: np.ndarray | None, contact: np.ndarray,
                   ) -> np.ndarray | None:
    """Per-window labels: no-touch where the last frame has no contact (surface,
    texture)."""
    if label_frames is None:
        return None
    lab = np.asarray(label_frames, object).copy()
    if task in ("surface", "texture"):
        lab[~contact] = NO_TOUCH
    return lab


def keep_contact(parts: list[TrialPart], contact_only: bool) -> tuple[list[TrialPart], int, int]:
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
