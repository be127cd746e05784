"""The ``host`` command: the tacfoot host toolkit.

Every command that computes a result accepts ``--json``. Bad input (a bad
argument, scene file or source) gives one clear line on stderr and exit status 2,
never a traceback, and so does a command that needs an extra the install lacks
(:mod:`host.extras`); ``--out`` follows one rule (:mod:`host.cli.common`).
Each command group lives in its own module, which registers its sub-commands.

:func:`main` is the one place that catches tacfoot's errors (every one derives from
:class:`device.errors.TacfootError`): any other exception, a bare ``ValueError`` or
``KeyError`` included, is a defect and shows its traceback. It also sets up the one
log handler (:mod:`device.logs`): ``-v`` adds debug notes, ``-q`` leaves errors only.
"""
from __future__ import annotations

import argparse
import sys

from device import logs
from device.errors import TacfootError, one_line
from host.cli import analyse, bench, deploy, export, learn, localiser, monitor, rig, sim
from host.cli.common import EXIT_BAD_INPUT, Parser
from host.extras import missing_extra

GROUPS = (sim, analyse, learn, localiser, bench, deploy, rig, monitor, export)


def installed_version() -> str:
    """tacfoot's version as installed (its package metadata)."""
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("tacfoot")
    except PackageNotFoundError:
        return "unknown (tacfoot is not installed: run from a checkout)"


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="host", description="tacfoot host toolkit")
    p.add_argument("--version", action="version", version=f"host (tacfoot) {installed_version()}")
    sub = p.add_subparsers(dest="command", required=True)
    for group in GROUPS:
        group.register(sub)
    logs.add_arguments(p)
    return p


def main(argv: list[str] | None = None) -> int:
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:           # -h (0) or a bad argument (2, one line)
        return exc.code if isinstance(exc.code, int) else 0
    with logs.configured(args.verbose, args.quiet):
        try:
            rc = args.func(args)
        except TacfootError as exc:         # bad input, a device or file that fails
            print(f"host {args.command}: error: {one_line(exc)}", file=sys.stderr)
            return EXIT_BAD_INPUT
        except ModuleNotFoundError as exc:  # an optional module the install lacks: name it
            missing = missing_extra(exc)
            if missing is None:
                raise
            print(f"host {args.command}: error: {missing}", file=sys.stderr)
            return EXIT_BAD_INPUT
        except BrokenPipeError:
            return 0
    return int(rc or 0)


if __name__ == "__main__":
    sys.exit(main())
