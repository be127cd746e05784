"""Source-string options shared by the camera and IMU sources.

A source's options come in its query string (``v4l2:///dev/video0?fps=30``) or as
keyword arguments (keywords win). Each option has a checker ``(name, value) ->
value`` that accepts the query-string text or a Python value and raises a
``ValueError`` naming the option and the value.
"""
from __future__ import annotations

import math
import re
from typing import Any, Callable

import numpy as np

from device.checks import frame_rate
from device.errors import InputError

__all__ = ["opt_int", "opt_int_in", "opt_float", "opt_positive", "opt_fps", "opt_bool",
           "opt_choice", "parse_options"]


def opt_int(name: str, value: Any) -> int:
    """An int (decimal text accepted)."""
    if isinstance(value, bool):
        raise InputError(f"{name} must be an int, got {value!r}")
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, str) and re.fullmatch(r"[+-]?\d+", value.strip()):
        return int(value)
    raise InputError(f"{name} must be an int, got {value!r}")


def opt_int_in(name: str, value: Any, lo: int, hi: int) -> int:
    """An int in ``[lo, hi]`` (decimal or ``0x`` hex text accepted)."""
    if isinstance(value, str):
        s = value.strip().lower()
        try:
            value = int(s, 16) if s.startswith("0x") else int(s, 10)
        except ValueError:
            raise InputError(f"{name} must be an int in [{lo}, {hi}], got {value!r}") from None
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise InputError(f"{name} must be an int in [{lo}, {hi}], got {value!r}")
    if not lo <= int(value) <= hi:
        raise InputError(f"{name} must be in [{lo}, {hi}], got {value!r}")
    return int(value)


def opt_float(name: str, value: Any) -> float:
    """A finite number."""
    if isinstance(value, bool):
        raise InputError(f"{name} must be a number, got {value!r}")
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(v):
        raise InputError(f"{name} must be finite, got {value!r}")
    return v


def opt_positive(name: str, value: Any) -> float:
    """A finite number > 0."""
    v = opt_float(name, value)
    if v <= 0:
        raise InputError(f"{name} must be > 0, got {value!r}")
    return v


def opt_fps(name: str, value: Any) -> float:
    """A frame rate in 1..1000 frames/s, the bound ``--fps`` has
    (:func:`device.checks.frame_rate`)."""
    return frame_rate(name, opt_float(name, value))


def opt_bool(name: str, value: Any) -> bool:
    """A bool, 0/1, or one of 1/true/yes/on/0/false/no/off."""
    if isinstance(value, bool):
        return value
    if isinstance(value, (int, np.integer)) and value in (0, 1):
        return bool(value)
    if isinstance(value, str) and value.strip().lower() in ("1", "true", "yes", "on", "0", "false", "no", "off"):
        return value.strip().lower() in ("1", "true", "yes", "on")
    raise InputError(f"{name} must be a bool, got {value!r}")


def opt_choice(name: str, value: Any, allowed: tuple) -> int:
    """The index in ``allowed`` of the number ``value``."""
    v = opt_float(name, value)
    for i, a in enumerate(allowed):
        if v == a:
            return i
    raise InputError(f"{name} must be one of {list(allowed)}, got {value!r}")


def parse_options(kind: str, source: str, query: dict, kwargs: dict,
                  spec: dict[str, Callable[[str, Any], Any]]) -> dict:
    """Check the merged ``query`` and ``kwargs`` options of ``source`` against ``spec``.

    ``kind`` names the source in errors ("camera", "IMU"); an unknown option or a
    bad value is a ``ValueError`` naming the option and the source string.
    """
    merged = {**query, **kwargs}
    unknown = sorted(set(merged) - set(spec))
    if unknown:
        raise InputError(f"unknown option {unknown[0]!r} for {kind} source {source!r}; known: {sorted(spec)}")
    out = {}
    for k, v in merged.items():
        try:
            out[k] = spec[k](k, v)
        except ValueError as e:
            raise InputError(f"{e} ({kind} source {source!r})") from None
    return out
