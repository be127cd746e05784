"""The tacfoot dataset folder (documented in docs/datasets.md).

::

    DIR/
      dataset.json        index: format, version, label names, one entry per trial
      trial_0000.npz      frames (F, H, W) uint8 + per-frame ground truth
      trial_0001.npz      ...

Every file is written to a temporary name in the same folder and then renamed,
so a crash loses at most the trial being written, and ``dataset.json`` always
lists only complete trials. A temporary name carries its writer's process id
(``.trial_0003.npz.pid1234.x8f2.tmp``), so the next writer removes the temporary
files (and folders) of writers that are no longer running.

One writer at a time: :class:`DatasetWriter` holds an exclusive advisory lock
(``fcntl.flock``) on the folder itself while it is open, and a second writer is
refused with :class:`DatasetLocked`. The folder, not ``dataset.json``, is locked,
because the index is replaced (a new inode) on every write. Readers take no lock:
they see the last complete index. (:func:`lock_folder` is that lock; ``host train``
takes it on its ``--out`` folder too.)

An index that lists a trial file twice, or a trial file that is not in the folder,
is refused when read (and so when a writer opens it to append), naming the entries.

Frames are stored as ``frames`` (F, H, W) uint8 in the compressed npz, or, for a
trial recorded from a video file that covers at least half of the file's frames
(``host record`` of a file), as the file's own bytes (``video``, ``video_suffix``,
``video_range`` = [start, end) frame numbers; the entry's ``frames_codec`` is
``source-video``): lossless with respect to the frames the recorder read, since
the writer decodes the stored bytes and keeps them only when they give exactly
those frames (else it stores ``frames``), and the size of the source video
(roboskin/smooth.avi: 4.0 MB, where the compressed frame array takes 52.6 MB).
:func:`load_trial` gives ``frames`` either way.

Each trial entry records its ``source`` (``simulator``, ``rig``, ``record``); the
index's ``source`` is the one they share, or ``"mixed"`` with the list in
``sources``.
"""
from __future__ import annotations

import errno
import fcntl
import json
import os
import re
import shutil
import tempfile
import zipfile
import zlib
from pathlib import Path

import numpy as np

from device.jsondoc import read_json_doc
from device.closing import Closing
from device.errors import TacfootError

FORMAT = "tacfoot-dataset"
VERSION = 1
INDEX = "dataset.json"


class DatasetError(TacfootError, ValueError):
    pass


class DatasetLocked(DatasetError):
    """Another writer has the dataset folder open."""


#: a temporary file's name: ``.NAME.pid<PID>.<random>.tmp``
_TMP_RE = re.compile(r"^\..*\.pid(\d+)\.[^.]*\.tmp$")


def temp_prefix(name: str) -> str:
    """The start of a temporary file's name for ``name``, with this process's id."""
    return f".{name}.pid{os.getpid()}."


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:          # someone else's live process
        return True
    return True


def _remove(p: Path) -> bool:
    try:
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        else:
            p.unlink()
        return True
    except FileNotFoundError:
        return False


def remove_stale_temp_files(folder: Path | str) -> int:
    """Remove the temporary files and folders in ``folder`` whose writer process is
    gone; the count removed. Those of live processes, and names without a process id,
    stay."""
    n = 0
    for p in Path(folder).glob(".*.tmp"):
        m = _TMP_RE.match(p.name)
        if m is None or int(m.group(1)) == os.getpid() or _alive(int(m.group(1))):
            continue
        n += _remove(p)
    return n


#: a temporary folder in the system's temp folder: ``tacfoot-KIND-pid<PID>-<random>``
_SYS_TMP_RE = re.compile(r"^tacfoot-[a-z]+-pid(\d+)-")


