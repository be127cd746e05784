"""Camera sources behind one small interface, chosen by a source string.

Like pyserial's ``serial_for_url``, the string picks the implementation::

    open_camera("v4l2:///dev/video0?width=640&height=480&fps=120&fourcc=MJPG")
    open_camera("file://clips/smooth.avi", start_frame=10, end_frame=100)
    open_camera("clips/smooth.avi")                 # bare path to a video file
    open_camera("data/tactip_shear/images/")        # folder of images, natural order
    open_camera("sim://walk?seed=3")                # frames rendered by device.sim

Every source has ``read() -> Frame | None`` (None at the end of a stream),
iteration, ``close()``, context-manager use, and ``width``, ``height``, ``fps``
(None when unknown) and ``n_frames`` (None when unknown or live; for video files it
is the container's count, which can be approximate).

``Frame.index`` is the frame's number in the whole stream (with ``start_frame=10``
the first frame has index 10). ``Frame.t_s`` is stream time ``index / fps`` for
files, folders and the simulator (``float(index)`` when the fps is unknown, as if
1 fps), and ``time.monotonic()`` just after the frame was grabbed for live cameras.

Options come as keyword arguments or in the URL query (``?seed=3``); keyword
arguments win. An option a source does not know is a ``ValueError`` naming it.

* file / folder / sim: ``start_frame`` (int, default 0), ``end_frame`` (int,
  exclusive, default: to the end), ``fps`` (float in 1..1000, the bound ``--fps``
  has; overrides the declared rate),
  ``realtime`` (bool: pace ``read()`` to ``fps`` instead of returning at once).
* sim: ``seed`` (int, default 0).
* v4l2: ``width``, ``height`` (int), ``fps`` (float in 1..1000), ``fourcc`` (4 chars, e.g.
  MJPG or YUYV), ``buffersize`` (int, default 1: always the newest frame).
* every source: ``gray`` (bool, default false): frames come as HxW gray uint8,
  converted in ``read()`` (the runtime's grab thread), so the marker pipeline reads the
  dome box in place and its loop converts nothing. A decoded colour frame is converted
  with the pipeline's own ``cv2.cvtColor`` (the same pins to the bit); a V4L2 camera
  in YUYV / UYVY / GREY hands over its luma plane without decoding colour
  (``device/pi/sources/luma.py``: the colour path's gray for neutral pixels). Simulator
  frames are gray already.

A video file whose header declares a rate outside 1..1000 frames/s (a broken
or odd header) is read at :data:`DEFAULT_FILE_FPS`, with a warning on stderr; a
simulated scene's rate is checked when the scene loads. A live camera that
reports such a rate counts as one whose rate is unknown.

Without ``gray``, images are returned as decoded: video frames as HxWx3 BGR uint8; folder images with
``cv2.IMREAD_UNCHANGED`` (a grayscale PNG stays HxW; an alpha channel is dropped);
simulator frames as HxW gray. Each ``read()`` returns a new array, so frames can be
kept (e.g. as a reference frame).
"""

from __future__ import annotations

import logging
import errno
import math
import os
import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator
from urllib.parse import parse_qsl, unquote, urlsplit

import cv2
import numpy as np

from device.checks import FPS_MAX_HZ, FPS_MIN_HZ
from device.pi.sources.luma import PACKED_YUV, PLANE_GRAY, luma_plane, to_gray_frame
from device.pi.sources.options import opt_bool, opt_fps, opt_int, parse_options
from device.closing import Closing
from device.errors import InputError, TacfootError

_log = logging.getLogger(__name__)

__all__ = [
    "BadFrameError",
    "CameraError",
    "CameraSource",
    "Frame",
    "ImageFolderSource",
    "SimSource",
    "V4L2Source",
    "VideoFileSource",
    "open_camera",
    "IMAGE_SUFFIXES",
    "VIDEO_SUFFIXES",
    "DEFAULT_FILE_FPS",
]

#: the rate a video file is read at when its header declares an implausible one
#: (the leg camera's usual rate)
DEFAULT_FILE_FPS = 120.0

