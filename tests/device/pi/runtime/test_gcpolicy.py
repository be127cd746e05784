"""The runtime's garbage-collector policy (device/pi/runtime/gcpolicy.py): after the
warm-up the long-lived objects are frozen, so a collection in the steady state walks
only what the run made since; the status counts the collections; closing the runtime
gives the process its collector back. Asserted on the collector's own counts
(gc.get_objects, gc.get_freeze_count, gc.callbacks), never on time."""
from __future__ import annotations

import gc

import pytest

from device.pi.runtime.gcpolicy import GcPolicy
from tests.device.pi.runtime.standins import SimCamera, make_runtime

WARMUP = 30


def test_the_steady_state_collections_walk_only_what_the_run_made(tmp_path):
    """Before the change every tracked object of the process (the models, ONNX
    Runtime, OpenCV, pytest: tens of thousands) stayed in gen 2, and the steady
    state's first full collection walked them all."""
    rt, _, _ = make_runtime(tmp_path, cam=SimCamera(), gc_warmup_frames=WARMUP)
    full = []
    rt.start()
    try:
        while rt.frames < WARMUP:
            rt.step()
        assert gc.get_freeze_count() > 10_000          # the runtime's and the process's
        # as frozen (frozen objects that die leave the count)
        assert rt.status()["gc"]["frozen_objects"] >= gc.get_freeze_count()
        n0 = rt.frames
        while rt.frames < n0 + 150:
            rt.step()
        # what a full collection of the steady state would walk, and one, counted
        full.append(len(gc.get_objects()))
        gc.collect(2)
        st = rt.status()["gc"]
    finally:
        rt.close()
    assert full[0] < 3_000, f"tracked objects outside the frozen set: {full[0]}"
    assert st["collections"]["2"] >= 1 and st["max_ms"] > 0
    assert gc.get_freeze_count() == 0                  # closed: the collector as before
    assert not any(getattr(cb, "__self__", None) is rt.gc for cb in gc.callbacks)


def test_no_warm_up_no_freeze_and_a_bad_warm_up_is_refused(tmp_path):
    rt, _, _ = make_runtime(tmp_path, cam=SimCamera(), gc_warmup_frames=None)
    rt.start()
    try:
        while rt.frames < 5:
            rt.step()
        assert gc.get_freeze_count() == 0 and rt.status()["gc"]["frozen_objects"] == 0
    finally:
        rt.close()
    with pytest.raises(ValueError, match="warmup_frames must be .* got -1"):
        GcPolicy(-1)
