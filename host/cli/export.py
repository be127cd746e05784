"""host export mcap DATASET --out FILE: a recorded or simulated dataset folder
(docs/datasets.md) as the leg's MCAP channels (docs/viewing.md).

Each trial's frames go through the marker pipeline (the trial's profile) as on the
leg: ``/tacfoot/image`` and ``/tacfoot/pins`` every ``--image-every`` frames,
``/tacfoot/grid`` and ``/tacfoot/imu`` (when the trial has one) every frame, and the
trial's ground truth on ``/tacfoot/labels``. Trials follow one another on one time
line, one second apart."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from host.cli.common import UserError, emit, whole
from host.data.dataset import load_trial, read_index

_NUM, _INT, _STR, _BOOL = ({"type": "number"}, {"type": "integer"}, {"type": "string"},
                           {"type": "boolean"})
#: the dataset's ground truth, beside the leg's channels
LABELS = {"/tacfoot/labels": {"title": "tacfoot.Labels", "type": "object", "properties": {
    "trial": _INT, "frame": _INT, "surface": _STR, "texture": _STR, "contact": _BOOL,
    "slip": _BOOL, "load_n": _NUM}}}
#: the gap between one trial's last frame and the next one's first, s
TRIAL_GAP_S = 1.0


def register(sub) -> None:
    s = sub.add_parser("export", help="convert a dataset for other tools")
    ssub = s.add_subparsers(dest="format", required=True)
    m = ssub.add_parser("mcap", help="a dataset folder as an MCAP log for Foxglove "
                                     "(docs/viewing.md; needs pip install .[viz])")
    m.add_argument("dataset", help="dataset folder (dataset.json + trial_*.npz)")
    m.add_argument("--out", required=True, help="the .mcap file to write")
    m.add_argument("--image-every", type=int, default=1,
                   help="log every Nth frame's image and pins (default 1)")
    m.add_argument("--json", action="store_true", help="print the result as JSON")
    m.set_defaults(func=cmd_export_mcap)


def open_log(path, image_every: int, flag: str = "--mcap", channels=None):
    """The McapLog a host command writes ``--mcap FILE`` with (written in the
    caller's thread, nothing dropped): the leg's channels, :data:`LABELS` and
    ``channels``; a UserError naming ``flag`` when it cannot be opened."""
    try:
        from device.pi.runtime.mcaplog import McapLog, McapLogError
        from device.pi.runtime.config import McapConfig
    except ImportError as exc:                     # pragma: no cover
        raise UserError(str(exc)) from None
    if image_every < 1:
        raise UserError(f"--mcap-image-every must be >= 1, got {image_every}")
    try:
        return McapLog(Path(path), McapConfig(image_every=image_every), max_mb=1e9,
                       channels={**LABELS, **(channels or {})})
    except McapLogError as exc:
        raise UserError(str(exc).replace("--mcap", flag)) from None


def close_log(log, flag: str = "--mcap") -> dict:
    """Close a log from :func:`open_log`: its file and message count; a UserError
    when messages could not be written."""
    log.close()
    if log.messages_lost:
        raise UserError(f"{flag} {log.path}: {log.messages_lost} messages could not be "
                        f"written")
    return {"file": str(log.path), "messages": log.messages_written}


def export_trials(log, dataset, trials, image_every: int) -> int:
    """Trials ``trials`` (indices) of a dataset folder into ``log``, one after
    another on one time line; the frames written."""
    doc = read_index(dataset)
    frames, t_base = 0, 0.0
    for i in trials:
        t_end = export_trial(log, load_trial(dataset, i), i, doc, t_base, image_every)
        frames += int(doc["trials"][i].get("frames", 0))
        t_base = t_end + TRIAL_GAP_S
    return frames


def add_mcap_args(s) -> None:
    """``--mcap FILE`` and ``--mcap-image-every N`` (host analyse, simulate, record)."""
    s.add_argument("--mcap", metavar="FILE",
                   help="also write the leg's MCAP channels to FILE for Foxglove "
                        "(docs/viewing.md; needs pip install .[viz])")
    s.add_argument("--mcap-image-every", type=whole(1, 1_000_000), default=4,
                   help="with --mcap, log every Nth frame's image and pins (default 4, "
                        "the leg's [mcap] image_every)")


def mcap_last_trials(log, out, trials: int, image_every: int) -> dict:
    """The dataset's last ``trials`` trials (the ones just written) into ``log``,
    then closed: its file and message count (``--mcap`` of simulate and record)."""
    n = len(read_index(out)["trials"])
    export_trials(log, out, range(max(0, n - trials), n), image_every)
    return close_log(log)


def cmd_export_mcap(args) -> None:
    if args.image_every < 1:
        raise UserError(f"--image-every must be >= 1, got {args.image_every}")
    doc = read_index(args.dataset)
    out = Path(args.out)
    log = open_log(out, args.image_every, "--out")
    try:
        frames = export_trials(log, args.dataset, range(len(doc["trials"])), args.image_every)
    finally:
        log.close()
    if log.messages_lost:
        raise UserError(f"--out {args.out}: {log.messages_lost} messages could not be "
                        f"written")
    res = {"out": str(out), "trials": len(doc["trials"]), "frames": frames,
           "messages": log.messages_written}
    emit(args, res, f"{out}: {res['trials']} trials, {frames} frames, "
                    f"{res['messages']} messages")


def export_trial(log, trial: dict, i: int, doc: dict, t_base: float,
                 image_every: int) -> float:
    """Trial ``i`` into ``log`` from ``t_base`` s; the time of its last frame, s."""
    from device.pi.runtime.mcapmsg import grid_doc
    from device.pi.vision.encoder import FrameEncoder

    info = trial["info"]
    frames = trial["frames"]
    n = len(frames)
    fps = float(info.get("fps") or 30.0)
    t_s = np.asarray(trial.get("t_s", np.arange(n) / fps), np.float64)
    enc = FrameEncoder(info.get("profile") or "roboskin", crop_px=None)
    s_names = doc.get("surface_labels") or []
    x_names = doc.get("texture_labels") or []

    def name(names, codes, k):
        if codes is None:
            return None
        c = int(codes[k])
        return names[c] if 0 <= c < len(names) else str(c)

    t = t_base
    for k in range(n):
        t = t_base + float(t_s[k] - t_s[0])
        ns = int(round(t * 1e9))
        ef = enc.encode(frames[k], t)
        ff = ef.features
        if k % image_every == 0:
            log.image(ns, frames[k], ff, enc.stream.reference)
        log.write("/tacfoot/grid", ns, grid_doc(ns, ff.grid))
        if "imu" in trial:
            v = np.asarray(trial["imu"][k], np.float64)
            log.write("/tacfoot/imu", ns, {"frame": k, "acc_g": np.round(v[:3], 5).tolist(),
                                           "gyro_dps": np.round(v[3:6], 4).tolist(),
                                           "faults": int(trial["imu_faults"][k])
                                           if "imu_faults" in trial else 0})
        lab = {"trial": i, "frame": k, "surface": name(s_names, trial.get("surface"), k),
               "texture": name(x_names, trial.get("texture"), k)}
        for key in ("contact", "slip"):
            if key in trial:
                lab[key] = bool(trial[key][k])
        if "load_n" in trial:
            lab["load_n"] = round(float(trial["load_n"][k]), 4)
        log.write("/tacfoot/labels", ns, lab)
    return t
