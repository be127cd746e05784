"""What every ``host`` command shares: the bad-input error and its exit status, the
argument parser and its checked number types, ``--out`` handling, JSON output,
progress bars, and opening sources, streams and models.

Bad input is one line on stderr and exit status 2, never a traceback
(docs/architecture.md, "Bad input and --out"): a command raises a
:class:`device.errors.TacfootError` (:class:`UserError` for what only the command can
see) and ``host``'s ``main`` reports it; a command catches one only to add what the
error cannot know (the flag or file it came from)."""
from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from pathlib import Path
from typing import Callable

from device.checks import bounds_text, finite_number, whole_number
from device.pi.models.regressor import Regressor
from device.pi.sources.camera import open_camera
from device.pi.models.localiser import Localiser
from device.pi.vision.pipeline import MarkerStream
from device.profile import load_pipeline_profile
from host.data.dataset import addable_folder, is_dataset
from host.rig.trials import RUN_STATE
from host.learn.onnx_io import json_default  # noqa: F401  (the commands' JSON of numpy values)
from host.extras import need
from device.errors import TacfootError

EXIT_BAD_INPUT = 2


class UserError(TacfootError):
    """Bad input from the user: printed as one line, exit status 2."""


class Parser(argparse.ArgumentParser):
    """argparse with a bad argument as one line (``host view: error: argument
    --gain: ...``) and exit status 2; its sub-command parsers are Parsers too."""

    def error(self, message: str):
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {message} (see {self.prog} -h)\n")


def whole(lo: int | None = None, hi: int | None = None) -> Callable[[str], int]:
    """An argparse ``type``: a whole number in ``[lo, hi]`` (either bound may be None)."""
    def parse(text: str) -> int:
        try:
            return whole_number("", int(text, 10), lo, hi)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"must be a whole number{bounds_text(lo, hi)}, got {text!r}") from None
    parse.__name__ = "whole number"
    return parse


def number(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
           hi_open: bool = False) -> Callable[[str], float]:
    """An argparse ``type``: a finite number within the bounds (closed unless
    ``lo_open`` / ``hi_open``); ``nan`` and ``inf`` are refused."""
    def parse(text: str) -> float:
        try:
            return finite_number("", float(text), lo, hi, lo_open=lo_open, hi_open=hi_open)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"must be a finite number{bounds_text(lo, hi, lo_open, hi_open)}, "
                f"got {text!r}") from None
    parse.__name__ = "number"
    return parse


def whole_list(lo: int | None = None, hi: int | None = None) -> Callable[[str], tuple]:
    """An argparse ``type``: whole numbers in ``[lo, hi]`` separated by commas, each
    one number or a range ``a-b`` (``1,3,10``, ``1-10``), sorted without repeats."""
    def parse(text: str) -> tuple:
        out = set()
        try:
            for part in text.split(","):
                a, dash, b = part.strip().partition("-")
                out.update(range(int(a, 10), int(b, 10) + 1) if dash else (int(a, 10),))
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"expected whole numbers like 1,3,10 or 1-10, got {text!r}") from None
        if not out:
            raise argparse.ArgumentTypeError(f"expected at least one number, got {text!r}")
        if lo is not None and min(out) < lo:
            raise argparse.ArgumentTypeError(f"every value must be >= {lo}, got {text!r}")
        if hi is not None and max(out) > hi:
            raise argparse.ArgumentTypeError(f"every value must be <= {hi}, got {text!r}")
        return tuple(sorted(out))
    parse.__name__ = "list of whole numbers"
    return parse


#: ``--seed``: what numpy's generators take
SEED = whole(0, 2**32 - 1)


def _mkparent(path: Path, flag: str) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"{flag} {path}: cannot create the folder {path.parent} "
                        f"({exc.strerror or exc})") from None


def out_file(path: str | Path, flag: str = "--out") -> Path:
    """``--out FILE``: missing parent folders are created, an existing file is
    replaced, an existing folder is refused."""
    p = Path(path)
    if p.is_dir():
        raise UserError(f"{flag} {p}: is a folder; give the name of a file to write")
    _mkparent(p, flag)
    return p


def out_folder(path: str | Path, holds: Callable[[Path], bool] | None = None, what: str = "",
               force: bool | None = None, flag: str = "--out") -> Path:
    """``--out DIR``: missing parent folders are created and a file is refused. An
    existing folder must be empty, or one the command adds to (``holds(folder)``,
    e.g. a dataset folder for the commands that append trials; ``what`` names that
    kind), or ``force`` (the command's ``--force``; None when it has none) says to
    replace what it holds."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise UserError(f"{flag} {p}: is a file, not a folder")
    if p.is_dir() and any(p.iterdir()) and not force and not (holds and holds(p)):
        why = f" and is not {what}" if what else ""
        fix = "add --force to replace what it holds, or choose" if force is not None else "choose"
        raise UserError(f"{flag} {p}: the folder is not empty{why}; {fix} a new or empty folder")
    _mkparent(p, flag)
    return p


def dataset_folder(path: Path) -> bool:
    """A dataset folder, or one a dataset writer was stopped in before its first
    trial was complete (it holds only the writer's temporary ``.*.tmp`` files and the
    rig's run state): the folders that ``simulate``, ``record`` and ``rig run`` add to."""
    return addable_folder(path, (RUN_STATE,))


def emit(args, data, text: str | None = None) -> None:
    """Print ``data`` as one JSON document with ``--json``, else ``text``."""
    if getattr(args, "json", False):
        print(json.dumps(data, default=json_default))
    elif text is not None:
        print(text)


def progress_bar(total: int, desc: str, enabled: bool = True):
    """A frame progress bar on stderr: off when ``enabled`` is False or ``-q`` hides
    progress notes, else tqdm decides (``disable=None``: a bar only on a terminal)."""
    tqdm = need("tqdm").tqdm
    shown = enabled and logging.getLogger("host").isEnabledFor(logging.INFO)
    return tqdm(total=total, desc=desc, unit="frame", disable=not shown or None,
                file=sys.stderr, leave=False)


def real_data_dir(given: str | None) -> Path:
    """The real recordings folder: ``given``, $TACFOOT_REAL_DATA or ../shared/data."""
    for cand in (given, os.environ.get("TACFOOT_REAL_DATA"),
                 Path(__file__).resolve().parents[3] / "shared" / "data"):
        if cand and Path(cand).is_dir():
            return Path(cand)
    raise UserError("real recordings not found: pass --data DIR or set TACFOOT_REAL_DATA")


def is_recording(source: str) -> bool:
    """A video, an image folder or sim:// (not a scene name or a dataset folder)."""
    p = Path(source)
    return (source.startswith(("sim://", "file://", "v4l2://"))
            or (p.is_file() and p.suffix.lower() != ".toml")
            or (p.is_dir() and not is_dataset(p)))


def open_source(source: str):
    """The camera for a source string; a bad one raises its CameraError or
    InputError, which ``host``'s ``main`` reports in one line."""
    return open_camera(source)


def load_localiser(model_dir: str | None) -> Localiser | None:
    """The localiser in ``model_dir`` (None without one)."""
    return Localiser.load(model_dir) if model_dir else None


def load_regressor(model_dir: str | None) -> Regressor | None:
    """The pressure regressor in ``model_dir`` (None without one)."""
    return Regressor.load(model_dir) if model_dir else None


def open_stream(args, localiser: Localiser | None = None) -> MarkerStream:
    """The marker pipeline for ``args.profile``."""
    return MarkerStream(load_pipeline_profile(args.profile), localiser=localiser)
