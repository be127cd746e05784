"""TOML loading and field validation shared by scene and profile files.

Every bad value raises one :class:`ConfigError` whose message names the file,
the dotted field and the offending value, e.g.::

    walk.toml: surface.mu must be >= 0, got -0.5
"""
from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any, Iterable
from device.errors import TacfootError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10 on Raspberry Pi OS bookworm
    import tomli as tomllib


class ConfigError(TacfootError, ValueError):
    """A scene, profile or config file holds a bad field."""


def read_toml(path: Path | str) -> dict:
    """The TOML document in ``path``. A missing file, a folder, a file that cannot be
    read, text that is not UTF-8 and bad TOML are each one :class:`ConfigError`
    naming the file."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise ConfigError(f"{path}: file not found") from None
    except IsADirectoryError:
        raise ConfigError(f"{path}: is a folder, not a TOML file") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text (byte {exc.start}); TOML files are "
                          f"UTF-8") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from None


class Fields:
    """Reads typed, range-checked values out of one TOML table.

    Unknown keys are an error: a typo must not silently fall back to a default.
    Call :meth:`done` after the last read to report keys nobody asked for.
    """

    def __init__(self, table: Any, where: str, source: str = ""):
        self.where = where
        self.source = source
        if not isinstance(table, dict):
            self.fail(where, table, "must be a table")
        self.table = table
        self.seen: set[str] = set()

    def _name(self, key: str) -> str:
        return f"{self.where}.{key}" if self.where else key

    def fail(self, field: str, value: Any, why: str):
        prefix = f"{self.source}: " if self.source else ""
        raise ConfigError(f"{prefix}{field} {why}, got {value!r}")

    def has(self, key: str) -> bool:
        return key in self.table

    def _lookup(self, key: str, default: Any) -> tuple[bool, Any]:
        """Mark ``key`` as read: (True, value) when the table has it, else (False,
        default); absent with no default is an error naming the field."""
        self.seen.add(key)
        if key in self.table:
            return True, self.table[key]
        if default is None:
            self.fail(self._name(key), None, "is required")
        return False, default
    def number(self, key: str, default: float | None = None, *, min: float | None = None,
               max: float | None = None, min_exclusive: bool = False,
               integer: bool = False) -> float:
        found, v = self._lookup(key, default)
        if not found:
            return v
        name = self._name(key)
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            self.fail(name, v, "must be a number")
        if integer and not float(v).is_integer():
            self.fail(name, v, "must be a whole number")
        if not math.isfinite(v):
            self.fail(name, v, "must be finite")
        if min is not None:
            if min_exclusive and v <= min:
                self.fail(name, v, f"must be > {min}")
            if not min_exclusive and v < min:
                self.fail(name, v, f"must be >= {min}")
        if max is not None and v > max:
            self.fail(name, v, f"must be <= {max}")
        return int(v) if integer else float(v)

    def integer(self, key: str, default: int | None = None, **kw) -> int:
        return int(self.number(key, default, integer=True, **kw))

    def string(self, key: str, default: str | None = None, *,
               choices: Iterable[str] | None = None) -> str:
        found, v = self._lookup(key, default)
        if not found:
            return v
        if not isinstance(v, str):
            self.fail(self._name(key), v, "must be a string")
        if choices is not None and v not in choices:
            self.fail(self._name(key), v, f"must be one of {sorted(choices)}")
        return v

    def boolean(self, key: str, default: bool) -> bool:
        self.seen.add(key)
        v = self.table.get(key, default)
        if not isinstance(v, bool):
            self.fail(self._name(key), v, "must be true or false")
        return v

    def pair(self, key: str, default: tuple[float, float] | None = None) -> tuple[float, float]:
        found, v = self._lookup(key, default)
        if not found:
            return v
        if (not isinstance(v, list) or len(v) != 2
                or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                           and math.isfinite(x) for x in v)):
            self.fail(self._name(key), v, "must be a list of two finite numbers")
        return float(v[0]), float(v[1])

    def number_list(self, key: str, default: list | None = None, *, min: float | None = None,
                    integer: bool = False) -> list:
        found, v = self._lookup(key, default)
        if not found:
            return list(v)
        ok = isinstance(v, list) and len(v) > 0 and all(
            isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
            and (not integer or float(x).is_integer()) and (min is None or x >= min)
            for x in v)
        if not ok:
            kind = "whole numbers" if integer else "finite numbers"
            bound = f" >= {min}" if min is not None else ""
            self.fail(self._name(key), v, f"must be a non-empty list of {kind}{bound}")
        return [int(x) for x in v] if integer else [float(x) for x in v]

    def sub(self, key: str, default: dict | None = None) -> "Fields":
        _, v = self._lookup(key, default)
        return Fields(v, self._name(key), self.source)

    def raw(self, key: str, default: Any = None) -> Any:
        self.seen.add(key)
        return self.table.get(key, default)

    def done(self):
        unknown = sorted(set(self.table) - self.seen)
        if unknown:
            key = unknown[0]
            prefix = f"{self.source}: " if self.source else ""
            raise ConfigError(f"{prefix}{self._name(key)} is not a known key "
                              f"(value {self.table[key]!r})")
