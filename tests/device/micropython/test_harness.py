"""The MicroPython harness itself: the code really runs on MicroPython, errors
surface, and the machine stand-in behaves the same on both interpreters."""

from tests.mpyrun import requires_mpy, run_mpy

SCRIPT = """
import sys, machine, mpy_args
u = machine.UART(0, 115200, rxbuf=4)
u.feed(b'abcdef')
b = bytearray(8)
n = u.readinto(b)
print(sys.implementation.name, n, bytes(b[:n]), u.overrun, mpy_args.ARGV[1:])
"""


@requires_mpy
def test_scripts_run_on_real_micropython_with_the_machine_standin():
    res = run_mpy(SCRIPT, args=["x", "7"], check=True)
    assert res.stdout.split() == ["micropython", "4", "b'abcd'", "2", "['x',", "'7']"]


@requires_mpy
def test_an_uncaught_exception_fails_the_run_with_its_traceback():
    res = run_mpy("import machine\nmachine.reset()\n")
    assert res.returncode == 1
    assert "MachineReset" in res.stderr