IMAGE_SUFFIXES = frozenset({".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".pbm", ".webp"})
VIDEO_SUFFIXES = frozenset({".avi", ".mp4", ".mkv", ".mov", ".m4v", ".webm", ".mpg", ".mpeg", ".wmv", ".h264"})


class CameraError(TacfootError, OSError):
    """A camera or recording cannot be opened or read."""


class BadFrameError(CameraError):
    """One frame of a file source cannot be read (an unreadable or odd-sized image);
    the source has moved past it, so the next ``read()`` gives the frame after."""


@dataclass(frozen=True, slots=True)
class Frame:
    index: int          # frame number in the stream
    t_s: float          # stream time (files, sim) or time.monotonic() (live)
    image: np.ndarray   # uint8, HxW gray or HxWx3 BGR

    def __repr__(self) -> str:
        return f"Frame(index={self.index}, t_s={self.t_s:.6f}, image={self.image.dtype}{self.image.shape})"


# ------------------------------------------------------------------ options
def _opt_fourcc(name: str, value: Any) -> str:
    if not isinstance(value, str) or len(value) != 4 or not value.isascii():
        raise InputError(f"{name} must be 4 ASCII characters such as 'MJPG', got {value!r}")
    return value


def _range_opts(opts: dict) -> tuple[int, int | None]:
    start = opts.get("start_frame", 0)
    end = opts.get("end_frame")
    if start < 0:
        raise InputError(f"start_frame must be >= 0, got {start!r}")
    if end is not None and end < start:
        raise InputError(f"end_frame must be >= start_frame ({start}), got {end!r}")
    return start, end


def _fps_opt(opts: dict) -> float | None:
    fps = opts.get("fps")
    return None if fps is None else opt_fps("fps", fps)


def _plausible_fps(fps) -> bool:
    return math.isfinite(fps) and FPS_MIN_HZ <= fps <= FPS_MAX_HZ


_STREAM_OPTS = {"start_frame": opt_int, "end_frame": opt_int, "fps": opt_fps, "realtime": opt_bool,
                "gray": opt_bool}


# ------------------------------------------------------------------ base class
class CameraSource(Closing):
    """Base class: subclasses implement ``_next() -> (image, t_s) | None``."""

    source: str = ""
    width: int = 0
    height: int = 0
    fps: float | None = None
    n_frames: int | None = None

    def __init__(self) -> None:
        self._closed = False
        self._index = 0                   # index of the next frame
        self._realtime = False
        self._pace_t0: float | None = None
        self._pace_i0 = 0

    # subclasses
    def _next(self) -> tuple[np.ndarray, float | None] | None:
        raise NotImplementedError

    def _release(self) -> None:
        pass

    # public
    def read(self) -> Frame | None:
        """The next frame, or None at the end of the stream."""
        if self._closed:
            raise ValueError(f"read from closed camera source {self.source!r}")
        got = self._next()
        if got is None:
            return None
        image, t_live = got
        index = self._index
        self._index += 1
        if t_live is not None:
            t_s = t_live
        else:
            t_s = index / self.fps if self.fps else float(index)
            if self._realtime and self.fps:
                self._pace(index)
        return Frame(index, t_s, image)

    def _open_file(self, path, source: str | None, start_frame: int, end_frame: int | None,
                   fps: float | None, realtime: bool) -> tuple[Path, int, int | None, float | None]:
        """Set-up shared by the file-backed sources: ``path``, ``source`` (default the
        path) and ``realtime``; returns the path, the checked frame range and fps."""
        path = Path(path)
        self.source = source if source is not None else str(path)
        self.path = path
        self._realtime = realtime
        start, end = _range_opts({"start_frame": start_frame, "end_frame": end_frame})
        return path, start, end, _fps_opt({"fps": fps})

    def _pace(self, index: int) -> None:
        now = time.monotonic()
        if self._pace_t0 is None:
            self._pace_t0, self._pace_i0 = now, index
            return
        delay = self._pace_t0 + (index - self._pace_i0) / self.fps - now
        if delay > 0:
            time.sleep(delay)

    def __iter__(self) -> Iterator[Frame]:
        while True:
            frame = self.read()
            if frame is None:
                return
            yield frame

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._release()

    @property
    def closed(self) -> bool:
        return self._closed

    def __repr__(self) -> str:
        return (f"{type(self).__name__}({self.source!r}, width={self.width}, height={self.height}, "
                f"fps={self.fps}, n_frames={self.n_frames})")


# ------------------------------------------------------------------ video file
class VideoFileSource(CameraSource):
    """A video file read with cv2.VideoCapture."""

    def __init__(self, path, *, start_frame: int = 0, end_frame: int | None = None,
                 fps: float | None = None, realtime: bool = False, gray: bool = False,
                 source: str | None = None):
        super().__init__()
        path, start, end, fps = self._open_file(path, source, start_frame, end_frame, fps, realtime)
        self.gray = opt_bool("gray", gray)
        self._decoded = None              # gray: the decode buffer, reused
        if not path.is_file():
            raise CameraError(errno.ENOENT, "no such video file", str(path))
        self._cap = cv2.VideoCapture(str(path))
        if not self._cap.isOpened():
            self._cap.release()
            raise CameraError(errno.EIO, "cannot open video file (not a video, or no decoder)", str(path))
        self.width = int(self._cap.get(cv2.CAP_PROP_FRAME_WIDTH))
        self.height = int(self._cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        declared = float(self._cap.get(cv2.CAP_PROP_FPS))
        if fps is None and _plausible_fps(declared):
            fps = declared
        elif fps is None:
            fps = DEFAULT_FILE_FPS
            _log.warning("warning: camera source %r: the file declares %g frames/s, outside "
                         "%g..%g; reading it at %g frames/s (give ?fps= to choose)",
                         self.source, declared, FPS_MIN_HZ, FPS_MAX_HZ, DEFAULT_FILE_FPS)
        self.fps = fps
        count = int(self._cap.get(cv2.CAP_PROP_FRAME_COUNT))
        total = count if count > 0 else None
        if total is not None:
            stop = total if end is None else min(end, total)
            self.n_frames = max(0, stop - start)
        elif end is not None:
            self.n_frames = None
        self._end = end
        # Skip by decoding: seeking by CAP_PROP_POS_FRAMES is not frame-exact for
        # every codec, and labels are indexed by decoded frame number.
        self._eof = False
        for _ in range(start):
            if not self._cap.grab():
                self._eof = True
                break
            self._index += 1

    def _next(self):
        if self._eof or (self._end is not None and self._index >= self._end):
            return None
        if not self.gray:
            ok, image = self._cap.read()
        else:                             # decode into one buffer; the gray copy is new
            ok, image = self._cap.read(self._decoded)
            self._decoded = image
        if not ok or image is None:
            self._eof = True
            return None
        return (to_gray_frame(image) if self.gray else image), None

    def _release(self) -> None:
        self._cap.release()


# ------------------------------------------------------------------ image folder
_DIGITS = re.compile(r"(\d+)")


def natural_key(name: str) -> tuple:
    """Sort key: digit runs compare as numbers (image_2 before image_10)."""
    parts = _DIGITS.split(name)
    primary = tuple((0, int(p)) if p.isdigit() else (1, p.lower()) for p in parts)
    return primary, name          # exact name breaks ties (a.png / A.png, 2 / 02)


class ImageFolderSource(CameraSource):
    """Images from a folder (natural order by name), or a single image file."""

    def __init__(self, path, *, start_frame: int = 0, end_frame: int | None = None,
                 fps: float | None = None, realtime: bool = False, gray: bool = False,
                 source: str | None = None):
        super().__init__()
        path, start, end, self.fps = self._open_file(path, source, start_frame, end_frame, fps, realtime)
        self.gray = opt_bool("gray", gray)
        if path.is_dir():
            files = [p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()]
            files.sort(key=lambda p: natural_key(p.name))
            if not files:
                raise CameraError(errno.ENOENT, "no image files in folder", str(path))
        elif path.is_file():
            files = [path]
        else:
            raise CameraError(errno.ENOENT, "no such image folder or file", str(path))
        self.files: list[Path] = files
        first = self._load(files[0])
        self.height, self.width = first.shape[:2]
        self._first = first if start == 0 else None
        self._index = start
        self._stop = len(files) if end is None else min(end, len(files))
        self.n_frames = max(0, self._stop - start)

    @staticmethod
    def _load(p: Path) -> np.ndarray:
        image = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise CameraError(errno.EIO, "cannot decode image", str(p))
        if image.dtype != np.uint8:
            raise CameraError(errno.EINVAL, f"image is {image.dtype}, expected uint8", str(p))
        if image.ndim == 3 and image.shape[2] == 4:
            image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
        elif image.ndim == 3 and image.shape[2] == 1:
            image = image[:, :, 0]
        return image

    def _next(self):
        i = self._index
        if i >= self._stop:
            return None
        if i == 0 and self._first is not None:
            image, self._first = self._first, None
        else:
            try:
                image = self._load(self.files[i])
            except CameraError as exc:
                self._index += 1                    # the next read() goes on past it
                raise BadFrameError(exc.errno, exc.strerror, exc.filename) from None
        if image.shape[:2] != (self.height, self.width):
            self._index += 1
            raise BadFrameError(errno.EINVAL,
                                f"image is {image.shape[1]}x{image.shape[0]}, the folder's first "
                                f"is {self.width}x{self.height}", str(self.files[i]))
        return (to_gray_frame(image) if self.gray else image), None


# ------------------------------------------------------------------ simulator
class SimSource(CameraSource):
    """Frames rendered by ``device.sim.Simulator``. ``.sim`` and ``.truth`` give the
    simulator and its per-frame ground truth."""

    def __init__(self, scene: str, *, seed: int = 0, start_frame: int = 0, end_frame: int | None = None,
                 fps: float | None = None, realtime: bool = False, gray: bool = True,
                 source: str | None = None):
        super().__init__()
        from device.sim import Simulator, load_scene   # lazy: the Pi never needs the simulator

        if not scene:
            raise InputError(f"sim source needs a scene name or path, got {source or scene!r}")
        self.source = source if source is not None else f"sim://{scene}"
        start, end = _range_opts({"start_frame": start_frame, "end_frame": end_frame})
        self.sim = Simulator(load_scene(scene), seed=seed)
        self.seed = seed
        self.width = int(self.sim.width)
        self.height = int(self.sim.height)
        sim_fps = float(self.sim.fps)
        self.fps = _fps_opt({"fps": fps}) or sim_fps
        self._realtime = realtime
        total = int(self.sim.n_frames)
        self._stop = total if end is None else min(end, total)
        self._index = start
        self.n_frames = max(0, self._stop - start)

    @property
    def truth(self):
        return self.sim.truth

    def _next(self):
        i = self._index
        if i >= self._stop:
            return None
        image = np.asarray(self.sim.render(i))          # gray already (``gray`` is moot)
        if image.dtype != np.uint8 or image.shape[:2] != (self.height, self.width):
            raise CameraError(errno.EINVAL,
                              f"simulator rendered {image.dtype}{image.shape} for frame {i}, expected "
                              f"uint8 ({self.height}, {self.width})", self.source)
        return image, None


# ------------------------------------------------------------------ live V4L2
class V4L2Source(CameraSource):
    """A live V4L2 camera. ``t_s`` is time.monotonic() just after the grab.

    A failed grab on an open camera raises CameraError (a live camera has no end of
    stream; most often it was unplugged)."""

    def __init__(self, device: str | int, *, width: int | None = None, height: int | None = None,
                 fps: float | None = None, fourcc: str | None = None, buffersize: int = 1,
                 gray: bool = False, source: str | None = None):
        super().__init__()
        self.device = device
        self.source = source if source is not None else f"v4l2://{device}"
        for name, v in (("width", width), ("height", height)):
            if v is not None and v <= 0:
                raise InputError(f"{name} must be > 0, got {v!r}")
        if buffersize < 1:
            raise InputError(f"buffersize must be >= 1, got {buffersize!r}")
        fps = _fps_opt({"fps": fps})
        if isinstance(device, str) and not os.path.exists(device):
            raise CameraError(errno.ENOENT, "no such camera device", device)
        cap = cv2.VideoCapture(device, cv2.CAP_V4L2)
        if not cap.isOpened():
            cap.release()
            raise CameraError(errno.EIO, "cannot open camera device with V4L2", str(device))
        self._cap = cap
        # Order matters for V4L2: pixel format, then size, then rate.
        if fourcc is not None:
            cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*fourcc))
        if width is not None:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, width)
        if height is not None:
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, height)
        if fps is not None:
            cap.set(cv2.CAP_PROP_FPS, fps)
        cap.set(cv2.CAP_PROP_BUFFERSIZE, buffersize)
        self.width = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH))
        self.height = int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        # a fixed size is part of the sensor's calibration: a driver that picked
        # another one is refused rather than silently used
        if (width is not None and self.width != width) or \
                (height is not None and self.height != height):
            cap.release()
            raise CameraError(errno.EINVAL, f"camera gives {self.width}x{self.height}, asked "
                                            f"for {width or self.width}x{height or self.height}",
                              str(device))
        got_fps = float(cap.get(cv2.CAP_PROP_FPS))
        self.fps = got_fps if _plausible_fps(got_fps) else None
        code = int(cap.get(cv2.CAP_PROP_FOURCC))
        self.fourcc = "".join(chr((code >> (8 * k)) & 0xFF) for k in range(4)) if code > 0 else None
        self.n_frames = None
        self.gray = opt_bool("gray", gray)
        # gray from a YUV or GREY camera: the raw buffer's luma plane, no colour decode;
        # from any other format (MJPG): the decoded frame, converted once here
        self._raw = None
        if self.gray and (self.fourcc in PACKED_YUV or self.fourcc in PLANE_GRAY):
            if cap.set(cv2.CAP_PROP_CONVERT_RGB, 0):
                self._raw = self.fourcc

    def _next(self):
        if not self._cap.grab():
            raise CameraError(errno.EIO, "camera grab failed (unplugged?)", str(self.device))
        t = time.monotonic()
        ok, image = self._cap.retrieve()
        if not ok or image is None:
            raise CameraError(errno.EIO, "camera retrieve failed", str(self.device))
        if self.gray:
            image = self._gray(image)
        return image, t

    def _gray(self, image: np.ndarray) -> np.ndarray:
        """The retrieved frame in gray: the luma plane of a raw buffer, else converted
        (a backend that ignored CONVERT_RGB gives a BGR frame of the right size)."""
        if self._raw is not None and not (image.ndim == 3 and image.shape[2] == 3):
            try:
                return luma_plane(image, self.width, self.height, self._raw)
            except ValueError as exc:
                raise CameraError(errno.EIO, f"camera buffer: {exc}", str(self.device)) from None
        return to_gray_frame(image)

    def _release(self) -> None:
        self._cap.release()


