"""Video files on the host: a whole file's frames into memory for offline work (the
Pi reads frames one at a time through :mod:`device.pi.sources.camera`), and, for
``host record``, a file's packets, frame times and frame count read one packet at a
time, stopping when enough are read."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def video_frames(path, limit: int | None = None, gray: bool = False) -> list[np.ndarray]:
    """The frames of a video file, the first ``limit`` of them when given, as
    decoded (BGR) or, with ``gray``, as 2-D uint8. A file OpenCV cannot open is a
    ValueError naming the path."""
    import cv2

    from device.pi.vision.extract import to_gray

    cap = cv2.VideoCapture(str(Path(path)))
    if not cap.isOpened():
        raise ValueError(f"cannot open video: path={str(path)!r}")
    frames: list[np.ndarray] = []
    try:
        while limit is None or len(frames) < limit:
            ok, img = cap.read()
            if not ok:
                break
            frames.append(to_gray(img) if gray else img)
    finally:
        cap.release()
    return frames


#: presentation order may differ from the order packets are stored in (B-frames):
#: the times are sorted within this many packets
REORDER_PACKETS = 16


def video_packets(container, stream):
    """The packets of ``stream`` in stored order, one at a time (PyAV's demux, without
    the empty packets that flush the decoder): a caller that stops early reads no
    further into the file, so memory does not grow with the file's size."""
    for p in container.demux(stream):
        if p.size:
            yield p


def frame_times(path, start: int = 0):
    """The presentation times (s: pts x time_base, from the stream's first packet)
    of a video file's frames from frame ``start`` on, one per frame in presentation
    order, read from its packets as they are asked for (PyAV; sorted within
    ``REORDER_PACKETS`` packets). A generator, or a string saying why there are none
    (no PyAV, no video stream, a packet without a time)."""
    try:
        import av
    except ImportError:
        return "PyAV (av) is not installed"
    try:
        container = av.open(str(path))
    except (av.FFmpegError, OSError, ValueError) as exc:
        return f"cannot open it with PyAV ({exc})"
    if not container.streams.video:
        container.close()
        return "no video stream"

    def times():
        import heapq
        stream = container.streams.video[0]
        tb = stream.time_base
        heap: list[int] = []
        k, t0 = 0, None
        try:
            for p in video_packets(container, stream):
                if p.pts is None or tb is None:
                    raise ValueError(f"packet {k} has no presentation time")
                heapq.heappush(heap, int(p.pts))
                if len(heap) > REORDER_PACKETS:
                    pts = heapq.heappop(heap)
                    t0 = pts if t0 is None else t0
                    if k >= start:
                        yield float((pts - t0) * tb)
                    k += 1
            while heap:
                pts = heapq.heappop(heap)
                t0 = pts if t0 is None else t0
                if k >= start:
                    yield float((pts - t0) * tb)
                k += 1
        finally:
            container.close()
    return times()


def count_frames(path, most: int) -> int:
    """The number of frames in a video file, counted as they are read and no more
    than ``most`` (its packets with PyAV; else frames grabbed with OpenCV); never the
    container's own estimate, which can be several times the truth."""
    most = max(0, int(most))
    try:
        import av
    except ImportError:
        av = None
    if av is not None:
        try:
            with av.open(str(path)) as c:
                n = 0
                for _ in (video_packets(c, c.streams.video[0]) if c.streams.video else ()):
                    if n >= most:
                        break
                    n += 1
                return n
        except (av.FFmpegError, OSError, ValueError):
            pass                         # a file PyAV cannot read: OpenCV counts
    import cv2
    cap = cv2.VideoCapture(str(path))
    n = 0
    try:
        while n < most and cap.grab():
            n += 1
    finally:
        cap.release()
    return n
