"""Hardware drivers of the data-collection rig (docs/rig.md): the z stepper with
acceleration ramps, the x DC motor with a run timeout, and the load cell (HX711 or
an ADC pin). Pins and ADCs come in through the constructors; time comes in through
``tick(dt_us)``, so the tests step them without real time.

Positions are integers: steps inside the stepper, micrometres for the DC axis;
loads are millinewtons.
"""


# -- z axis: stepper -------------------------------------------------------------------
class Stepper:
    """Step/dir stepper with a trapezoidal speed ramp (integer arithmetic).

    ``tick(dt_us)`` issues the steps due in the elapsed time. Position 0 is the
    home switch (top); positive is down, towards the base plate."""

    def __init__(self, step_pin, dir_pin, steps_per_mm=400, accel_mm_s2=200,
                 start_speed_mm_s=1):
        self.step_pin = step_pin
        self.dir_pin = dir_pin
        self.steps_per_mm = steps_per_mm
        self.accel = accel_mm_s2 * steps_per_mm           # steps/s^2
        self.v_start = max(1, start_speed_mm_s * steps_per_mm)
        self.pos = 0
        self.target = 0
        self.lo = None          # soft limits, steps (None: none, e.g. before homing)
        self.hi = None
        self.v = 0              # steps/s, >= 0
        self.dir = 1            # direction of the present motion
        self.v_max = self.v_start
        self.moving = False
        self._acc = 0           # step phase, step*us
        self._vacc = 0          # velocity phase, (steps/s)*us

    def move_to(self, target, speed_steps_s):
        self.target = target
        self.v_max = max(self.v_start, speed_steps_s)
        if target != self.pos or self.v:
            self.moving = True

    def halt(self):
        """Stop at once (an emergency stop: no ramp)."""
        self.target = self.pos
        self.v = 0
        self._acc = 0
        self.moving = False

    def tick(self, dt_us):
        if not self.moving:
            return 0
        rem = self.target - self.pos
        want = 1 if rem > 0 else (-1 if rem < 0 else self.dir)   # on target: keep braking
        dist = rem if rem > 0 else -rem
        if self.v == 0:
            self.dir = want
        # speed: brake if reversing or within the stopping distance, else ramp up
        self._vacc += self.accel * dt_us
        dv = self._vacc // 1000000
        self._vacc -= dv * 1000000
        if self.v and (want != self.dir or dist == 0 or self.v * self.v >= 2 * self.accel * dist):
            self.v -= dv
            if self.v < self.v_start:
                self.v = 0 if (want != self.dir or dist == 0) else self.v_start
        else:
            self.v += dv
            if self.v > self.v_max:
                self.v = self.v_max
            if self.v < self.v_start:
                self.v = self.v_start
        if self.v == 0:
            if dist == 0:
                self.moving = False
                return 0
            self.dir = want
            self.v = self.v_start
        if self.dir != want:      # still braking the other way
            n_ok = False
        else:
            n_ok = True
        self.dir_pin.value(1 if self.dir > 0 else 0)
        self._acc += self.v * dt_us
        n = self._acc // 1000000
        self._acc -= n * 1000000
        if n_ok and n > dist:
            n = dist
        stop = n_ok and n == dist
        # braking through a reversal may carry on past the old target, never past
        # the soft limits
        if self.hi is not None and self.dir > 0 and self.pos + n >= self.hi:
            n = self.hi - self.pos if self.hi > self.pos else 0
            stop = True
        if self.lo is not None and self.dir < 0 and self.pos - n <= self.lo:
            n = self.pos - self.lo if self.pos > self.lo else 0
            stop = True
        p = self.step_pin
        for _ in range(n):
            p.value(1)
            p.value(0)
        self.pos += n * self.dir
        if stop:                  # on target (or at a limit): the pulses stop, so does the motor
            self.v = 0
            self._acc = 0
            self.moving = self.pos != self.target
            if self.moving and ((self.hi is not None and self.pos >= self.hi and
                                 self.target >= self.pos) or
                                (self.lo is not None and self.pos <= self.lo and
                                 self.target <= self.pos)):
                self.target = self.pos
                self.moving = False
        return n


