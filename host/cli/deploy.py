"""``host deploy``: install the runtime on a Pi, or on every leg of a robot."""
from __future__ import annotations

import sys

from host.cli.common import UserError, emit
from host.deploy.options import DeployInputError, add_arguments, options_from_args
from host.deploy.release import run, summary_text
from host.deploy.robot import deploy_robot, read_robot, robot_text, status


def _legs(args) -> list:
    if args.robot:
        if args.target:
            raise DeployInputError("give the legs either as targets or with --robot, "
                                   "not both")
        return read_robot(args.robot, options_from_args(args, target="robot"))
    if not args.target:
        raise DeployInputError("name the Pi to deploy to ([USER@]HOST[:PORT]), or --robot FILE")
    return [options_from_args(args, target=t) for t in args.target]


def cmd_deploy(args):
    log = (lambda msg: print(msg, file=sys.stderr)) if not args.dry_run or args.json else (
        lambda msg: None)
    try:
        legs = _legs(args)
        for o in legs:
            o.check()
        if args.status:
            res = status(legs)
            emit(args, res, robot_text(res))
            return 0 if res["ok"] else 1
        if len(legs) == 1 and not args.robot:
            res = run(legs[0], dry_run=args.dry_run, rollback=args.rollback, log=log)
            emit(args, res, summary_text(res))
            return 0 if res.get("ok") or args.dry_run else 1
        if args.rollback:
            raise DeployInputError("--rollback takes one target")
        res = deploy_robot(legs, dry_run=args.dry_run, log=log)
    except DeployInputError as exc:
        raise UserError(str(exc)) from None
    emit(args, res, robot_text(res))
    return 0 if res.get("ok") or args.dry_run else 1


def register(sub) -> None:
    """The sub-command deploy."""
    s = sub.add_parser("deploy", help="install the runtime on a Pi, or on every leg of a "
                                      "robot, over SSH (signed models, health check, "
                                      "rollback)")
    add_arguments(s)
    s.set_defaults(func=cmd_deploy)
