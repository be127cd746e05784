"""A clip's still stretch, found by itself (``host calibrate``).

The frames stream in one at a time and are never all held. The first
``FIT_FRAMES`` fix where the pins are searched (the dome) and the threshold
(:func:`host.analysis.calibrate.fit_threshold`); every frame's blobs are then
found with that threshold and matched one to one (within half a pitch) to the
previous frame's and to the first frame of the current stretch. A frame
continues the stretch when its pins moved at most ``STILL_PX`` from the previous
frame and drifted at most ``DRIFT_PITCH`` pitch from the stretch's first frame
(medians over the pins matched; fewer than 3 matched is moving). A slow drag moves
little from one frame to the next but drifts, so both tests are needed.

:func:`calibrate_clip` calibrates from the earliest stretch of ``want`` still frames
(the scan stops there); when :func:`host.analysis.calibrate.calibrate` refuses it
(the pins wander, the layout is loose), it tries the next, up to ``MAX_TRIES``.
With ``least`` under ``want`` and no full stretch in the clip, the longest stretch
of at least ``least`` frames is used and :attr:`Found.note` says so in one line;
so is a whole clip shorter than ``least`` whose frames are all still (a single
image cannot be checked for motion). Otherwise it refuses with a :class:`NoStillStretch` naming the frames it looked
at and the longest stretch it saw. The scan stops after ``MAX_SCAN`` frames, and
only the current stretch, the longest short one and the fitting frames are held.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterable, Iterator

import numpy as np

from device.pi.vision.extract import PinDetector, to_gray
from device.pi.vision.matching import match_pins
from host.analysis.calibrate import (STILL_PX, NotAtRest, calibrate, find_region,
                                     fit_threshold, frames_text)

#: a still stretch drifts at most this many pitches from its first frame
DRIFT_PITCH = 0.035
#: still frames wanted by default ...
WANT_FRAMES = 16
#: ... and, with no stretch that long in the clip, the fewest accepted
LEAST_FRAMES = 6
#: the dome and the threshold are fitted on this many leading frames of the scan
FIT_FRAMES = 8
#: the scan stops after this many frames
MAX_SCAN = 1000
#: at most this many full stretches are tried when calibrate refuses one
MAX_TRIES = 3


class NoStillStretch(NotAtRest):
    """No usable still stretch in the frames looked at; the message names them."""


@dataclass
class Stretch:
    """Consecutive still frames: the first one's index in the clip and the gray
    frames."""
    start: int
    frames: list = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.frames)

    def text(self) -> str:
        return frames_text(self.start, len(self))


def _median_motion(a: np.ndarray, b: np.ndarray, gate_px: float) -> float:
    """Median distance (px) of the pins of ``a`` matched one to one within
    ``gate_px`` in ``b``; inf with fewer than 3 matched."""
    if len(a) < 3 or len(b) < 3:
        return float("inf")
    idx = match_pins(a, b, gate_px)
    ok = idx >= 0
    if ok.sum() < 3:
        return float("inf")
    return float(np.median(np.hypot(*(b[idx[ok]] - a[ok]).T)))


class StillScan:
    """The still stretches of a stream of frames (gray or BGR), in order; ``first``
    is the first frame's index in its clip. After (or during) :meth:`stretches`,
    ``looked`` is how many frames were read and ``longest`` the longest stretch
    seen (start, frames)."""

    def __init__(self, frames: Iterable[np.ndarray], first: int = 0):
        self._it = iter(frames)
        self.first = int(first)
        self.looked = 0
        self.ended = False
        self.longest = (self.first, 0)
        self.pitch_px = float("nan")

    def looked_text(self) -> str:
        return frames_text(self.first, max(1, self.looked))

    def _read(self) -> Iterator[np.ndarray]:
        while self.looked < MAX_SCAN:
            try:
                f = next(self._it)
            except StopIteration:
                self.ended = True
                return
            self.looked += 1
            g = to_gray(f)
            yield g.copy() if np.shares_memory(g, f) else g     # a source may reuse its buffer

    def stretches(self, want: int) -> Iterator[Stretch]:
        """Each stretch of still frames, cut at ``want`` frames (a stretch reaching
        ``want`` is yielded at once and the next starts after it), in clip order;
        a ValueError when the leading frames show no pins at all."""
        reader = self._read()
        head = [g for _, g in zip(range(FIT_FRAMES), reader)]
        if not head:
            return
        dome = find_region(head)
        params, info, _ = fit_threshold(head, dome)
        self.pitch_px = pitch = float(info["pitch_px"])
        det = PinDetector(params, head[0].shape, dome)
        gate, drift_max = 0.5 * pitch, DRIFT_PITCH * pitch
        run = Stretch(self.first)
        anchor = prev = None

        def frames():
            yield from head
            head.clear()
            yield from reader

        for k, g in enumerate(frames(), start=self.first):
            pins = det.detect(g)[0]
            still = (prev is not None and len(run)
                     and _median_motion(prev, pins, gate) <= STILL_PX
                     and _median_motion(anchor, pins, gate) <= drift_max)
            if not still:
                if len(run):
                    yield run
                run, anchor = Stretch(k), pins
            run.frames.append(g)
            prev = pins
            if len(run) > self.longest[1]:
                self.longest = (run.start, len(run))
            if len(run) >= want:
                yield run
                run, prev = Stretch(k + 1), None
        if len(run):
            yield run


@dataclass
class Found:
    """A calibration from a clip's still stretch: the result of
    :func:`host.analysis.calibrate.calibrate`, the stretch's first frame, and a
    one-line ``note`` when it is shorter than wanted."""
    result: dict
    frame: np.ndarray
    note: str = ""


def _refusal(scan: StillScan, want: int, least: int, tried: list[str]) -> NoStillStretch:
    """The one-line refusal: the first still stretch tried and why it was refused,
    or, with none tried, the frames looked at and the longest stretch seen."""
    if scan.looked == 0:
        return NoStillStretch("no frames to calibrate from")
    if tried:
        more = (f"; {len(tried) - 1} later still stretch(es) refused as well"
                if len(tried) > 1 else "")
        return NoStillStretch(f"{tried[0]}{more} (the still stretches of {scan.looked_text()})")
    s, n = scan.longest
    longest = f"the longest is {frames_text(s, n)} ({n} frames)" if n > 1 else "none is"
    need = f"{want}" if least >= want else f"{least} (of the {want} wanted)"
    return NoStillStretch(
        f"no still stretch of {need} frames in {scan.looked_text()} (pins moving at most "
        f"{STILL_PX} px from frame to frame and {DRIFT_PITCH} pitch from the stretch's first "
        f"frame); {longest}; film the skin with nothing touching it, or pick the frames "
        f"with --start and --frames")


def calibrate_clip(frames: Iterable[np.ndarray], want: int = WANT_FRAMES,
                   least: int | None = None, first: int = 0, name: str = "calibrated",
                   expect_pins: int | None = None) -> Found:
    """Calibrate from the earliest still stretch of ``want`` frames of ``frames``
    (an iterable, read lazily; ``first`` is its first frame's index in the clip),
    or, when there is none and ``least`` < ``want``, from the longest stretch of at
    least ``least`` frames, or a whole clip shorter than that but still (said in
    :attr:`Found.note`). A :class:`NoStillStretch`
    (or the last :class:`NotAtRest` of a stretch tried) naming the frames when
    nothing calibrates; a ValueError when the frames show no pins."""
    want = max(2, int(want))
    least = want if least is None else max(2, min(int(least), want))
    scan = StillScan(frames, first)
    short: Stretch | None = None
    tried: list[str] = []
    for run in scan.stretches(want):
        if len(run) < want:
            if (len(run) >= least or run.start == first) and (short is None
                                                              or len(run) > len(short)):
                short = run
            continue
        try:
            return Found(calibrate(run.frames, name=name, start=run.start,
                                   expect_pins=expect_pins), run.frames[0])
        except NotAtRest as exc:
            tried.append(str(exc))
            if len(tried) >= MAX_TRIES:
                break
    whole = (short is not None and scan.ended and len(short) == scan.looked
             and least < want)
    if short is not None and len(short) < least and not whole:
        short = None
    if short is not None:
        try:
            res = calibrate(short.frames, name=name, start=short.start, expect_pins=expect_pins)
        except NotAtRest as exc:
            tried.append(str(exc))
        else:
            note = (f"no still stretch of {want} frames in {scan.looked_text()}; calibrated "
                    f"from the longest, {short.text()} ({len(short)} frames)")
            if len(short) < least:
                note = (f"the clip has only {len(short)} frame(s), all still, under the "
                        f"{least} wanted at least; calibrated from all of them")
            return Found(res, short.frames[0], note)
    raise _refusal(scan, want, least, tried)
