"""The camera feed's grab thread (device/pi/runtime/feed.py): a lossless source is read
ahead and handed over whole and in order; a live one hands over the newest frame."""
from __future__ import annotations

import time

import numpy as np

from device.pi.runtime.feed import READ_AHEAD, READ_AHEAD_BYTES, CameraFeed, read_ahead_frames


class Counter:
    """A source of ``n`` numbered frames (None after the last), counting its reads."""

    def __init__(self, n: int):
        self.n = n
        self.reads = 0

    def read(self):
        if self.reads >= self.n:
            return None
        self.reads += 1
        return self.reads - 1

    def close(self):
        pass


def _drain(feed, limit_s: float = 5.0) -> list:
    got, t_end = [], time.monotonic() + limit_s
    while time.monotonic() < t_end:
        item = feed.get(0.05)
        if item == "eof":
            return got
        if item is not None:
            got.append(item[0])
    raise AssertionError(f"no eof after {limit_s} s, got {len(got)} frames")


def test_a_lossless_source_is_read_ahead_a_bounded_number_of_frames_and_handed_over_whole():
    cam = Counter(50)
    feed = CameraFeed(lambda: cam, lossless=True, first=cam).start()
    try:
        time.sleep(0.2)                               # the loop is busy: nothing taken
        assert cam.reads == READ_AHEAD + 1            # the queue is full, one more in hand
        first = feed.get(0.5)
        time.sleep(0.1)
        assert cam.reads == READ_AHEAD + 2            # the free slot is filled, no more
        assert _drain(feed) == list(range(1, 50)) and first[0] == 0
        assert feed.eof and feed.dropped == 0
    finally:
        feed.stop()


def test_a_live_source_hands_over_the_newest_frame_and_counts_the_rest():
    cam = Counter(30)
    feed = CameraFeed(lambda: cam, lossless=False, first=cam).start()
    try:
        time.sleep(0.2)                               # every frame read, none taken
        assert feed.get(0.5) == "eof"                 # only the newest item is left
        assert feed.dropped == 30                     # every frame overtaken by a newer one
    finally:
        feed.stop()


def test_stop_ends_a_grab_thread_that_waits_for_room():
    cam = Counter(1000)
    feed = CameraFeed(lambda: cam, lossless=True, first=cam).start()
    time.sleep(0.1)
    t0 = time.monotonic()
    feed.stop()
    assert time.monotonic() - t0 < 0.5


class Big:
    """``n`` frames of ``nbytes`` bytes each (None after the last)."""

    class Frame:
        def __init__(self, image):
            self.image = image

    def __init__(self, n: int, nbytes: int):
        self.n, self.nbytes, self.reads = n, nbytes, 0

    def read(self):
        if self.reads >= self.n:
            return None
        self.reads += 1
        return Big.Frame(np.zeros(self.nbytes, np.uint8))

    def close(self):
        pass


def test_large_frames_are_read_ahead_within_the_byte_budget():
    assert read_ahead_frames(640 * 480 * 3) == READ_AHEAD              # VGA: all 8
    assert read_ahead_frames(1920 * 1080 * 3) == 1                     # 1080p: one
    assert read_ahead_frames(READ_AHEAD_BYTES // 3) == 3
    assert read_ahead_frames(0) == READ_AHEAD
    cam = Big(20, READ_AHEAD_BYTES // 3)
    feed = CameraFeed(lambda: cam, lossless=True, first=cam).start()
    try:
        time.sleep(0.2)                               # the loop is busy: nothing taken
        assert cam.reads == 3 + 1                     # 3 queued (the budget), one in hand
        got = 0
        while feed.get(0.5) not in (None, "eof"):
            got += 1
        assert got == 20
    finally:
        feed.stop()
