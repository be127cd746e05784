"""An ``.npz`` data spec of marker vectors: ``vectors`` (N, T, M, 2), ``labels`` (N,)
or ``targets`` (N,), optional ``imu`` (N, T, 6), ``contact`` (N,), ``lost``
(N, T, M), ``groups`` (N,)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from device.profile import load_pipeline_profile
from host.data.windows import (IMU_CHANNELS, NO_TOUCH, DataError, WindowSet, check_label_name,
                               check_labels, finalise)


def load_npz(path: Path, task: str, T: int, contact_only: bool, profile: str,
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
            check_labels(task, labels, f"{where or path}: labels", indexed=True,
                         allow_no_touch=True)
    c = per_window("contact", (), None)
    if c is not None:
        contact, contact_from = c.astype(bool), "npz"
    else:
        thr = load_pipeline_profile(profile).contact_px
        last = v[:, -1]
        ok = ~lost[:, -1]
        n_ok = ok.sum(axis=1)
        mean_mag = np.where(n_ok > 0, (np.hypot(last[..., 0], last[..., 1]) * ok).sum(axis=1)
                            / np.maximum(n_ok, 1), 0.0)
        contact, contact_from = mean_mag > thr, "vectors"
    if task == "texture" and labels is not None:
        # no-touch marks an .npz's windows without contact; on one with contact it
        # would be a texture class merged with them
        hit = np.flatnonzero((labels == NO_TOUCH) & contact)
        if hit.size:
            check_label_name(NO_TOUCH, f"{where}: labels[{hit[0]}] (a window with contact): "
                                       f"a texture label")
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
    return finalise(ws, min_classes, str(path))
