"""The root of every exception tacfoot defines (docs/architecture.md, "Errors and logs").

Every error class of ``device`` and ``host`` derives from :class:`TacfootError`, so a
caller can catch tacfoot's errors and nothing else, as python-can's ``CanError``
lets it catch the library's. Each class keeps the standard base that says what kind
of error it is, so callers that catch by kind keep working:

- bad input (a config, a profile, a model, a data set, an argument) is also a
  ``ValueError``;
- a device or file that cannot be read or written (a camera, a serial port, an MCAP
  log) is also an ``OSError``;
- a failure of a running part (the IMU driver, the rig link, a build) keeps the
  ``RuntimeError`` it had.

The entry points (``host`` and ``python -m device.pi``) catch :class:`TacfootError`
in one place and report it as one line with exit status 2; anything else, a bare
``ValueError`` or ``KeyError`` included, is a defect and shows its traceback.

The MicroPython modules (``device/micropython``, ``device/sim/mpy/lib``) run on the
gait MCU, where this package does not exist; their few exceptions are outside this
rule. This module imports nothing, so any layer may import it.
"""
from __future__ import annotations


class TacfootError(Exception):
    """An error tacfoot raises on purpose: its message is one line for the user."""


class InputError(TacfootError, ValueError):
    """Bad input with no more specific class: names the field and the value."""


def one_line(exc: BaseException) -> str:
    """``exc`` as the one line an entry point prints: ``FILE: what is wrong`` for an
    I/O error that names its file (``str`` of an ``OSError`` would add ``[Errno N]``),
    else its message."""
    if isinstance(exc, OSError) and exc.filename and exc.strerror:
        return f"{exc.filename}: {exc.strerror}"
    return str(exc)
