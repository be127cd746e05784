"""``host record``: a labelled trial from any camera (and IMU) without the rig.

One call records one trial of ``seconds`` of frames (or until a file source ends)
with one label, and appends it to a dataset folder (:mod:`host.data.dataset`), as
``host rig run`` does: the trial file is written under a temporary name and renamed
when complete, then the index. Frames are spooled to a temporary file in the
folder while they arrive, so a 30 s, 120 fps recording does not sit in memory; a
crash or Ctrl-C loses only the trial being recorded and leaves no temporary file (a
SIGKILL leaves its temporaries, named by its process id, which the folder's next
writer removes).

A recorded trial has no ground truth for contact or load: the dataset loader takes
contact from the marker pipeline (as for a CSV manifest of clips), and the label is
the surface and texture name of every contact frame. ``dataset.json`` keeps the
labels in ``record_labels`` (the ``surface_labels`` and ``texture_labels`` of the
folder) and each trial's ``label``, ``camera`` and ``imu``, the ``recording`` it
came from (:func:`host.data.recordings.source_recording`: a file's name and SHA-256
with ``start_frame``, ``simulated:SCENE seed N``, or a live session) and the
``profile`` it was recorded for with its ``profile_sha256``.

``frames=N`` (``host record --frames N --start K``, file and simulated sources)
records exactly N frames from frame K of the source; a source that ends sooner is a
RecordError and nothing is added.

A trial from a video file stores the file's compressed packets, not the decoded
frames: :func:`remux_clip` copies the packets from the keyframe at or before the
trial's first frame to its last frame into a small file of the same container,
without re-encoding (PyAV), and the dataset writer keeps that clip only when it
decodes to exactly the frames read (``frames_codec`` ``source-video``,
``video_range`` [first, first + N) in the clip, first = the frames from the keyframe
to frame K). Otherwise it stores the frame array and says why in the trial's
``frames_note``. On roboskin's clips (a keyframe every 12 frames) a trial of 10 % of
a clip takes about 1.1x the source's bytes for those frames; the frame array took
about 13x. The source is read one packet at a time, no further than the trial's
last frame, and a trial of a video file keeps the file's own frame times in ``t_s``
(:func:`host.data.video.frame_times`; the entry's ``timestamps`` says whose).
"""
from __future__ import annotations

import logging
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from device.pi.sources.camera import CameraSource
from device.pi.sources.imu import ImuSource
from host.data.dataset import DatasetError, DatasetWriter, addable_folder, temp_prefix
from host.data.recordings import profile_ref, source_recording
from host.data.video import frame_times
from host.data.windows import LABEL_RE, check_label_name
from host.rig.trials import RUN_STATE
from device.errors import TacfootError

__all__ = ["RecordError", "record", "LABEL_RE"]


class RecordError(TacfootError, ValueError):
    """A bad argument or an unusable output folder; the message names it."""


def _labels(writer: DatasetWriter, label: str) -> list[str]:
    idx = writer.index
    if idx.get("source") not in (None, "record"):
        raise RecordError(f"{writer.dir}: a {idx['source']!r} dataset; record into its own "
                          f"folder")
    names = list(idx.get("record_labels") or [])
    if label not in names:
        names.append(label)
    return names


def _video_file(url: str) -> Path | None:
    """The video file behind a camera source string, if it is one."""
    from device.pi.sources.camera import VIDEO_SUFFIXES
    s = url[len("file://"):] if url.startswith("file://") else url
    p = Path(s)
    return p if "://" not in s and p.suffix.lower() in VIDEO_SUFFIXES and p.is_file() else None


