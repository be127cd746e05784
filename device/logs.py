"""The one log handler of the entry points, and ``-v``/``-q`` (docs/architecture.md,
"Errors and logs").

Every module logs through ``logging.getLogger(__name__)``; only an entry point
(``host``, ``python -m device.pi run``) calls :func:`configured`, which puts one handler
on the ``device`` and ``host`` loggers. It writes each message as the plain line it
is (no level or time prefix: the messages name their command themselves) to
stderr, never stdout, so the JSON a command prints stays the only thing there.

Levels: ``-q`` shows errors only, the default warnings and progress notes (INFO),
``-v`` debug notes too. A library user who calls no entry point gets Python's
default: warnings and errors on stderr.
"""
from __future__ import annotations

import argparse
import contextlib
import logging
import sys

#: the loggers the handler goes on: every module's logger is below one of them
ROOTS = ("device", "host")


class _StderrHandler(logging.StreamHandler):
    """A handler that writes to the ``sys.stderr`` of the moment (a test's captured
    stream, or a stream replaced after set-up), not the one it was made with."""

    def __init__(self):
        super().__init__(sys.stderr)

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, _value):       # StreamHandler sets it once; the property decides
        pass


def level_for(verbose: int = 0, quiet: int = 0) -> int:
    """The logging level for ``-v`` given ``verbose`` times and ``-q`` ``quiet`` times."""
    if quiet > 0:
        return logging.ERROR
    return logging.DEBUG if verbose > 0 else logging.INFO


@contextlib.contextmanager
def configured(verbose: int = 0, quiet: int = 0):
    """While the block runs, the one stderr handler is on the tacfoot loggers at the
    level ``-v``/``-q`` ask for; after it, the loggers are as they were (an entry
    point called twice in one process, as the tests do, leaves nothing behind)."""
    level = level_for(verbose, quiet)
    handler = _StderrHandler()
    handler.setFormatter(logging.Formatter("%(message)s"))
    saved = []
    for name in ROOTS:
        logger = logging.getLogger(name)
        saved.append((logger, logger.level))
        logger.addHandler(handler)
        logger.setLevel(level)
    try:
        yield level
    finally:
        for logger, old in saved:
            logger.removeHandler(handler)
            logger.setLevel(old)


def add_arguments(parser, default=0) -> None:
    """``-v``/``--verbose`` and ``-q``/``--quiet`` on an argparse parser and on each
    of its sub-command parsers (``host -q train`` and ``host train -q`` both work;
    a sub-command's flag counts only when given). A sub-command that has its own
    ``--quiet`` (no progress bars) keeps it; it quiets the log as well."""
    g = parser.add_mutually_exclusive_group()
    have = parser._option_string_actions
    for flags, help_ in ((("-v", "--verbose"), "also print debug notes on stderr"),
                         (("-q", "--quiet"), "print only errors on stderr (no progress "
                                             "notes or warnings)")):
        if not any(f in have for f in flags):
            g.add_argument(*flags, action="count", default=default, help=help_)
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in {id(s): s for s in action.choices.values()}.values():
                add_arguments(sub, argparse.SUPPRESS)
