"""The runtime's garbage-collector policy: one full collection before the loop, then,
after a warm-up, the objects that live for the whole run are frozen, so that no
collection of the steady state walks them. See docs/reliability.md ("Garbage
collection in the loop") and docs/BENCHMARKS.md for the figures.

Why: a started runtime holds about 37,000 objects the collector tracks (the models,
ONNX Runtime, OpenCV, numpy and the config). Measured on the 2-core bench machine,
a gen-2 (full) collection over them takes 8-11 ms of CPU (about 40 ms on a Pi 4
core: five frames at 120 fps), and the first one comes by itself in the steady
state (no full collection ever ran, so every long-lived object counts as new).
Frozen, they are out of every collection: a full one walks only what the run made
since, well under a millisecond.

What it leaves alone: automatic collection stays on, with CPython's thresholds.
The steady state makes almost no container objects (about 0.3 gen-0 collections
per 1,000 frames, 0.05 ms each, on the sim walk), so there is nothing to win by
turning it off, and turned off, a path that makes reference cycles (an exception's
traceback on each camera error, say) would grow memory without bound.

Process-wide by nature (CPython has one collector): :meth:`GcPolicy.close`
unfreezes and removes the callback, so a process that runs a runtime in-process
(tests, host tools) gets its collector back as it was.
"""
from __future__ import annotations

import gc
import time

#: frames processed before the long-lived objects are frozen: the first frames load
#: what is loaded lazily (ONNX Runtime's first run, the tracker's buffers)
WARMUP_FRAMES = 120


class GcPolicy:
    """Counts the collections (per generation, and the longest, in ms) from
    :meth:`start` to :meth:`close`, and freezes the survivors once
    :meth:`frame_done` has seen ``warmup_frames`` frames (0 or None: never)."""

    def __init__(self, warmup_frames: int | None = WARMUP_FRAMES, clock=time.perf_counter):
        if warmup_frames is not None and (not isinstance(warmup_frames, int) or warmup_frames < 0):
            raise ValueError(f"warmup_frames must be a whole number >= 0 or None, "
                             f"got {warmup_frames!r}")
        self.warmup_frames = warmup_frames or 0
        self.clock = clock
        self.collections = [0, 0, 0]
        self.collected = 0             # unreachable objects the collections freed
        self.max_ms = 0.0
        self.frozen = 0                # objects frozen at the warm-up (0: not yet)
        self._t = None
        self._on = False

    def _callback(self, phase: str, info: dict) -> None:
        if phase == "start":
            self._t = self.clock()
            return
        g = int(info.get("generation", 2))
        self.collections[min(max(g, 0), 2)] += 1
        self.collected += int(info.get("collected", 0))
        if self._t is not None:
            ms = (self.clock() - self._t) * 1e3
            if ms > self.max_ms:
                self.max_ms = ms
            self._t = None

    def start(self) -> None:
        """Before the loop: one full collection (off the frames' clock), then count."""
        gc.collect()
        if not self._on:
            gc.callbacks.append(self._callback)
            self._on = True

    def frame_done(self, frames: int) -> None:
        """After frame number ``frames`` (1-based): at the warm-up's end, collect the
        young generations (the full collection ran at :meth:`start`; this walks only
        what the warm-up made) and freeze every survivor."""
        if self.frozen or not self.warmup_frames or frames < self.warmup_frames:
            return
        gc.collect(1)
        gc.freeze()
        self.frozen = max(gc.get_freeze_count(), 1)

    def close(self) -> None:
        """Unfreeze and stop counting (the collector as it was before the runtime)."""
        if self.frozen:
            gc.unfreeze()
        if self._on:
            try:
                gc.callbacks.remove(self._callback)
            except ValueError:
                pass
            self._on = False

    def status(self) -> dict:
        return {"frozen_objects": self.frozen, "warmup_frames": self.warmup_frames,
                "collections": {str(g): n for g, n in enumerate(self.collections)},
                "collected": self.collected, "max_ms": round(self.max_ms, 3)}