def system_temp_dir(kind: str) -> Path:
    """A new temporary folder ``tacfoot-KIND-pid<PID>-...`` in the system's temp
    folder, after removing those of processes that are no longer running (a run
    killed with SIGKILL leaves its own behind); the caller removes it."""
    root = Path(tempfile.gettempdir())
    for p in root.glob("tacfoot-*-pid*"):
        m = _SYS_TMP_RE.match(p.name)
        if m is not None and int(m.group(1)) != os.getpid() and not _alive(int(m.group(1))):
            _remove(p)
    return Path(tempfile.mkdtemp(prefix=f"tacfoot-{kind}-pid{os.getpid()}-", dir=root))


def atomic_write(path: Path, write) -> None:
    """Call ``write(fh)`` on a temp file beside ``path``, fsync, then rename."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=temp_prefix(path.name), suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)        # mkstemp makes 0600; use the usual mode
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def write_npz(fh, arrays: dict, level: int = 1) -> None:
    """``arrays`` as an .npz (what ``np.load`` reads) deflated at ``level``: level 1
    stores a trial's frames as small as ``np.savez_compressed``'s level 6 (camera
    noise does not compress further) in under half the time."""
    with zipfile.ZipFile(fh, "w", compression=zipfile.ZIP_DEFLATED,
                         compresslevel=int(level)) as z:
        for name, a in arrays.items():
            with z.open(f"{name}.npy", "w", force_zip64=True) as f:
                np.lib.format.write_array(f, np.asanyarray(a), allow_pickle=False)


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write(path, lambda fh: fh.write(text.encode()))


def lock_folder(folder: Path | str, busy: str) -> int:
    """Take the exclusive advisory lock (``fcntl.flock``) on the existing folder
    ``folder``; the descriptor that holds it (closing it releases the lock, as
    does the end of the process). When another open holds it: DatasetLocked,
    ``"{folder}: {busy}"``. A dataset's writer and ``host train --out`` lock their
    folder this way."""
    fd = os.open(folder, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        os.close(fd)
        if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            raise DatasetLocked(f"{folder}: {busy}") from None
        raise
    return fd


class DatasetWriter(Closing):
    """Append trials to a dataset folder, one atomic file each, holding the folder's
    writer lock until :meth:`close` (or the end of a ``with`` block, or the
    process). ``meta["source"]`` is the source of the trials this writer adds."""

    def __init__(self, out_dir: Path | str, meta: dict | None = None,
                 source: str | None = None):
        self.dir = Path(out_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        self._lock_fd: int | None = None
        self._lock_fd = lock_folder(
            self.dir, "another writer is adding trials to this dataset; wait for it to "
                      "finish, or choose another folder")
        try:
            self.removed_temp_files = remove_stale_temp_files(self.dir)
            idx = self.dir / INDEX
            if idx.exists():
                self.index = read_index(self.dir)
            else:
                self.index = {"format": FORMAT, "version": VERSION, "trials": []}
        except BaseException:
            self.close()
            raise
        meta = dict(meta or {})
        self.source = source or meta.pop("source", None)
        old = self.index.get("source")
        if old not in (None, "mixed"):
            for t in self.index["trials"]:   # an index with one source for all its trials
                if isinstance(t, dict):
                    t.setdefault("source", old)
        self.index.update(meta)

    def close(self) -> None:
        """Release the folder's writer lock."""
        fd, self._lock_fd = self._lock_fd, None
        if fd is not None:
            os.close(fd)              # closing the descriptor drops the flock

    @property
    def n_trials(self) -> int:
        return len(self.index["trials"])

    def _update_sources(self) -> None:
        sources = sorted({t["source"] for t in self.index["trials"]
                          if isinstance(t, dict) and t.get("source")})
        self.index.pop("sources", None)
        if len(sources) == 1:
            self.index["source"] = sources[0]
        elif sources:
            self.index["source"] = "mixed"
            self.index["sources"] = sources

    def add_trial(self, frames: np.ndarray, truth: dict, info: dict,
                  video: Path | str | None = None, video_start: int = 0) -> Path:
        """Write a trial; ``video``: the video file the frames were read from, from
        frame ``video_start`` on (stored instead of the frames when it decodes to
        exactly them and the frames are at least half of the file's)."""
        if self._lock_fd is None:
            raise DatasetError(f"{self.dir}: the writer is closed")
        listed = {t["file"] for t in self.index["trials"]}
        k = self.n_trials
        while f"trial_{k:04d}.npz" in listed or (self.dir / f"trial_{k:04d}.npz").exists():
            k += 1                       # never a listed name, nor a file left in the folder
        name = f"trial_{k:04d}.npz"
        got = _video_arrays(video, video_start, frames) if video is not None else None
        arrays = got if isinstance(got, dict) else None
        codec = "source-video" if arrays else "npz"
        arrays = arrays or {"frames": np.ascontiguousarray(frames)}
        for k, v in truth.items():
            arrays[k] = np.asarray(v)
        atomic_write(self.dir / name, lambda fh: write_npz(fh, arrays))
        entry = {"file": name, "frames": int(frames.shape[0]), "frames_codec": codec,
                 "bytes": int((self.dir / name).stat().st_size), **info}
        if isinstance(got, str):          # why the video was not kept
            entry["frames_note"] = "; ".join(x for x in (entry.get("frames_note"), got) if x)
        if self.source and "source" not in entry:
            entry["source"] = self.source
        self.index["trials"].append(entry)
        self._update_sources()
        atomic_write_text(self.dir / INDEX, json.dumps(self.index, indent=1))
        return self.dir / name


