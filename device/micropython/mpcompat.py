"""What MicroPython has built in and CPython lacks, in one place: ``const`` and the
wrapping ``ticks`` clock. On MicroPython these are the real ones; under CPython (the
tests, the sim rig) stand-ins with the same arithmetic (30-bit wrap, signed
difference) so the same modules run on both. Copy this file to the board with the
others."""

try:
    from micropython import const
except ImportError:             # CPython
    def const(x):
        return x

try:
    from time import ticks_add, ticks_diff, ticks_ms, ticks_us
except ImportError:             # CPython
    import time as _time

    _MASK = 0x3FFFFFFF          # MicroPython's ticks period is 2**30
    _HALF = 0x20000000

    def ticks_ms():
        return int(_time.monotonic() * 1000) & _MASK

    def ticks_us():
        return int(_time.monotonic() * 1000000) & _MASK

    def ticks_add(a, b):
        return (a + b) & _MASK

    def ticks_diff(a, b):
        """a - b as a signed number in [-2**29, 2**29), as MicroPython's."""
        return ((a - b + _HALF) & _MASK) - _HALF
