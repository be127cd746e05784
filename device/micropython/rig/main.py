"""Entry point on the Raspberry Pi Pico: wire the real ``machine`` objects to
``rig.firmware.Rig`` and run the main loop over USB serial. Copy to the board as
``main.py`` (with ``rig/``, ``tflink.py`` and ``mpu6050.py``). Pins: docs/rig.md, "Wiring"."""

import sys
import time

import machine
import micropython

from rig.drivers import AdcLoad, DCMotor, HX711, Stepper
from rig.firmware import Rig

# -- configuration (edit for your frame) ----------------------------------------------
STEPS_PER_MM = 400          # 200 steps/rev, 1/16 microstepping, 8 mm lead screw
TRAVEL_MM = 40
LOAD_CELL = "hx711"         # or "adc"
HX711_OFFSET = 0            # raw counts with nothing on the load cell
HX711_COUNTS_PER_N = 10000
LINK_TIMEOUT_MS = 1000
WDT_TIMEOUT_MS = 2000


class UsbStream:
    """sys.stdin/stdout.buffer without blocking: read only what select says is
    there, one byte at a time into a preallocated buffer (no allocation)."""

    def __init__(self):
        import select
        self._poll = select.poll()
        self._poll.register(sys.stdin, select.POLLIN)
        self._one = bytearray(1)
        self._in = sys.stdin.buffer
        self._out = sys.stdout.buffer

    def readinto(self, buf):
        n = 0
        while n < len(buf) and self._poll.poll(0):
            if not self._in.readinto(self._one):
                break
            buf[n] = self._one[0]
            n += 1
        return n

    def write(self, buf):
        return self._out.write(buf)


class NoImu:
    """Stands in for a missing or wrong MPU6050: zeros, with the fault flag set."""
    faults = 1
    values = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)

    def read(self):
        return self.values


def build():
    P = machine.Pin
    stepper = Stepper(P(2, P.OUT), P(3, P.OUT), steps_per_mm=STEPS_PER_MM)
    P(4, P.OUT, value=0)                                    # stepper driver EN (active low)
    motor = DCMotor(machine.PWM(P(6), freq=20000), P(7, P.OUT), P(8, P.OUT))
    if LOAD_CELL == "hx711":
        load = HX711(P(10, P.IN), P(11, P.OUT), HX711_OFFSET, HX711_COUNTS_PER_N)
    else:
        load = AdcLoad(machine.ADC(P(26)))
    try:
        from mpu6050 import MPU6050
        imu = MPU6050(machine.I2C(0, scl=P(1), sda=P(0), freq=400000))
    except (ImportError, OSError, ValueError):
        imu = NoImu()           # never print: stdout is the host link
    home = P(14, P.IN, P.PULL_UP)
    estop = P(15, P.IN, P.PULL_UP)

    class ActiveLow:                                         # switches close to ground
        def __init__(self, pin):
            self.pin = pin

        def value(self):
            return 0 if self.pin.value() else 1

    return Rig(UsbStream(), stepper, motor, load, imu, ActiveLow(home), ActiveLow(estop),
               wdt_factory=lambda: machine.WDT(timeout=WDT_TIMEOUT_MS), travel_mm=TRAVEL_MM,
               link_timeout_ms=LINK_TIMEOUT_MS)


def main():
    micropython.kbd_intr(-1)            # binary frames on stdin: 0x03 is not Ctrl-C
    rig = build()
    while True:
        rig.poll(time.ticks_us())


if __name__ == "__main__":
    main()