def _grey(img: np.ndarray) -> np.ndarray:
    if img.ndim == 3:
        import cv2
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    return np.ascontiguousarray(img, np.uint8)


def decode_video(data: bytes, suffix: str, start: int, end: int) -> np.ndarray:
    """Frames ``start`` .. ``end - 1`` (grey, uint8) of a video file's bytes, read as
    ``host record`` reads a file source (through a file in a temporary folder of the
    system's, :func:`system_temp_dir`)."""
    d = system_temp_dir("video")
    try:
        p = d / f"video{suffix}"
        p.write_bytes(data)
        return _decode_file(p, start, end)
    finally:
        shutil.rmtree(d, ignore_errors=True)


def _decode_file(path: Path, start: int, end: int) -> np.ndarray:
    from device.pi.sources.camera import open_camera
    with open_camera(str(path), start_frame=int(start), end_frame=int(end)) as cam:
        out = [_grey(fr.image) for fr in cam]
    return np.stack(out) if out else np.zeros((0, 0, 0), np.uint8)


def _same_frames(path: Path, start: int, frames: np.ndarray) -> bool:
    """Whether the video file decodes, from frame ``start``, to exactly ``frames``
    (compared one frame at a time)."""
    from device.pi.sources.camera import open_camera
    n = int(frames.shape[0])
    k = 0
    with open_camera(str(path), start_frame=int(start), end_frame=int(start) + n) as cam:
        for fr in cam:
            img = _grey(fr.image)
            if k >= n or img.shape != frames.shape[1:] or not np.array_equal(img, frames[k]):
                return False
            k += 1
    return k == n


def _video_arrays(video, start: int, frames: np.ndarray) -> dict | str:
    """The ``video`` arrays of a trial when the file decodes to exactly ``frames``
    from ``start`` and the frames are at least half of the file's; else why not (the
    entry's ``frames_note``). The file's frames are counted (up to twice the trial's),
    not taken from its container's estimate, and its bytes are read only when kept."""
    from device.pi.sources.camera import CameraError
    from host.data.video import count_frames
    n = int(frames.shape[0])
    total = count_frames(video, 2 * n + 1)
    if 2 * n < total:
        return (f"stored as frames: {n} frames are under half of the video's (it has "
                f"more than {2 * n})")
    try:
        same = _same_frames(Path(video), start, frames)
    except (CameraError, OSError, ValueError) as exc:
        return f"stored as frames: the video does not decode ({exc})"
    if not same:
        return "stored as frames: the video does not decode to exactly the frames read"
    data = Path(video).read_bytes()
    return {"video": np.frombuffer(data, np.uint8), "video_suffix": np.array(Path(video).suffix),
            "video_range": np.array([start, start + n], np.int64)}


