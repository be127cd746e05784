"""``host rig check``, ``host rig run`` (the data-collection rig) and ``host record``
(a labelled trial from any camera, without the rig)."""
from __future__ import annotations


from device.errors import TacfootError, one_line
from device.pi.sources.camera import CameraError, open_camera
from device.pi.sources.imu import IMUError, open_imu
from host.cli.export import add_mcap_args, mcap_last_trials, open_log
from host.cli.common import (SEED, UserError, dataset_folder, emit, number, open_source,
                             out_folder, progress_bar, whole)
from host.rig.record import RecordError, record
from host.rig.plan import load_plan, plan_summary
from host.rig.trials import run, summary_text


def cmd_rig(args):
    plan = load_plan(args.trials)
    if args.rig_command == "check":
        s = plan_summary(plan)
        emit(args, s, f"{s['source']}: {s['trials']} trials ({len(s['plates'])} plate(s) x "
                      f"{s['repetitions']} repetitions x {len(s['variants'])} variants), "
                      f"about {s['estimated_s'] / 60:.1f} min")
        return 0
    out = out_folder(args.out, holds=dataset_folder, what="a tacfoot dataset")
    s = run(plan, args.rig, args.camera, out, resume=args.resume,
            profile=args.profile, progress=not args.json, yes=args.yes, seed=args.seed)
    emit(args, s, summary_text(s))
    return 1 if s["failed"] or s["remaining"] else 0


def _open_range(args):
    """The camera, opened at ``--start`` for ``--frames`` frames when given (file and
    simulated sources only: a live camera has no frame numbers to start from)."""
    if args.frames is not None and args.seconds is not None:
        raise UserError(f"give --seconds or --frames, not both (got --seconds "
                        f"{args.seconds:g} and --frames {args.frames})")
    if args.frames is None and args.seconds is None:
        args.seconds = 30.0
    if args.frames is None and not args.start:
        return open_source(args.camera)
    if args.camera.lower().startswith("v4l2://"):
        raise UserError(f"--start/--frames need a file or sim:// source; "
                        f"{args.camera} is a live camera (use --seconds)")
    opts = {"start_frame": args.start}
    if args.frames is not None:
        opts["end_frame"] = args.start + args.frames
    try:
        return open_camera(args.camera, **opts)
    except TacfootError as exc:              # the flag named: the source's error has no flag
        raise UserError(f"--camera {args.camera}: {one_line(exc)}") from None


def cmd_record(args):
    out = out_folder(args.out, holds=dataset_folder, what="a tacfoot dataset")
    log = None
    if args.mcap:                       # opened first: a bad FILE fails before the work
        log = open_log(args.mcap, args.mcap_image_every)
    try:
        return _record(args, out, log)
    finally:
        if log is not None:
            log.close()                 # a second close does nothing


def _record(args, out, log):
    camera = _open_range(args)
    imu = None
    if args.imu:
        try:
            imu = open_imu(args.imu)
        except TacfootError as exc:          # IMUError, or a bad source (InputError)
            camera.close()
            raise UserError(f"--imu {args.imu}: {exc}") from None
    fps = getattr(camera, "fps", None) or 120.0
    total = args.frames if args.frames is not None else int(round(args.seconds * fps))
    try:
        with camera, progress_bar(total, f"record {args.label}", not args.json) as bar:
            entry = record(camera, imu, args.label, args.seconds, args.out,
                           camera_url=args.camera, imu_url=args.imu or "",
                           progress=bar.update, frames=args.frames, start=args.start,
                           profile=args.profile)
    except (RecordError, CameraError, IMUError) as exc:
        raise UserError(f"{exc}; nothing was added to {args.out}") from None
    finally:
        if imu is not None:
            imu.close()
    if log is not None:
        entry["mcap"] = mcap_last_trials(log, out, 1, args.mcap_image_every)
    emit(args, entry, f"wrote {entry['path']}: {entry['frames']} frames of {args.label!r} "
                      f"({entry['seconds']:.2f} s" + (f", {entry['fps']:.1f} fps" if entry["fps"]
                                                      else "") + ")")
    return 0


def register(sub) -> None:
    """The sub-commands rig (check and run) and record."""
    s = sub.add_parser("record", help="record a labelled trial from a camera, without the rig")
    s.add_argument("--camera", required=True,
                   help="v4l2:///dev/video0, a video file, a folder of images or sim://SCENE")
    s.add_argument("--imu", help="i2c://1/0x68, file://imu.npy or sim://SCENE (optional)")
    s.add_argument("--label", required=True, help="the surface or texture name, e.g. lego")
    s.add_argument("--seconds", type=number(0, 86_400, lo_open=True),
                   help="how long to record (a file source may end sooner); default 30 "
                        "(not with --frames)")
    s.add_argument("--frames", type=whole(1, 10_000_000),
                   help="record exactly N frames (file and sim:// sources; an error if the "
                        "source ends sooner)")
    s.add_argument("--start", type=whole(0, 10_000_000), default=0,
                   help="the source frame to start at (file and sim:// sources); default 0")
    s.add_argument("--profile", default="roboskin",
                   help="the sensor profile the trial is recorded for (kept in dataset.json)")
    s.add_argument("--out", required=True, help="dataset folder to append the trial to")
    add_mcap_args(s)
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_record)

    s = sub.add_parser("rig", help="data-collection rig: validate and run trial files")
    rig_sub = s.add_subparsers(dest="rig_command", required=True)
    r = rig_sub.add_parser("check", help="validate a trial file (nothing moves)")
    r.add_argument("trials", help="trial file (.toml), see docs/rig.md")
    r.add_argument("--json", action="store_true")
    r.set_defaults(func=cmd_rig)
    r = rig_sub.add_parser("run", help="run a trial file on the rig and record a dataset")
    r.add_argument("trials", help="trial file (.toml), see docs/rig.md")
    r.add_argument("--rig", required=True, help="serial port or pyserial URL, or sim://")
    r.add_argument("--camera", required=True, 
                   help="v4l2:///dev/video0, or sim:// with --rig sim://")
    r.add_argument("--out", required=True, help="dataset folder")
    r.add_argument("--resume", action="store_true", help="run only the trials not yet recorded")
    r.add_argument("--profile", default="roboskin", help="sensor profile of the recordings")
    r.add_argument("--yes", action="store_true", help="do not prompt for plate swaps")
    r.add_argument("--seed", type=SEED, default=0, help="sim:// noise seed")
    r.add_argument("--json", action="store_true")
    r.set_defaults(func=cmd_rig)
