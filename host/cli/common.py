"""What every ``host`` command shares: the bad-input error and its exit status,
JSON output, progress bars, and opening sources, streams and models."""
from __future__ import annotations

import json
import os
import sys
from pathlib import Path

from device.pi.models.artefact import ModelError
from device.pi.models.regressor import Regressor
from device.pi.sources.camera import CameraError, open_camera
from device.pi.models.localiser import Localiser
from device.pi.vision.pipeline import MarkerStream
from device.profile import load_pipeline_profile
from host.data.dataset import is_dataset
from host.learn.onnx_io import json_default  # noqa: F401  (the commands' JSON of numpy values)

EXIT_BAD_INPUT = 2


class UserError(Exception):
    """Bad input from the user: printed as one line, exit status 2."""


def emit(args, data, text: str | None = None) -> None:
    """Print ``data`` as one JSON document with ``--json``, else ``text``."""
    if getattr(args, "json", False):
        print(json.dumps(data, default=json_default))
    elif text is not None:
        print(text)


def progress_bar(total: int, desc: str, enabled: bool = True):
    """A frame progress bar on stderr (off when ``enabled`` is False)."""
    from tqdm import tqdm
    return tqdm(total=total, desc=desc, unit="frame", disable=not enabled or None,
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
    """The camera for a source string; a bad one is a :class:`UserError`."""
    try:
        return open_camera(source)
    except (CameraError, ValueError) as exc:
        raise UserError(str(exc)) from None


def _load_model(load, model_dir: str | None):
    if not model_dir:
        return None
    try:
        return load(model_dir)
    except ModelError as exc:
        raise UserError(str(exc)) from None


def load_localiser(model_dir: str | None) -> Localiser | None:
    """The localiser in ``model_dir`` (None without one)."""
    return _load_model(Localiser.load, model_dir)


def load_regressor(model_dir: str | None) -> Regressor | None:
    """The pressure regressor in ``model_dir`` (None without one)."""
    return _load_model(Regressor.load, model_dir)


def open_stream(args, localiser: Localiser | None = None) -> MarkerStream:
    """The marker pipeline for ``args.profile``."""
    return MarkerStream(load_pipeline_profile(args.profile), localiser=localiser)
