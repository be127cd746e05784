"""``host rig check`` and ``host rig run``: the data-collection rig."""
from __future__ import annotations

from pathlib import Path

from host.cli.common import UserError, emit
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
    try:
        s = run(plan, args.rig, args.camera, Path(args.out), resume=args.resume,
                profile=args.profile, progress=not args.json, yes=args.yes, seed=args.seed)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    emit(args, s, summary_text(s))
    return 1 if s["failed"] or s["remaining"] else 0


def register(sub) -> None:
    """The sub-command rig, with check and run."""
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
    r.add_argument("--seed", type=int, default=0, help="sim:// noise seed")
    r.add_argument("--json", action="store_true")
    r.set_defaults(func=cmd_rig)