# -- x axis: DC motor through an H-bridge ----------------------------------------------
class DCMotor:
    """PWM on the bridge's enable, two direction inputs. Open loop: the speed
    follows the duty cycle (``max_speed_mm_s`` at full duty, calibrated), and the
    position is the integral of the commanded speed. Every run has a timeout."""

    def __init__(self, pwm, in1, in2, max_speed_mm_s=50, timeout_ms=10000):
        self.pwm = pwm
        self.in1 = in1
        self.in2 = in2
        self.max_speed_um_s = max_speed_mm_s * 1000
        self.timeout_us = timeout_ms * 1000
        self.x_um = 0
        self.speed_um_s = 0
        self.dir = 0
        self.left_us = 0        # run time left
        self.run_us = 0
        self._acc = 0
        self.timed_out = False
        self.stop()

    def run(self, distance_um, speed_um_s):
        duration_us = (abs(distance_um) * 1000000) // speed_um_s
        self.dir = 1 if distance_um > 0 else -1
        self.speed_um_s = speed_um_s
        self.left_us = duration_us
        self.run_us = 0
        self.timed_out = False
        self.in1.value(1 if self.dir > 0 else 0)
        self.in2.value(0 if self.dir > 0 else 1)
        self.pwm.duty_u16((speed_um_s * 65535) // self.max_speed_um_s)

    @property
    def running(self):
        return self.dir != 0

    def stop(self):
        self.pwm.duty_u16(0)
        self.in1.value(0)
        self.in2.value(0)
        self.dir = 0
        self.speed_um_s = 0

    def tick(self, dt_us):
        if not self.dir:
            return
        step = dt_us if dt_us < self.left_us else self.left_us
        self._acc += self.speed_um_s * step
        d = self._acc // 1000000
        self._acc -= d * 1000000
        self.x_um += d * self.dir
        self.left_us -= step
        self.run_us += dt_us
        if self.run_us > self.timeout_us:
            self.timed_out = True
            self.stop()
        elif self.left_us <= 0:
            self.stop()


# -- load cell ---------------------------------------------------------------------------
class HX711:
    """HX711 24-bit bridge ADC, bit-banged (channel A, gain 128). ``read_mn()``
    returns the last load in mN; it does not wait for a conversion."""

    def __init__(self, dout, sck, offset=0, counts_per_n=1000):
        self.dout = dout
        self.sck = sck
        self.offset = offset
        self.counts_per_n = counts_per_n
        self.last_mn = 0
        self.faults = 0
        sck.value(0)

    def read_mn(self):
        if self.dout.value():                 # conversion not ready: keep the last
            return self.last_mn
        v = 0
        s = self.sck
        d = self.dout
        for _ in range(24):
            s.value(1)
            s.value(0)
            v = (v << 1) | d.value()
        s.value(1)                             # 25th pulse: channel A, gain 128 next
        s.value(0)
        if v & 0x800000:
            v -= 0x1000000
        if v == 0x7FFFFF or v == -0x800000:    # saturated: bridge open or overloaded
            self.faults += 1
            return self.last_mn
        self.last_mn = ((v - self.offset) * 1000) // self.counts_per_n
        return self.last_mn


class AdcLoad:
    """A load cell behind an amplifier on an ADC pin: ``mn_per_count`` after
    subtracting ``offset`` (u16 counts)."""

    def __init__(self, adc, offset=0, mn_per_count=1):
        self.adc = adc
        self.offset = offset
        self.mn_per_count = mn_per_count
        self.faults = 0
        self.last_mn = 0

    def read_mn(self):
        v = self.adc.read_u16()
        if v >= 65535:                         # rail: amplifier saturated or open
            self.faults += 1
            return self.last_mn
        self.last_mn = (v - self.offset) * self.mn_per_count
        return self.last_mn

