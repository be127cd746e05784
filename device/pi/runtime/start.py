"""A leg runtime from the command line's strings (``python -m device.pi run``): the
config, the models, the sources and the port, each refused with one line
(:class:`~device.pi.runtime.loop.StartupError`, exit 2). Split from
:mod:`device.pi.runtime.loop`."""
from __future__ import annotations

import logging
import os
import sys
from urllib.parse import parse_qsl, urlsplit
import cv2
from device.checks import frame_rate
from device.config import ConfigError
from device.pi.models.artefact import ModelError
from device.pi.runtime.config import load_leg_config
from device.pi.runtime.link import LinkError, open_port
from device.pi.runtime.load import check_models_folder, default_models_dir, load_models
from device.pi.sources.camera import CameraError, open_camera
from device.pi.sources.imu import IMUError, IMUUnavailable, RetryingImuSource, open_imu
from device.pi.sources.options import opt_bool
from device.profile import load_pipeline_profile
from device.pi.runtime.loop import LegRuntime, StartupError

_log = logging.getLogger(__name__)

# ---------------------------------------------------------------------------
# Building from source strings
# ---------------------------------------------------------------------------

def build_runtime(camera: str, imu: str, serial: str, *, models_dir=None, config=None,
                  fps: float | None = None, json_log: str | None = None,
                  status: str | None = None, frames: int | None = None,
                  float_models: bool = False, port=None, notify=None,
                  rules_only: bool = False) -> LegRuntime:
    """A runtime from the command line's strings; StartupError (exit 2) for a bad
    config, model, source or port, and for a models folder with no model in it: the
    leg runs on the surface rule alone only when ``rules_only`` asks for it (it then
    loads no model, says so in one line on stderr and in the status)."""
    if rules_only and models_dir is not None:
        raise StartupError(f"--rules-only loads no model; give it or --models "
                           f"{str(models_dir)!r}, not both")
    cv2.setNumThreads(1)              # one thread for the work (ONNX Runtime: intra_op 1)
    sys.setswitchinterval(0.001)      # hand a grabbed frame to the loop without a 5 ms wait
    try:
        cfg = load_leg_config(config)
    except ConfigError as exc:
        raise StartupError(str(exc)) from None
    if fps is not None:
        # the bound every frame rate has, a source's own ?fps= too
        cfg.camera.fps = frame_rate("--fps", fps, error=StartupError)
    try:
        load_pipeline_profile(cfg.models.profile)
    except (OSError, ValueError) as exc:         # ProfileError is a ValueError
        raise StartupError(f"{cfg.source or 'config'}: models.profile: {exc}") from None
    live = camera.lower().startswith("v4l2://")
    q = dict(parse_qsl(urlsplit(camera).query))
    try:
        # a file or sim:// source played at its frame rate delivers frames as a
        # camera does, whether or not the loop keeps up: the newest frame wins
        paced = opt_bool("realtime", q.get("realtime", False))
    except ValueError as exc:
        raise StartupError(f"--camera {camera!r}: {exc}") from None
    # frames come gray, converted on the grab thread (a YUYV camera's luma plane):
    # the loop reads the dome's box in place; ?gray=0 keeps the colour frames
    opts = {} if "gray" in q else {"gray": True}
    if live:
        c = cfg.camera
        for k, v in (("width", c.width), ("height", c.height), ("fps", c.fps),
                     ("fourcc", c.fourcc), ("buffersize", c.buffersize)):
            if k not in q:
                opts[k] = v

    def factory():
        return open_camera(camera, **opts)

    first = None
    opened = []                            # closed again if start-up fails later

    def fail(msg: str):
        for r in opened:
            try:
                r.close()
            except Exception:
                pass
        raise StartupError(msg)

    try:
        first = factory()
        opened.append(first)
    except CameraError as exc:
        if not live:
            raise StartupError(f"--camera {camera!r}: cannot open: {exc}") from None
        first = None                     # a live camera not there yet: fault + retries
    except ValueError as exc:
        raise StartupError(f"--camera: {exc}") from None
    if fps is None and first is not None and first.fps:
        cfg.camera.fps = float(first.fps)      # the rate the source actually runs at
    if status:
        if os.path.isdir(status):
            fail(f"--status {status!r} is a folder; give a file, e.g. "
                 f"{os.path.join(status, 'status.json')}")
        folder = os.path.dirname(os.path.abspath(status))
        if not os.path.isdir(folder):
            fail(f"--status {status!r}: the folder {folder} does not exist")
        if not os.access(folder, os.W_OK):
            fail(f"--status {status!r}: the folder {folder} is not writable")
    if models_dir is not None:
        check_models_folder(models_dir, fail)
    try:
        # the pins and the pipeline are the models' profile's (their model spec)
        models = load_models(models_dir, "float" if float_models else cfg.models.variant,
                             None, cfg, rules_only=rules_only)
    except (ModelError, ValueError) as exc:
        fail(str(exc))
    if rules_only:
        _log.warning("device.pi run: note: --rules-only: no model loaded; the surface "
                     "decision comes from the rules alone (status: rules_only true)")
    elif not models.loaded:
        where = models_dir if models_dir is not None else default_models_dir()
        fail(f"no model found in {'--models ' if models_dir is not None else ''}"
             f"{str(where)!r} (it should hold surface/, texture/, slip/ or pressure/); "
             f"give --models DIR, or --rules-only to run on the surface rules alone")
    try:
        imu_src = open_imu(imu)
        opened.append(imu_src)
    except IMUUnavailable as exc:
        # nothing answers yet: run with the IMU fault set and keep trying (a wrong
        # device or a bad option below still refuses to start)
        _log.warning("device.pi run: warning: --imu: %s; running with the IMU fault set, "
                     "retrying", exc)
        imu_src = RetryingImuSource(imu, exc)
        opened.append(imu_src)
    except (ValueError, IMUError) as exc:
        fail(f"--imu: {exc}")
    if port is None:
        try:
            port = open_port(serial, cfg.serial.baudrate)
            opened.append(port)
        except LinkError as exc:
            fail(str(exc))
    log = None
    if json_log:
        try:
            log = open(json_log, "wb", buffering=0)    # line by line: greppable live
        except OSError as exc:
            fail(f"--json-log {json_log!r}: {exc}")
    return LegRuntime(cfg, factory, imu_src, port, models, lossless=not (live or paced),
                      fps=cfg.camera.fps,
                      json_log=log, status_path=status, max_frames=frames, first_camera=first,
                      notify=notify, camera_opts=opts if live else None)
