"""The gait example (device/micropython/gait_example.py) on REAL MicroPython and on
CPython: it picks a preset per surface at step boundaries, falls back to safe when the
link goes stale or reports a fault, and sends the GAIT context the Pi decodes."""
from __future__ import annotations

import json

from device.pi import protocol as P
from tests import REPO_ROOT
from tests.mpyrun import cpython_path, requires_mpy, run_both

VECTORS = REPO_ROOT / "tests" / "device" / "pi" / "protocol_vectors.json"


GAIT = r"""
import json, mpy_args, machine
from binascii import hexlify, unhexlify
import surface_link as SL
import gait_example as G

now = [0]
u = machine.UART(0, 921600, rxbuf=512)
link = SL.SurfaceLink(u, stale_ms=150, clock=lambda: now[0])
loop = G.GaitLoop(link, context_ms=20, clock=lambda: now[0])
plan = json.loads(mpy_args.ARGV[1])     # [[until_ms, wire_hex or ""], ...]
presets = []
tx = []
k = 0
while now[0] < plan[-1][0]:
    while plan[k][0] <= now[0]:
        k += 1
    if plan[k][1] and now[0] % 20 == 0:
        u.feed(unhexlify(plan[k][1]))
    presets.append(loop.step())
    tx.append(hexlify(u.take()).decode())
    now[0] += 10
print(json.dumps({"presets": presets, "tx": "".join(tx), "switches": loop.switches}))
"""


def _gait_plan():
    vec = {v["name"]: v["wire_hex"] for v in json.loads(VECTORS.read_text())["messages"]}
    # the same SURFACE bytes repeated are fine for the consumer (age is local)
    return [[2000, vec["surface_hard"]], [4000, vec["surface_slippery_slip"]],
            [6000, vec["surface_soft"]], [7000, ""], [8000, vec["surface_hard"]]]


def _check_gait(out: dict):
    pre = out["presets"]
    at = lambda ms: pre[ms // 10]  # noqa: E731
    assert at(0) == "safe"                       # start safe; switch at the step's end
    assert at(G_PERIOD["safe"]) == "hard"
    assert at(1990) == "hard"
    # a change of surface is taken at the next step boundary (<= one period)
    assert at(2000 + G_PERIOD["hard"]) == "slippery"
    assert at(3990) == "slippery"
    assert at(4000 + G_PERIOD["slippery"]) == "soft"
    # the link goes quiet at 6000: safe within stale_ms (+ one tick)
    first_safe = next(i for i in range(600, len(pre)) if pre[i] == "safe") * 10
    assert 6000 + 150 - 20 < first_safe <= 6000 + 150 + 20
    assert at(6990) == "safe"
    assert at(7000 + G_PERIOD["safe"]) == "hard"
    # GAIT context went back every 20 ms, and decodes with the Pi's decoder
    msgs = [P.decode_message(f) for f in P.FrameDecoder().feed(bytes.fromhex(out["tx"]))]
    assert len(msgs) == len(pre) // 2 and all(isinstance(m, P.Gait) for m in msgs)
    stance = [m for m in msgs if m.phase == P.PHASE_STANCE]
    swing = [m for m in msgs if m.phase == P.PHASE_SWING]
    assert stance and swing
    assert all(m.load_n == 45.0 and m.vel_mm_s[0] < 0 for m in stance)
    assert all(m.load_n == 0.0 and m.vel_mm_s[0] > 0 for m in swing)
    assert all(m.flags == 0 for m in msgs)
    # slippery steps are shorter and slower: smaller stance speed than on hard ground
    hard_v = min(m.vel_mm_s[0] for m in msgs[:90] if m.phase == P.PHASE_STANCE)
    wet_v = min(m.vel_mm_s[0] for m in msgs[110:190] if m.phase == P.PHASE_STANCE)
    assert abs(wet_v) < abs(hard_v)


def _gait_periods():
    cpython_path()
    import gait_example
    return {k: v[1] for k, v in gait_example.PRESETS.items()}


G_PERIOD = {}


@requires_mpy
def test_gait_example_picks_presets_and_sends_gait_context():
    G_PERIOD.update(_gait_periods())
    mp, cp = run_both(GAIT, args=[json.dumps(_gait_plan())])
    assert json.loads(mp) == json.loads(cp)
    _check_gait(json.loads(mp))


def test_gait_example_presets_suit_each_surface_and_choose_safe_on_doubt():
    cpython_path()
    import gait_example as G
    hard, soft, wet, safe = (G.PRESETS[k] for k in ("hard", "soft", "slippery", "safe"))
    assert wet[0] < hard[0] and wet[1] > hard[1]        # wet: shorter, slower steps
    assert soft[2] > hard[2]                            # soft: higher clearance
    import surface_link as SL
    s = SL.SurfaceState()
    assert G.choose_preset(s, "hard") == "safe"         # never received -> safe
    s.valid, s.stale, s.class_id = True, False, SL.CLASS_SOFT
    s.probs_u8[SL.CLASS_SOFT] = 200
    assert G.choose_preset(s, "hard") == "soft"
    s.probs_u8[SL.CLASS_SOFT] = 100                     # not confident: keep
    assert G.choose_preset(s, "hard") == "hard"
    s.faults = SL.FAULT_CAMERA
    assert G.choose_preset(s, "hard") == "safe"