def read_index(path: Path | str, check_files: bool = True) -> dict:
    """A dataset folder's index; a DatasetError names the file when it is not one,
    or when ``trials`` is not a list of entries that each name a trial file and
    its frame count. A file listed twice (its windows would be trained and tested
    on) and, with ``check_files``, a listed file that is not in the folder are
    DatasetErrors naming them."""
    doc, file = read_json_doc(path, INDEX, FORMAT, VERSION, "dataset", "index", DatasetError)
    trials = doc.get("trials", [])
    if not isinstance(trials, list):
        raise DatasetError(f"{file}: trials must be a list of trial entries, got {trials!r:.60}")
    first: dict[str, int] = {}
    twice = []
    for i, e in enumerate(trials):
        if (not isinstance(e, dict) or not isinstance(e.get("file"), str)
                or Path(e["file"]).name != e["file"] or not e["file"].endswith(".npz")):
            raise DatasetError(f"{file}: trials[{i}] must be an entry naming its .npz file in "
                               f"the folder, got {e!r:.60}")
        n = e.get("frames", 0)
        if isinstance(n, bool) or not isinstance(n, int) or n < 0:
            raise DatasetError(f"{file}: trials[{i}].frames must be a whole number >= 0, "
                               f"got {n!r}")
        if e["file"] in first:
            twice.append(f"trials[{i}] {e['file']} (also trials[{first[e['file']]}])")
        first.setdefault(e["file"], i)
    if twice:
        raise DatasetError(f"{file}: {len(twice)} trial file(s) listed twice: "
                           f"{_some(twice)}; remove the repeated entries")
    if check_files:
        missing = [f"trials[{i}] {e['file']}" for i, e in enumerate(trials)
                   if not (file.parent / e["file"]).is_file()]
        if missing:
            raise DatasetError(f"{file}: {len(missing)} listed trial file(s) missing from "
                               f"{file.parent}: {_some(missing)}; restore them or remove "
                               f"their entries")
    doc["trials"] = trials
    return doc


def _some(names: list[str], n: int = 5) -> str:
    return ", ".join(names[:n]) + (f" and {len(names) - n} more" if len(names) > n else "")


def load_trial(dataset_dir: Path | str, i: int) -> dict:
    """Trial ``i``'s arrays and its index entry (``info``); a missing, truncated or
    corrupt trial file is a DatasetError naming it."""
    doc = read_index(dataset_dir, check_files=False)
    try:
        entry = doc["trials"][i]
    except IndexError:
        raise DatasetError(f"{dataset_dir}: no trial {i} (has {len(doc['trials'])})") from None
    file = Path(dataset_dir) / entry["file"]
    try:
        with np.load(file, allow_pickle=False) as z:
            out = {k: z[k] for k in z.files if not k.startswith("video")}
            if "frames" not in out and "video" in z.files:
                a, b = (int(x) for x in z["video_range"])
                out["frames"] = decode_video(z["video"].tobytes(), str(z["video_suffix"]), a, b)
                if out["frames"].shape[0] != b - a:
                    raise DatasetError(f"{file}: the stored video gives "
                                       f"{out['frames'].shape[0]} frames, not {b - a}")
            return out | {"info": entry}
    except FileNotFoundError:
        raise DatasetError(f"{file}: trial file missing") from None
    except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError, KeyError) as exc:
        raise DatasetError(f"{file}: corrupt or truncated trial file ({exc})") from None


def is_dataset(path: Path | str) -> bool:
    return (Path(path) / INDEX).is_file()


def addable_folder(path: Path | str, also: tuple[str, ...] = ()) -> bool:
    """A folder a :class:`DatasetWriter` may add trials to: a dataset, or one a writer
    was stopped in before its first trial was complete (it holds only writers'
    temporary ``.*.tmp`` files, and files named in ``also``). ``path`` is a folder."""
    return is_dataset(path) or all(
        (f.name.startswith(".") and f.name.endswith(".tmp")) or f.name in also
        for f in Path(path).iterdir())
