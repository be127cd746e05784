"""Argument checks shared by the Pi code, the simulator and the host.

Each returns the value as a plain int or float, or raises ``error`` (by default
:class:`device.errors.InputError`, a ValueError; or a caller's class such as
host.data's DataError) naming the argument and
the value: ``k must be a whole number >= 1, got k=0``. A bool is not a number
here, and numeric text is not either (source query strings are parsed by
:mod:`device.pi.sources.options`).
"""
from __future__ import annotations

import math
from urllib.parse import urlsplit

import numpy as np

from device.errors import InputError

__all__ = ["whole_number", "finite_number", "positive_number", "frame_rate", "bounds_text",
           "serial_url", "FPS_MIN_HZ", "FPS_MAX_HZ"]

#: the frame rates a camera may run at: ``--fps``, a camera source's ``fps``
#: option and a scene's ``fps`` are all held to this range (a slower rate would
#: let the stall check wait minutes; a faster one is no camera the leg has)
FPS_MIN_HZ, FPS_MAX_HZ = 1.0, 1000.0


def bounds_text(lo, hi, lo_open: bool = False, hi_open: bool = False) -> str:
    """The bounds as the messages word them: ' >= 1', ' in [0, 255]', '' (none)."""
    if lo is not None and hi is not None:
        return f" in {'(' if lo_open else '['}{lo}, {hi}{')' if hi_open else ']'}"
    if lo is not None:
        return f" {'>' if lo_open else '>='} {lo}"
    if hi is not None:
        return f" {'<' if hi_open else '<='} {hi}"
    return ""


def whole_number(name: str, value, lo: int | None = None, hi: int | None = None,
                 error: type[ValueError] = InputError) -> int:
    """``value`` as an int in ``[lo, hi]`` (either bound may be None)."""
    if (isinstance(value, bool) or not isinstance(value, (int, np.integer))
            or (lo is not None and value < lo) or (hi is not None and value > hi)):
        raise error(f"{name} must be a whole number{bounds_text(lo, hi)}, got {name}={value!r}")
    return int(value)


def finite_number(name: str, value, lo: float | None = None, hi: float | None = None, *,
                  lo_open: bool = False, hi_open: bool = False,
                  error: type[ValueError] = InputError) -> float:
    """``value`` as a finite float within the bounds (closed unless ``lo_open`` /
    ``hi_open``; either may be None)."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise error(f"{name} must be a number, got {name}={value!r}")
    v = float(value)
    if (not math.isfinite(v)
            or (lo is not None and (v <= lo if lo_open else v < lo))
            or (hi is not None and (v >= hi if hi_open else v > hi))):
        raise error(f"{name} must be a finite number{bounds_text(lo, hi, lo_open, hi_open)}, "
                    f"got {name}={value!r}")
    return v


def positive_number(name: str, value, error: type[ValueError] = InputError) -> float:
    """``value`` as a finite float > 0."""
    return finite_number(name, value, 0, lo_open=True, error=error)


def frame_rate(name: str, value, error: type[ValueError] = InputError) -> float:
    """``value`` as a frame rate in [:data:`FPS_MIN_HZ`, :data:`FPS_MAX_HZ`] frames/s."""
    return finite_number(name, value, FPS_MIN_HZ, FPS_MAX_HZ, error=error)


#: pyserial URL schemes that reach a port over the network and need host:port
_NETWORK_SCHEMES = ("socket", "rfc2217")


def serial_url(url, error: type[ValueError] = InputError) -> str:
    """``url`` when it can name a serial port: a device path or a pyserial URL
    (``loop://``, ``socket://host:port``). A ``socket://`` or ``rfc2217://`` URL
    must carry a host and a port in 1..65535: pyserial's own message for a
    missing port does not say what is wrong."""
    if not isinstance(url, str) or not url.strip():
        raise error(f"serial port must be a device path or a pyserial URL, got {url!r}")
    scheme, sep, _ = url.partition("://")
    if sep and scheme.lower() in _NETWORK_SCHEMES:
        parts = urlsplit(url)
        try:
            port = parts.port
        except ValueError:          # not a number, or beyond 65535
            port = None
        if not parts.hostname or not port:
            raise error(f"{url!r}: a {scheme.lower()}:// URL needs a host and a port "
                        f"1-65535, e.g. {scheme.lower()}://localhost:7777")
    return url
