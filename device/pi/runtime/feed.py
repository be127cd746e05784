"""The camera feed: frames from a camera source on a grab thread, with reopen and
backoff, so a camera that blocks or vanishes cannot stall the leg runtime's loop."""
from __future__ import annotations

import queue
import threading
import time

from device.pi.sources.camera import BadFrameError

#: frames a lossless source (a file, sim://) is read ahead of the loop
READ_AHEAD = 8
#: and at most this many bytes of them (at least one frame): 8 VGA colour frames,
#: one 1080p frame
READ_AHEAD_BYTES = 8 * 1024 * 1024


def read_ahead_frames(nbytes: int) -> int:
    """Frames a lossless source is read ahead when each holds ``nbytes`` bytes."""
    if nbytes <= 0:
        return READ_AHEAD
    return max(1, min(READ_AHEAD, READ_AHEAD_BYTES // nbytes))


class CameraFeed:
    """Frames from a camera factory on a grab thread.

    ``lossless`` (files and sim:// read as fast as the loop goes): every frame is
    handed over in order (the grab thread waits for the loop). Otherwise (live
    cameras, and sources paced at their frame rate) the newest frame wins: a frame
    the loop has not taken when the next one arrives is dropped and counted in
    ``dropped``, so a loop that falls behind works on the newest frame, and each
    decision keeps the time stamp of the frame it was made on. A source that raises is closed and reopened with a backoff doubling from
    ``reopen_min_s`` to ``reopen_max_s``; the thread never gives up. ``read()``
    returning None ends a finite stream (``eof``). A file source's unreadable frame
    (``BadFrameError``: the source has moved past it) is counted in ``skipped`` and
    reading goes on: reopening a file would replay it from the start."""

    def __init__(self, factory, *, lossless: bool, reopen_min_s: float = 0.1,
                 reopen_max_s: float = 2.0, first=None, clock=time.monotonic):
        self.factory = factory
        self.lossless = lossless
        self.min_s, self.max_s = reopen_min_s, reopen_max_s
        self.clock = clock
        self._q: queue.Queue = queue.Queue(maxsize=READ_AHEAD)
        self._limit = READ_AHEAD          # frames read ahead, fewer for large frames
        self._room = threading.Event()   # lossless: set by get() once half the queue is free
        self._stop = threading.Event()
        self._reopen = threading.Event()
        self._cam = first
        self.opens = 1 if first is not None else 0
        self.errors = 0
        self.skipped = 0                  # unreadable frames of a file source, skipped
        self.dropped = 0                  # frames overtaken by a newer one (loop behind)
        self.last_error = ""
        self.eof = False
        self.opened_at = clock() if first is not None else None
        self._thread = threading.Thread(target=self._run, name="camera", daemon=True)

    def start(self):
        self._thread.start()
        return self

    def _put(self, item) -> None:
        if self.lossless:
            # read ahead (read_ahead_frames of this frame's size); when that many are
            # queued, wait until get() has freed half of them: the loop wakes this
            # thread once per READ_AHEAD // 2 frames, not per frame
            if item is not None:
                image = getattr(item[0], "image", None)
                self._limit = read_ahead_frames(int(getattr(image, "nbytes", 0)))
            while not self._stop.is_set():
                if self._q.qsize() < self._limit:
                    try:
                        self._q.put_nowait(item)
                        return
                    except queue.Full:
                        pass
                self._room.clear()
                if self._q.qsize() < self._limit:             # freed meanwhile
                    continue
                self._room.wait(0.05)
        else:
            while True:                                   # newest only: drop older frames
                try:
                    if self._q.get_nowait() is not None:
                        self.dropped += 1
                except queue.Empty:
                    break
            try:
                self._q.put_nowait(item)
            except queue.Full:
                pass

    def _run(self) -> None:
        backoff = self.min_s
        while not self._stop.is_set():
            if self._reopen.is_set():
                self._reopen.clear()
                self._close_cam()
            if self._cam is None:
                try:
                    self._cam = self.factory()
                    self.opens += 1
                    self.opened_at = self.clock()
                    backoff = self.min_s
                except Exception as exc:        # CameraError, OSError, driver errors
                    self.errors += 1
                    self.last_error = str(exc)
                    self._stop.wait(backoff)
                    backoff = min(self.max_s, max(backoff * 2, 1e-3))
                    continue
            try:
                fr = self._cam.read()
            except BadFrameError as exc:        # one bad file frame: skip it, go on
                self.skipped += 1
                self.last_error = str(exc)
                continue
            except Exception as exc:            # unplugged: close, reopen with backoff
                self.errors += 1
                self.last_error = str(exc)
                self._close_cam()
                self._stop.wait(backoff)
                backoff = min(self.max_s, max(backoff * 2, 1e-3))
                continue
            if fr is None:
                self.eof = True
                self._put(None)
                return
            self._put((fr, self.clock()))

    def _close_cam(self) -> None:
        cam, self._cam = self._cam, None
        if cam is not None:
            try:
                cam.close()
            except Exception:
                pass

    def get(self, timeout: float):
        """(Frame, t_available) or None (no frame within ``timeout``), or the string
        "eof" at the end of a finite stream."""
        try:
            item = self._q.get(timeout=max(timeout, 0.0)) if timeout > 0 else self._q.get_nowait()
        except queue.Empty:
            return None
        if self._q.qsize() <= self._limit // 2 and not self._room.is_set():
            self._room.set()
        return "eof" if item is None else item

    def reopen(self) -> None:
        """Ask for a reopen (e.g. a new frame rate); done on the grab thread before
        its next grab."""
        self._reopen.set()

    def stop(self) -> None:
        self._stop.set()
        self._room.set()
        try:
            self._q.get_nowait()
        except queue.Empty:
            pass
        self._thread.join(timeout=2.0)
        self._close_cam()
