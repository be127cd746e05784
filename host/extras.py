"""The optional dependencies of the host toolkit, and the one line that names the
extra to install when one is missing (issue 32 item 4).

A Pi installs tacfoot without extras (numpy, OpenCV, onnxruntime, pyserial,
smbus2); training, simulating, the figures and the benchmarks need the ``host``
extra, the CNN the ``cnn`` extra, the MCAP log the ``viz`` extra. Optional
modules are imported with :func:`need`, which raises :class:`MissingExtra` (a
``ModuleNotFoundError``, so code that falls back on ``ImportError`` still does);
``host``'s ``main`` turns it, or any ``ModuleNotFoundError`` of a module listed
here, into one line and exit status 2 (:func:`missing_extra`).
"""
from __future__ import annotations

import importlib
from device.errors import TacfootError

#: top-level module -> the extra of pyproject.toml that installs it
EXTRA_OF = {
    "tqdm": "host", "sklearn": "host", "joblib": "host", "skl2onnx": "host",
    "onnx": "host", "matplotlib": "host", "PIL": "host", "websockets": "host",
    "av": "host", "torch": "cnn", "mcap": "viz", "foxglove": "viz",
}


class MissingExtra(TacfootError, ModuleNotFoundError):
    """An optional module is not installed: the message names the extra."""

    def __init__(self, module: str, extra: str, hint: str | None = None):
        self.extra = extra
        super().__init__(f"needs the {extra} extra (module {module!r} is not installed): "
                         f"{hint or f'pip install {install_spec(extra)}'}", name=module)


def install_spec(extra: str) -> str:
    """What to give pip for ``extra``: ``'tacfoot[host]'``."""
    return f"'tacfoot[{extra}]'"


def missing_extra(exc: BaseException) -> MissingExtra | None:
    """``exc`` as a :class:`MissingExtra` when it is a missing optional module
    (one of :data:`EXTRA_OF`), else None (a bug, or a module of no extra)."""
    if isinstance(exc, MissingExtra):
        return exc
    if not isinstance(exc, ModuleNotFoundError):
        return None
    root = (exc.name or "").split(".")[0]
    extra = EXTRA_OF.get(root)
    return None if extra is None else MissingExtra(root, extra)


def need(module: str):
    """Import and return ``module``; :class:`MissingExtra` naming its extra when it
    (or one of its own dependencies listed in :data:`EXTRA_OF`) is not installed."""
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        found = missing_extra(exc)
        if found is None:
            raise
        raise found from None