# ------------------------------------------------------------------ factory
_V4L2_OPTS = {"width": opt_int, "height": opt_int, "fps": opt_fps, "fourcc": _opt_fourcc,
              "buffersize": opt_int, "gray": opt_bool}
_SIM_OPTS = {**_STREAM_OPTS, "seed": opt_int}


def _open_path(path_str: str, source: str, query: dict, opts: dict) -> CameraSource:
    o = parse_options("camera", source, query, opts, _STREAM_OPTS)
    path = Path(path_str).expanduser()
    if path.is_dir() or path.suffix.lower() in IMAGE_SUFFIXES or path_str.endswith(("/", os.sep)):
        return ImageFolderSource(path, source=source, **o)
    if not path.exists():
        raise CameraError(errno.ENOENT, "does not exist (no such video file or image folder)",
                          str(path))
    return VideoFileSource(path, source=source, **o)


def open_camera(source: str, **opts) -> CameraSource:
    """Open the camera source named by ``source``; see the module docstring."""
    if not isinstance(source, str) or not source.strip():
        raise InputError(f"camera source must be a non-empty string, got {source!r}")
    if "://" not in source:
        return _open_path(source, source, {}, opts)
    scheme, rest = source.split("://", 1)
    scheme = scheme.lower()
    if scheme == "file":
        # file://rel/path, file:///abs/path. A query is taken only when the whole
        # string is not itself an existing path.
        path_str, query = rest, {}
        if "?" in rest and not Path(unquote(rest)).exists():
            path_str, q = rest.split("?", 1)
            query = dict(parse_qsl(q, keep_blank_values=True))
        path_str = unquote(path_str)
        if not path_str:
            raise InputError(f"file source needs a path, got {source!r}")
        return _open_path(path_str, source, query, opts)
    if scheme == "sim":
        parts = urlsplit(source)
        scene = unquote(parts.netloc + parts.path)
        o = parse_options("camera", source, dict(parse_qsl(parts.query, keep_blank_values=True)), opts, _SIM_OPTS)
        return SimSource(scene, source=source, **o)
    if scheme == "v4l2":
        parts = urlsplit(source)
        o = parse_options("camera", source, dict(parse_qsl(parts.query, keep_blank_values=True)), opts, _V4L2_OPTS)
        if parts.path:
            device: str | int = unquote(parts.path)
        elif parts.netloc.isdigit():
            device = int(parts.netloc)          # v4l2://0 -> camera index 0
        else:
            raise InputError(f"v4l2 source needs a device such as v4l2:///dev/video0, got {source!r}")
        return V4L2Source(device, source=source, **o)
    raise InputError(f"unknown camera source scheme {scheme!r} in {source!r}; "
                     f"use v4l2://, file://, sim:// or a path")
