"""What the leg runtime takes from the gait MCU's GAIT packets (issue 29, item 12): a
phase other than stance (0) or swing (1), or a packet flagged non-finite, is refused
and counted; a packet flagged clamped is used with its clamped values and counted."""
from __future__ import annotations

import struct

from device.pi import protocol as P
from tests.device.pi.runtime.standins import make_runtime, run_for

_GAIT = struct.Struct("<BHhhhB")


def raw_gait(phase, load_x10, vel, flags, seq):
    """A GAIT frame with any phase and flags byte (Gait.pack clamps the phase)."""
    return P.encode_frame(P.MSG_GAIT, _GAIT.pack(phase, load_x10, *vel, flags), seq, 0)


#: (frame it is sent at, wire bytes, taken?): a good swing, then a phase of 2 and of
#: 255, a stance flagged non-finite (its load was NaN, sent as 0), a stance flagged
#: clamped (its load beyond the field, sent as 6553.5 N), a plain stance
PLAN = [
    (4, raw_gait(P.PHASE_SWING, 30, (0, 0, 0), 0, 1), True),
    (8, raw_gait(2, 990, (5, 0, 0), 0, 2), False),
    (12, raw_gait(255, 990, (5, 0, 0), 0, 3), False),
    (16, raw_gait(P.PHASE_STANCE, 0, (5, 0, 0), P.GAIT_FLAG_NONFINITE, 4), False),
    (20, raw_gait(P.PHASE_STANCE, 0xFFFF, (0, 0, 0), P.GAIT_FLAG_CLAMPED, 5), True),
    (24, raw_gait(P.PHASE_STANCE, 50, (0, 0, 0), P.GAIT_FLAG_CLAMPED | P.GAIT_FLAG_NONFINITE,
                  6), False),
    (28, raw_gait(P.PHASE_STANCE, 70, (0, 0, 0), 0, 7), True),
]


def test_a_gait_phase_out_of_range_or_flagged_non_finite_is_refused_and_counted(tmp_path):
    """Before: phase 2..255 was taken as swing and both flags were ignored (24,259 such
    packets accepted in a probe)."""
    rt, _, port = make_runtime(tmp_path)
    seen = {}

    def hook(rt):
        for at, wire, _ in PLAN:
            if rt.frames == at and at not in seen:
                port.inbox += wire
                seen[at] = None
            if rt.frames == at + 2 and seen.get(at) is None and at in seen:
                g = rt.gait
                seen[at] = None if g is None else (g.stance, round(g.load_n, 1))
    run_for(rt, frames=34, hook=hook)
    assert [seen[at] for at, _, _ in PLAN] == [
        (False, 3.0), (False, 3.0), (False, 3.0), (False, 3.0),      # refused: swing stays
        (True, 6553.5), (True, 6553.5),                               # clamped: used
        (True, 7.0)]
    st = rt.status()
    assert st["gait_packets"] == len(PLAN)
    assert st["gait_refused"] == sum(not ok for _, _, ok in PLAN) == 4
    assert st["gait_clamped"] == 1
