"""``host deploy``: install the runtime on a Pi."""
from __future__ import annotations

import sys

from host.cli.common import UserError, emit
from host.deploy.options import DeployInputError, add_arguments, options_from_args
from host.deploy.release import run, summary_text


def cmd_deploy(args):
    try:
        opts = options_from_args(args)
        opts.check()
    except DeployInputError as exc:
        raise UserError(str(exc)) from None
    log = (lambda msg: print(msg, file=sys.stderr)) if not args.dry_run or args.json else (
        lambda msg: None)
    res = run(opts, dry_run=args.dry_run, rollback=args.rollback, log=log)
    emit(args, res, summary_text(res))
    return 0 if res.get("ok") or args.dry_run else 1


def register(sub) -> None:
    """The sub-command deploy."""
    s = sub.add_parser("deploy", help="install the runtime on a Pi over SSH (systemd, "
                                      "health check, rollback)")
    add_arguments(s)
    s.set_defaults(func=cmd_deploy)
