"""The rig's drivers (device/micropython/rig/drivers.py) on CPython: the stepper's
ramp, for any moves. The drivers also run on real MicroPython inside the firmware
scenarios (test_firmware.py)."""
from __future__ import annotations

import importlib

from hypothesis import given, settings
from hypothesis import strategies as st

from tests.mpyrun import cpython_path


class _CountPin:
    def __init__(self):
        self.level = 0
        self.rising = 0

    def value(self, v=None):
        if v is None:
            return self.level
        if v and not self.level:
            self.rising += 1
        self.level = 1 if v else 0


@settings(max_examples=30, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 1500), st.integers(100, 4000), st.integers(1, 300)),
                min_size=1, max_size=4),
       st.integers(500, 3000))
def test_stepper_reaches_every_target_within_its_speed_limit(moves, dt_us):
    """Retargeting mid-move (as a press does at contact) included: the pulses add up
    to the position, the speed never passes the highest cap given, and the last move
    ends exactly on its target; braking through a reversal never passes a soft limit."""
    cpython_path()
    drv = importlib.import_module("rig.drivers")
    step, d = _CountPin(), _CountPin()
    s = drv.Stepper(step, d, steps_per_mm=100, accel_mm_s2=200)
    s.lo, s.hi = 0, 1500                                  # soft limits, as after homing
    net = pulses = cap = 0
    for i, (target, speed, ticks_before_next) in enumerate(moves):
        s.move_to(target, speed)
        cap = max(cap, speed, s.v_start)
        last = i == len(moves) - 1
        for _ in range(100000 if last else ticks_before_next):
            before = s.pos
            n = s.tick(dt_us)
            pulses += n
            net += n if d.level else -n
            assert s.pos - before == (n if d.level else -n)
            assert 0 <= s.v <= cap
            assert 0 <= s.pos <= 1500                          # never past a soft limit
            if not s.moving:
                break
    assert step.rising == pulses
    assert not s.moving and s.pos == moves[-1][0] and net == s.pos
