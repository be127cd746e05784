"""The camera feed's grab thread (device/pi/runtime/feed.py): a lossless source is read
ahead and handed over whole and in order; a live one hands over the newest frame."""
from __future__ import annotations

import time

from device.pi.runtime.feed import READ_AHEAD, CameraFeed


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