def remux_clip(video: Path, start: int, n: int, folder: Path) -> tuple[Path, int] | str:
    """Copy the packets of ``video``'s first video stream, from the keyframe at or
    before frame ``start`` through frame ``start + n - 1``, into ``folder/clip.SUFFIX``
    without re-encoding. Returns (the clip, the clip's frame that is frame ``start``),
    or why it cannot (no PyAV, a stream that reorders frames, too few packets)."""
    try:
        import av
    except ImportError:
        return "no remux: PyAV (av) is not installed"
    from host.data.video import video_packets
    dst = Path(folder) / f"clip{Path(video).suffix.lower()}"
    try:
        with av.open(str(video)) as ic:
            if not ic.streams.video:
                return f"no remux: {Path(video).name} has no video stream"
            stream = ic.streams.video[0]
            # from the last keyframe at or before frame start through frame start + n - 1,
            # reading no packet after it
            kept: list = []             # the packets from the last keyframe so far
            k = None
            for i, p in enumerate(video_packets(ic, stream)):
                if i < start + n and kept and (p.pts is None or p.pts != p.dts
                                               or p.dts <= kept[-1].dts):
                    return "no remux: the stream's packets are not one per frame in order"
                if p.is_keyframe and i <= start:
                    kept, k = [], i
                if k is not None:
                    kept.append(p)
                if i >= start + n - 1:
                    break
            if k is None:
                return f"no remux: no keyframe at or before frame {start}"
            if k + len(kept) < start + n:
                return (f"no remux: {k + len(kept)} packets for frames {start} .. "
                        f"{start + n - 1}")
            if kept[0].pts is None or kept[0].pts != kept[0].dts:
                return "no remux: the stream's packets are not one per frame in order"
            with av.open(str(dst), "w") as oc:
                out = oc.add_stream_from_template(stream)
                t0 = kept[0].dts
                for p in kept:
                    p.stream = out
                    p.dts -= t0
                    p.pts -= t0
                    oc.mux(p)
    except (av.FFmpegError, OSError, ValueError) as exc:
        return f"no remux: {exc}"
    return dst, start - k


def _frame_times(grid: list[float], src: list[float], clock, video: Path | None,
                 camera_url: str, fps: float | None) -> tuple[list[float], dict]:
    """The trial's ``t_s`` and the entry's ``timestamps`` note. A video file's frames
    keep the file's own times (pts x time_base) when it has one per frame, strictly
    increasing; else they are on the reader's uniform 1/fps grid and one warning line
    says why (a variable-rate file's real times are then lost)."""
    if video is None:
        return grid, {}
    why = clock if isinstance(clock, str) else None
    if why is None and len(src) != len(grid):
        why = f"{len(src)} frame times for {len(grid)} frames"
    if why is None and (not np.all(np.isfinite(src)) or np.any(np.diff(src) <= 0)):
        why = "its frame times are not strictly increasing"
    if why is None:
        t = [float(x - src[0]) for x in src]
        return t, {"timestamps": "the file's own (pts x time_base)"}
    rate = f"{fps:g} frames/s" if fps else "1 frame/s"
    logging.getLogger(__name__).warning(
        "warning: %s: the file's own frame times are not used (%s); t_s is on a uniform "
        "grid at %s, the rate it declares", camera_url, why, rate)
    return grid, {"timestamps": f"uniform at {rate} (the file's own not used: {why})"}


