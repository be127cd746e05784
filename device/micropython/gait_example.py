# Example gait loop for the locomotion MCU: surfaces -> gait presets, GAIT context back.
#
# Runs on MicroPython (and CPython, for tests). On the robot:
#
#   import machine, gait_example
#   gait_example.main(machine.UART(0, 921600, tx=machine.Pin(0), rx=machine.Pin(1),
#                                  timeout=0, rxbuf=1024))
#
# Presets (one foot's view of a trot; the numbers are starting points to tune):
#   hard       normal steps
#   soft       higher clearance (the foot sinks in), a little slower
#   slippery   wet or slipping: shorter, slower steps
#   safe       the link is stale or the sensor reports a camera/model fault:
#              short, slow, high steps that work on any surface
# "no-touch" and low-confidence classes keep the current preset (a foot in swing
# sees no touch by design).
from surface_link import (CLASS_HARD, CLASS_SLIPPERY, CLASS_SOFT, FAULT_CAMERA, FAULT_MODEL,
                          PHASE_STANCE, PHASE_SWING, SurfaceLink, ticks_diff, ticks_ms)

# name: (step_length_mm, step_period_ms, clearance_mm)
PRESETS = {
    "hard": (120, 500, 30),
    "soft": (110, 560, 60),
    "slippery": (60, 750, 30),
    "safe": (50, 800, 60),
}
CLASS_PRESET = {CLASS_HARD: "hard", CLASS_SOFT: "soft", CLASS_SLIPPERY: "slippery"}
MIN_PROB_U8 = 128          # a class needs p >= 0.5 to switch presets
STANCE_FRACTION_PCT = 60   # duty factor
BODY_LOAD_N = 45.0         # expected load on this foot in stance (robot weight / feet in stance)


def choose_preset(state, current="safe"):
    """The preset name for a SurfaceState (see the table above)."""
    if state.stale or not state.valid:
        return "safe"
    if state.faults & (FAULT_CAMERA | FAULT_MODEL):
        return "safe"
    if state.slip:
        return "slippery"
    name = CLASS_PRESET.get(state.class_id)
    if name is None or state.probs_u8[state.class_id] < MIN_PROB_U8:
        return current
    return name


def gait_context(preset, t_in_cycle_ms):
    """(phase, expected load N, expected foot velocity (x, y, z) mm/s) for a time
    in the step cycle, for a foot moving along x under a body moving forward."""
    length_mm, period_ms, clearance_mm = PRESETS[preset]
    stance_ms = period_ms * STANCE_FRACTION_PCT // 100
    swing_ms = period_ms - stance_ms
    if t_in_cycle_ms < stance_ms:
        return PHASE_STANCE, BODY_LOAD_N, (-length_mm * 1000 // stance_ms, 0, 0)
    half = swing_ms // 2
    up = 1 if (t_in_cycle_ms - stance_ms) < half else -1
    return (PHASE_SWING, 0.0, (length_mm * 1000 // swing_ms, 0,
                               up * clearance_mm * 1000 // max(half, 1)))


class GaitLoop:
    """Polls the link, picks a preset at each step boundary, sends GAIT context
    every ``context_ms``."""

    def __init__(self, link, context_ms=20, clock=None):
        self.link = link
        self.clock = clock if clock is not None else ticks_ms
        self.context_ms = context_ms
        self.preset = "safe"
        self.cycle_start = self.clock()
        self.last_sent = self.cycle_start - context_ms
        self.switches = 0

    def step(self):
        """One pass of the control loop; returns the preset in use."""
        self.link.poll()
        now = self.clock()
        s = self.link.state(now)
        t = ticks_diff(now, self.cycle_start)
        period = PRESETS[self.preset][1]
        want = choose_preset(s, self.preset)
        if want == "safe" and self.preset != "safe":
            self._switch(want, now)              # fall back at once, not at the step end
        elif t >= period:
            if want != self.preset:
                self._switch(want, now)
            else:
                self.cycle_start = now
        if ticks_diff(now, self.last_sent) >= self.context_ms:
            phase, load_n, vel = gait_context(self.preset, ticks_diff(now, self.cycle_start))
            self.link.send_gait(phase, load_n, vel)
            self.last_sent = now
        return self.preset

    def _switch(self, name, now):
        self.preset = name
        self.cycle_start = now
        self.switches += 1


def main(uart, stale_ms=150, steps=-1):
    """Run the loop on ``uart`` (forever when steps < 0)."""
    loop = GaitLoop(SurfaceLink(uart, stale_ms=stale_ms))
    while steps != 0:
        loop.step()
        steps -= 1
    return loop
