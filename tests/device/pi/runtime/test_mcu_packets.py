"""Packets between the leg runtime and the gait MCU (issue 29).

Item 12: what the runtime takes from GAIT packets: a phase other than stance (0) or
swing (1), or a packet flagged non-finite, is refused and counted; a packet flagged
clamped is used with its clamped values and counted.

Item 13: the SURFACE `clamped` bit means a value beyond its field, not the pressure
model's error around no load."""
from __future__ import annotations

import struct

from device.pi import protocol as P
from device.pi.runtime.config import LegConfig
from device.pi.runtime.load import load_models
from device.pi.runtime.loop import LegRuntime
from tests.device.pi.runtime.standins import (FPS, NullImu, RecordingPort, SimCamera,
                                              make_runtime, run_for)

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


def test_surface_from_the_real_models_in_a_walk_never_says_clamped():
    """The leg's own models on sim://walk: the pressure regressor's estimate in the air
    is a few hundredths of a newton below 0 (its error is 0.024 N), which the SURFACE
    field (0..655.35 N) clamped and flagged on 138 of the walk's 720 frames, from
    frame 7 on. A normal load cannot pull: below 0 it is no load, sent as 0 with no
    fault."""
    cfg = LegConfig()
    models = load_models(None, "int8", None, cfg)
    assert models.pressure is not None
    port = RecordingPort()
    cam = SimCamera("walk")
    rt = LegRuntime(cfg, cam.factory, NullImu(), port, models, lossless=True, fps=FPS,
                    notify=lambda s: None)
    run_for(rt, frames=100)
    surf = [m for _, m in port.frames() if isinstance(m, P.Surface)]
    assert len(surf) >= 99
    assert [i for i, m in enumerate(surf) if m.faults & P.FAULT_CLAMPED] == []
    assert sum(m.load_n == 0.0 for m in surf[10:]) > 5       # the swing frames: no load
