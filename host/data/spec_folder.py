"""A dataset folder data spec (written by ``host simulate``, ``host rig run`` or
``host record``): labels, contact and load per frame from the trial's truth; a
recorded trial without contact truth takes contact from the marker pipeline."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from host.data.dataset import DatasetError, load_trial, read_index
from host.data.extract import extract_features, frame_intervals
from host.data.recordings import profile_ref, sim_recording
from host.data.windows import (IMU_CHANNELS, SLIP_LABELS, DataError, TrialPart, WindowSet,
                               check_labels, finalise, keep_contact, stack_parts, window_ends,
                               window_labels)


def trial_recording(path: Path, entry: dict) -> dict:
    """The recording a trial entry names (``recording``, written by ``host record``
    and ``host simulate``); an older entry of a simulated run names its scene and
    seed; any other trial is a recording of its own."""
    rec = entry.get("recording")
    if isinstance(rec, dict) and isinstance(rec.get("id"), str) and rec["id"]:
        return rec
    if entry.get("scene") is not None and entry.get("seed") is not None:
        return sim_recording(entry["scene"], entry["seed"])
    return {"id": f"trial:{path.resolve() / entry.get('file', '')}"}


def _names(paths: list[str], most: int = 5) -> str:
    names = [Path(p).name for p in paths]
    return str(names[:most])[:-1] + (f", ... {len(names) - most} more]" if len(names) > most
                                     else "]")


def load_dataset(path: Path, task: str, T: int, stride: int, contact_only: bool,
                  profile: str, frame_size, progress: bool, cache: dict,
                  min_classes: int) -> WindowSet:
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
    contact_from: set = set()
    for i, entry in enumerate(entries):
        fname = entry.get("file", f"trial {i}")
        why = _other_profile(entry, profile)
        if why:
            raise DataError(f"{path / fname}: {why}")
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
            except DatasetError as exc:             # it names the file
                raise DataError(str(exc)) from None
            except (OSError, ValueError, KeyError) as exc:
                raise DataError(f"{path / fname}: cannot read the trial: {exc}") from None
            frames = tr["frames"]
            clip = extract_features(frames, profile, frame_size, n_frames=len(frames),
                                    progress=progress, desc=f"{path.name}/{fname}",
                                    fps=float(entry.get("fps") or 0) or None)
            truth = {k: tr[k] for k in ("contact", "surface", "texture", "slip", "load_n", "imu")
                     if k in tr}
            t_s = tr.get("t_s") if hasattr(tr, "get") else None
            if t_s is not None and len(t_s) == clip.n_frames and clip.session is not None:
                clip.session[:, -1] = frame_intervals(list(np.asarray(t_s, np.float64)))
            cache[key] = (clip, truth)
        F = clip.n_frames
        need = {"surface": "surface", "texture": "texture", "slip": "slip",
                "pressure": "load_n"}[task]
        for k in ("contact", need):
            if k == "contact" and k not in truth:
                continue        # a recording without the rig: contact from the pipeline
            if k not in truth or len(truth[k]) != F:
                why = ("is missing" if k not in truth else
                       f"has {len(truth[k])} rows, not one per frame ({F} frames)")
                raise DataError(f"{path / fname}: truth array {k!r} {why}"
                                + (f"; task {task} needs it (a trial recorded without the "
                                   f"rig has only its label)" if k not in truth else ""))
        ends, nref = window_ends(clip.ready, 0, F, T, stride)
        dropped_ref += nref
        contact_from.add("truth" if "contact" in truth else "pipeline")
        contact = (np.asarray(truth["contact"], bool) if "contact" in truth
                   else np.asarray(clip.contact, bool))[ends]
        labels = targets = None
        if task in ("surface", "texture"):
            codes = np.asarray(truth[task], np.int64)[ends]
            nm = list(names[task])
            if codes.size and (codes.min() < 0 or codes.max() >= len(nm)):
                raise DataError(f"{path / fname}: {task} code {int(codes.max())} has no name in "
                                f"{task}_labels {nm}")
            # texture names of frames without contact become no-touch (the
            # simulator's "none"); the names that reach a window are checked
            for c in np.unique(codes[contact] if task == "texture" else codes):
                check_labels(task, nm[c], f"{path / fname}: {task} code {int(c)} "
                                          f"({task}_labels in {path / 'dataset.json'})")
            labels = window_labels(task, np.array(nm, object)[codes], contact)
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
        rec = trial_recording(path, entry)
        trials[i] = {"kind": "dataset", "path": str(path / fname), "span_start": 0,
                     "frames": F, "fps": clip.fps, "scene": entry.get("scene"),
                     "seed": entry.get("seed"), "recording": rec}
        parts.append(TrialPart(clip, ends, labels, targets, contact, imu, i, 0, F,
                               rec["id"], int(rec.get("start_frame") or 0)))
    with_imu = [trials[p.trial]["path"] for p in parts if p.imu is not None]
    if with_imu and len(with_imu) < len(parts):
        without = [trials[p.trial]["path"] for p in parts if p.imu is None]
        raise DataError(f"{path}: trials {_names(with_imu)} have an IMU and "
                        f"{_names(without)} have none, so the IMU would be dropped for "
                        f"every trial: record every trial with --imu, or move the trials "
                        f"without it to a folder of their own")
    parts, cut, kept = keep_contact(parts, contact_only)
    arrays = stack_parts(parts, task, T, trials)
    notes = [f"{dropped_ref} windows dropped: they start before the reference frame"] \
        if dropped_ref else []
    src = {"specs": [str(path)], "trials": [dict(v, group=i) for i, v in enumerate(trials.values())],
           "windows_cut": cut, "windows_kept": kept, "contact_only": contact_only,
           "kept_fraction": kept / cut if cut else 1.0, "contact_from": sorted(contact_from), "notes": notes,
           "extract_frames": sum(p.clip.n_frames for p in parts),
           "extract_s": sum(p.clip.seconds for p in parts)}
    return finalise(WindowSet(task=task, window=T, classes=[], source=src, **arrays),
                     min_classes, str(path))


def _other_profile(entry: dict, profile) -> str:
    """Why a trial recorded for one sensor profile cannot give features for
    ``profile``, or ''. A trial that kept its profile's checksum (``host record``) is
    compared by it, so a .toml of another sensor is refused as a built-in name is."""
    rec, rec_sha = entry.get("profile"), entry.get("profile_sha256")
    if rec is None:
        return ""
    if rec_sha:
        want = profile_ref(profile)["sha256"]
        if want is None or want == rec_sha:
            return ""
    elif rec == profile or str(profile).endswith(".toml"):
        return ""
    return (f"recorded with profile {rec!r}, features asked for profile {profile!r} (another "
            f"sensor description): record with --profile {profile}, or train with --profile "
            f"{rec}")
