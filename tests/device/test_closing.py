"""device/closing.py: with-blocks and garbage collection close the object."""
from __future__ import annotations

import gc

import pytest

from device.closing import Closing


class Thing(Closing):
    def __init__(self, log, fail=False):
        self.log, self.fail = log, fail

    def close(self):
        self.log.append("closed")
        if self.fail:
            raise OSError("already gone")


def test_a_with_block_closes_even_when_it_raises():
    log = []
    with pytest.raises(RuntimeError):
        with Thing(log) as t:
            assert isinstance(t, Thing)
            raise RuntimeError("inside")
    assert log[0] == "closed"


def test_garbage_collection_closes_and_swallows_a_failing_close():
    log = []
    Thing(log, fail=True)
    gc.collect()
    assert log == ["closed"]