def record(camera: CameraSource, imu: ImuSource | None, label: str, seconds: float,
           out: Path | str, *, camera_url: str = "", imu_url: str = "",
           progress=None, frames: int | None = None, start: int = 0,
           profile: str = "roboskin") -> dict:
    """Record frames from ``camera`` for ``seconds`` of stream time (or until it
    ends), or exactly ``frames`` frames (``seconds`` None), one IMU row per frame
    from ``imu`` when given, and append the trial to the dataset folder ``out``.
    ``start``: the source frame ``camera`` starts at (opened with
    ``start_frame=start``; the IMU skips as many rows), kept in the trial's
    ``recording``. ``progress``: a callable taking the number of new frames (a
    progress bar's ``update``). Returns the trial's index entry."""
    check_label_name(label, "--label", RecordError)     # the rule host train applies too
    if frames is None and seconds is None:
        raise RecordError("give --seconds or --frames")
    if frames is not None and seconds is not None:
        raise RecordError(f"give --seconds or --frames, not both (got --seconds {seconds} "
                          f"and --frames {frames})")
    if frames is not None and (isinstance(frames, bool) or not isinstance(frames, int)
                               or frames < 1):
        raise RecordError(f"--frames must be a whole number >= 1, got {frames!r}")
    if isinstance(start, bool) or not isinstance(start, int) or start < 0:
        raise RecordError(f"--start must be a whole number >= 0, got {start!r}")
    if seconds is not None and not (isinstance(seconds, (int, float)) and np.isfinite(seconds)
                                    and seconds > 0):
        raise RecordError(f"--seconds must be a number > 0, got {seconds!r}")
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise RecordError(f"--out {out}: exists and is not a folder")
    if out.is_dir() and not addable_folder(out, (RUN_STATE,)):
        raise RecordError(f"--out {out}: a folder that is not a tacfoot dataset; choose an "
                          f"empty or new folder")
    if not out.parent.is_dir():
        raise RecordError(f"--out {out}: the parent folder {out.parent} does not exist")
    try:
        writer = DatasetWriter(out, source="record")     # reads and checks the index
    except DatasetError as exc:
        raise RecordError(str(exc)) from None
    try:
        names = _labels(writer, label)
    except RecordError:
        writer.close()
        raise

    fd, spool = tempfile.mkstemp(prefix=temp_prefix("record"), suffix=".tmp", dir=out)
    shape = None
    t_s, imu_rows, imu_faults = [], [], []
    t_wall = time.time()
    clip_dir = None
    # a video file's own frame times (pts x time_base), read beside its frames
    source_video = _video_file(camera_url)
    clock = frame_times(source_video, start) if source_video is not None else None
    clock_gen = None if isinstance(clock, str) else clock    # closed at the end
    t_src: list[float] = []
    try:
        if imu is not None:
            for _ in range(start):          # the IMU row of the first recorded frame
                imu.read()
        with os.fdopen(fd, "wb") as fh:
            t0 = None
            for fr in camera:
                if frames is not None and len(t_s) >= frames:
                    break
                img = fr.image
                if img.ndim == 3:
                    import cv2
                    img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
                if shape is None:
                    shape = img.shape
                    t0 = fr.t_s
                elif img.shape != shape:
                    raise RecordError(f"{camera_url or camera}: frame {fr.index} is "
                                      f"{img.shape[1]}x{img.shape[0]}, the first was "
                                      f"{shape[1]}x{shape[0]}")
                t = fr.t_s - t0
                if clock is not None and not isinstance(clock, str):
                    ts = next(clock, None)
                    if ts is None:
                        clock = "the file has fewer packets than frames"
                    else:
                        t_src.append(ts)
                        t = ts - t_src[0]
                if seconds is not None and t >= seconds:
                    break
                fh.write(np.ascontiguousarray(img, np.uint8).tobytes())
                t_s.append(fr.t_s - t0)
                if imu is not None:
                    v, f = imu.read()
                    imu_rows.append(np.array(v, np.float32))
                    imu_faults.append(int(f))
                if progress is not None:
                    progress(1)
        n = len(t_s)
        if n == 0:
            raise RecordError(f"{camera_url or camera}: no frames"
                              + (f" from frame {start}" if start else ""))
        if frames is not None and n < frames:
            raise RecordError(f"{camera_url or camera}: --frames {frames} from --start "
                              f"{start}, but the source ends after {n} frames (frame "
                              f"{start + n - 1})")
        t_s, times_note = _frame_times(t_s, t_src[:n], clock, source_video, camera_url,
                                       getattr(camera, "fps", None))
        data = np.memmap(spool, np.uint8, "r", shape=(n, *shape))
        code = names.index(label)
        truth = {"t_s": np.asarray(t_s, np.float64),
                 "surface": np.full(n, code, np.int8), "texture": np.full(n, code, np.int8)}
        if imu is not None:
            truth["imu"] = np.stack(imu_rows)
            truth["imu_faults"] = np.asarray(imu_faults, np.uint16)
        fps = (n - 1) / t_s[-1] if n > 1 and t_s[-1] > 0 else None
        writer.index.update({"source": "record", "record_labels": names,
                             "surface_labels": names, "texture_labels": names})
        rec = source_recording(camera_url, t_wall) if camera_url else {"id": f"live:{t_wall}"}
        rec["start_frame"] = int(start)
        prof = profile_ref(profile)
        info = {"label": label, "camera": camera_url, "imu": imu_url or None,
                "recording": rec, "profile": prof["name"], "profile_sha256": prof["sha256"],
                "fps": None if fps is None else round(fps, 3), "width": int(shape[1]),
                "height": int(shape[0]), "recorded_at": round(t_wall, 3),
                "seconds": round(float(t_s[-1]), 4)}
        info.update(times_note)
        video, first = source_video, int(start)
        # the clip's temporary folder is a writer's temporary in --out: the next writer
        # removes it if this process is killed
        clip_dir = tempfile.mkdtemp(prefix=temp_prefix("clip"), suffix=".tmp", dir=out)
        if video is not None:
            got = remux_clip(video, first, n, Path(clip_dir))
            if isinstance(got, str):      # the whole file, when it is most of it
                info["frames_note"] = got
            else:
                video, first = got
        path = writer.add_trial(data, truth, info, video=video, video_start=first)
        del data
        return dict(writer.index["trials"][-1], path=str(path))
    finally:
        writer.close()
        if clock_gen is not None:
            clock_gen.close()
        if clip_dir is not None:
            shutil.rmtree(clip_dir, ignore_errors=True)
        try:
            os.unlink(spool)
        except FileNotFoundError:
            pass
