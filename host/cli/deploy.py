"""``host deploy``: install the runtime on a Pi, or on every leg of a robot.

A signal during a deploy (SIGTERM, SIGHUP, SIGINT) does not end ``host`` at once: it
trips a :class:`host.deploy.ssh.Stop`, every leg goes back to the release it had (as
when a leg fails), the summary is printed, the ssh connections are closed, and the
exit status is 128 + the signal's number."""
from __future__ import annotations

import contextlib
import logging
import signal

from host.cli.common import emit
from host.deploy.options import DeployInputError, add_arguments, options_from_args
from host.deploy.release import run, summary_text
from host.deploy.robot import deploy_robot, read_robot, robot_text, status
from host.deploy.ssh import Stop

SIGNALS = ("SIGTERM", "SIGHUP", "SIGINT")

_log = logging.getLogger(__name__)


def _legs(args) -> list:
    if args.robot:
        if args.target:
            raise DeployInputError("give the legs either as targets or with --robot, "
                                   "not both")
        return read_robot(args.robot, options_from_args(args, target="robot"))
    if not args.target:
        raise DeployInputError("name the Pi to deploy to ([USER@]HOST[:PORT]), or --robot FILE")
    return [options_from_args(args, target=t) for t in args.target]


@contextlib.contextmanager
def stopped_by_signals(log):
    """A Stop that SIGTERM, SIGHUP and SIGINT trip while the block runs (the old
    handlers are put back after it)."""
    stop = Stop()

    def handler(signum, frame):
        name = signal.Signals(signum).name
        if stop.trip(name):
            log(f"host deploy: {name}: stopping; every leg goes back to the release it had")
        else:
            log(f"host deploy: {name}: already stopping ({stop.signal_name}); putting the "
                f"old release back, wait")

    old = {}
    for name in SIGNALS:
        sig = getattr(signal, name)
        old[sig] = signal.signal(sig, handler)
    try:
        yield stop
    finally:
        for sig, h in old.items():
            signal.signal(sig, h)


def _exit_code(res: dict, stop: Stop, dry_run: bool) -> int:
    if res.get("ok") or dry_run:
        return 0
    if stop.signal_name:
        return 128 + int(getattr(signal, stop.signal_name))
    return 1


def cmd_deploy(args):
    log = _log.info if not args.dry_run or args.json else (lambda msg: None)
    warn = _log.warning
    legs = _legs(args)
    for o in legs:
        o.check()
    if args.status:
        if args.dry_run:
            raise DeployInputError("--status only reads each leg (it connects to them); "
                                   "it has no --dry-run")
        res = status(legs)
        emit(args, res, robot_text(res))
        return 0 if res["ok"] else 1
    if len(legs) == 1 and not args.robot:
        with stopped_by_signals(warn) as stop:
            res = run(legs[0], dry_run=args.dry_run, rollback=args.rollback, log=log,
                      stop=stop)
        emit(args, res, summary_text(res))
        return _exit_code(res, stop, args.dry_run)
    if args.rollback:
        raise DeployInputError("--rollback takes one target")
    with stopped_by_signals(warn) as stop:
        res = deploy_robot(legs, dry_run=args.dry_run, log=log, stop=stop)
    emit(args, res, robot_text(res))
    return _exit_code(res, stop, args.dry_run)


def register(sub) -> None:
    """The sub-command deploy."""
    s = sub.add_parser("deploy", help="install the runtime on a Pi, or on every leg of a "
                                      "robot, over SSH (signed models, health check, "
                                      "rollback)")
    add_arguments(s)
    s.set_defaults(func=cmd_deploy)
