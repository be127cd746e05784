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
vectors are put on the profile's fixed pin layout (:mod:`host.data.extract`). A
window is cut wherever all its T frames have a reference; its label, contact flag
and target are those of its last frame, where the decision is made.

A *trial* is one recording: a clip file, a ``sim://`` scene with its seed, a trial of
a dataset folder, or a group of an ``.npz``. ``groups`` holds its id, so splits can
keep trials apart (:func:`host.data.splits.split_grouped`,
:func:`host.data.splits.group_kfold`), and ``t_index`` / ``trial_len`` place each
window in it (:func:`host.data.splits.split_time`).
"""
from __future__ import annotations

from pathlib import Path
from typing import Iterable

from host.data.spec_csv import load_manifest
from host.data.spec_folder import load_dataset
from host.data.spec_npz import load_npz
from host.data.windows import (DEFAULT_FRAME_SIZE, DataError, WindowSet, check_int, check_task,
                               finalise)


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
    check_task(task)
    T = check_int("window", window, 1)
    stride = check_int("stride", stride, 1)
    min_classes = check_int("min_classes", min_classes, 1)
    if frame_size:
        frame_size = check_int("frame_size", frame_size, 1)
    else:
        frame_size = None
    if not isinstance(spec, (str, Path)) or not str(spec).strip():
        raise DataError(f"data spec must be a path, got spec={spec!r}")
    cache = {} if cache is None else cache
    p = Path(spec).expanduser()
    suffix = p.suffix.lower()
    if suffix == ".csv":
        return load_manifest(p, task, T, stride, contact_only, profile, frame_size, progress,
                              cache, min_classes)
    if suffix == ".npz":
        if not p.is_file():
            raise DataError(f"no such file: {p}")
        return load_npz(p, task, T, contact_only, profile, min_classes=min_classes)
    if p.is_dir():
        if not (p / "dataset.json").is_file():
            raise DataError(f"{p}: a folder spec must be a dataset folder (with dataset.json); "
                            f"to use a folder of images, list it in a CSV manifest")
        return load_dataset(p, task, T, stride, contact_only, profile, frame_size, progress,
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
    return finalise(ws, min_classes, " + ".join(str(s) for s in specs))
