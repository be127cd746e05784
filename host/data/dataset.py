"""The tacfoot dataset folder (documented in docs/datasets.md).

::

    DIR/
      dataset.json        index: format, version, label names, one entry per trial
      trial_0000.npz      frames (F, H, W) uint8 + per-frame ground truth
      trial_0001.npz      ...

Every file is written to a temporary name in the same folder and then renamed,
so a crash loses at most the trial being written, and ``dataset.json`` always
lists only complete trials.
"""
from __future__ import annotations

import json
import os
import tempfile
import zipfile
import zlib
from pathlib import Path

import numpy as np

from device.jsondoc import read_json_doc

FORMAT = "tacfoot-dataset"
VERSION = 1
INDEX = "dataset.json"


class DatasetError(ValueError):
    pass


def atomic_write(path: Path, write) -> None:
    """Call ``write(fh)`` on a temp file beside ``path``, fsync, then rename."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
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


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write(path, lambda fh: fh.write(text.encode()))


class DatasetWriter:
    """Append trials to a dataset folder, one atomic file each."""

    def __init__(self, out_dir: Path | str, meta: dict | None = None):
        self.dir = Path(out_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        idx = self.dir / INDEX
        if idx.exists():
            self.index = read_index(self.dir)
        else:
            self.index = {"format": FORMAT, "version": VERSION, "trials": []}
        self.index.update(meta or {})

    @property
    def n_trials(self) -> int:
        return len(self.index["trials"])

    def add_trial(self, frames: np.ndarray, truth: dict, info: dict) -> Path:
        name = f"trial_{self.n_trials:04d}.npz"
        arrays = {"frames": np.ascontiguousarray(frames)}
        for k, v in truth.items():
            arrays[k] = np.asarray(v)
        atomic_write(self.dir / name, lambda fh: np.savez_compressed(fh, **arrays))
        entry = {"file": name, "frames": int(frames.shape[0]), **info}
        self.index["trials"].append(entry)
        atomic_write_text(self.dir / INDEX, json.dumps(self.index, indent=1))
        return self.dir / name


def read_index(path: Path | str) -> dict:
    """A dataset folder's index; a DatasetError names the file when it is not one,
    or when ``trials`` is not a list of entries that each name a trial file and
    its frame count."""
    doc, file = read_json_doc(path, INDEX, FORMAT, VERSION, "dataset", "index", DatasetError)
    trials = doc.get("trials", [])
    if not isinstance(trials, list):
        raise DatasetError(f"{file}: trials must be a list of trial entries, got {trials!r:.60}")
    for i, e in enumerate(trials):
        if (not isinstance(e, dict) or not isinstance(e.get("file"), str)
                or Path(e["file"]).name != e["file"] or not e["file"].endswith(".npz")):
            raise DatasetError(f"{file}: trials[{i}] must be an entry naming its .npz file in "
                               f"the folder, got {e!r:.60}")
        n = e.get("frames", 0)
        if isinstance(n, bool) or not isinstance(n, int) or n < 0:
            raise DatasetError(f"{file}: trials[{i}].frames must be a whole number >= 0, "
                               f"got {n!r}")
    doc["trials"] = trials
    return doc


def load_trial(dataset_dir: Path | str, i: int) -> dict:
    """Trial ``i``'s arrays and its index entry (``info``); a missing, truncated or
    corrupt trial file is a DatasetError naming it."""
    doc = read_index(dataset_dir)
    try:
        entry = doc["trials"][i]
    except IndexError:
        raise DatasetError(f"{dataset_dir}: no trial {i} (has {len(doc['trials'])})") from None
    file = Path(dataset_dir) / entry["file"]
    try:
        with np.load(file, allow_pickle=False) as z:
            return {k: z[k] for k in z.files} | {"info": entry}
    except FileNotFoundError:
        raise DatasetError(f"{file}: trial file missing") from None
    except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError, KeyError) as exc:
        raise DatasetError(f"{file}: corrupt or truncated trial file ({exc})") from None


def is_dataset(path: Path | str) -> bool:
    return (Path(path) / INDEX).is_file()
