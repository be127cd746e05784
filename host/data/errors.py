"""The data toolkit's error: :class:`DataError`, a bad data spec.

Its own module so that every module of :mod:`host.data` can raise it without importing
another's: :mod:`host.data.extract` raises it and :mod:`host.data.windows` reads
extract's :class:`~host.data.extract.ClipFeatures`, so with the error in ``windows``
the two imported each other. ``from host.data.windows import DataError`` still works.
"""
from __future__ import annotations
from device.errors import TacfootError


class DataError(TacfootError, ValueError):
    """A bad data spec; the message names the file, row, column or key and the value."""
