"""The small programs :mod:`host.bench.counts` runs under callgrind, one per thing
counted: ``python -m host.bench.count_drivers KIND FRAMES_DIR N [--timings FILE]``.

Every driver reads every frame of the folder of gray PGM files into memory first
(the same work whatever ``N``), then runs its loop over the first ``N``, and nothing
else: the process is counted whole, and the difference between two lengths removes
the start-up, the imports and the frame loading (:mod:`host.bench.counts`).

KIND is one of

* ``pipeline``: ``MarkerStream(PROFILE).process`` on each gray frame (what ``host
  analyse`` runs). With ``--timings FILE`` the sums of its stage timers
  (``FrameFeatures.timings_ms``) are written there as JSON, for the timer split;
* ``detect``, ``track``, ``grid``, ``features``: the pipeline's stages, cumulative
  (``track`` is detection then tracking, and so on), run by the stream's own stage
  objects (``detector``, ``tracker``, ``grid``) once a warm-up pass over the first
  frames has chosen the reference: the difference of consecutive variants is one
  stage's count;
* ``peer``: OpenCV's SimpleBlobDetector and a nearest-neighbour match to the first
  frame's blobs (:class:`host.bench.sim.BaselineBlobTracker`).
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

PROFILE = "roboskin"
KINDS = ("pipeline", "detect", "track", "grid", "features", "peer")
#: the cumulative stage variants, in order
STAGE_VARIANTS = ("detect", "track", "grid", "features")


def load_gray(folder, n: int) -> list:
    """The first ``n`` images of ``folder`` (sorted by name), gray uint8."""
    import cv2
    files = sorted(p for p in Path(folder).iterdir() if p.suffix.lower() == ".pgm")[:n]
    if len(files) < n:
        raise SystemExit(f"{folder}: {len(files)} PGM frames, {n} wanted")
    frames = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in files]
    if any(f is None for f in frames):
        raise SystemExit(f"{folder}: a PGM frame could not be read")
    return frames


def run_pipeline(frames, timings_file=None) -> None:
    from device.pi.vision.pipeline import MarkerStream
    stream = MarkerStream(PROFILE)
    sums: dict = {}
    for g in frames:
        out = stream.process(g)
        for k, v in out.timings_ms.items():
            sums[k] = sums.get(k, 0.0) + v
    if timings_file:
        Path(timings_file).write_text(json.dumps({"frames": len(frames), "timings_ms": sums}))


def run_stages(frames, upto: str) -> None:
    """Detection, then tracking, the contact grid and the features (up to and with
    ``upto``) on each frame, with the stage objects of a stream whose reference was
    chosen on the first frames."""
    from device.pi.vision.features import shear_and_sum
    from device.pi.vision.pipeline import MarkerStream
    stream = MarkerStream(PROFILE)
    for g in frames:                        # warm-up: the dome, exposure, reference
        stream.process(g)
        if stream.reference is not None:
            break
    if stream.reference is None:
        raise SystemExit("no reference chosen on these frames")
    det, tracker, grid = stream.detector, stream.tracker, stream.grid
    level = STAGE_VARIANTS.index(upto)
    for g in frames:
        pins, _ = det.detect_gray(det.gray_crop(g))
        if level >= 1:
            vectors, lost = tracker.update(pins, 1)
            if level >= 2:
                grid.update(det.binary)
                if level >= 3:
                    shear_and_sum(vectors, ~lost)


def run_peer(frames) -> None:
    from host.bench.sim import BaselineBlobTracker, single_thread
    single_thread()
    peer = BaselineBlobTracker()
    for g in frames:
        peer.process(g)


def main(argv=None) -> int:
    import argparse
    ap = argparse.ArgumentParser(prog="python -m host.bench.count_drivers")
    ap.add_argument("kind", choices=KINDS)
    ap.add_argument("frames_dir")
    ap.add_argument("n", type=int)
    ap.add_argument("--timings", help="pipeline: write the stage timers' sums here")
    a = ap.parse_args(argv)
    import cv2
    cv2.setNumThreads(1)                    # as the runtime and the other benchmarks
    # every frame is read in both runs of a pair, so the loading cancels in the
    # difference; only the first n are processed
    everything = sorted(p for p in Path(a.frames_dir).iterdir() if p.suffix.lower() == ".pgm")
    frames = load_gray(a.frames_dir, max(a.n, len(everything)))[:a.n]
    if a.kind == "pipeline":
        run_pipeline(frames, a.timings)
    elif a.kind == "peer":
        run_peer(frames)
    else:
        run_stages(frames, a.kind)
    return 0


if __name__ == "__main__":
    sys.exit(main())
