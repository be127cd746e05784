"""device/sim/mpy/runner.py: the code really runs on MicroPython, errors surface,
and the machine stand-in behaves the same on both interpreters."""

import subprocess
import sys

import pytest

from device.sim.mpy import runner
from device.sim.mpy.runner import MpyUnavailable, cpython_path, run_mpy
from tests.mpyrun import requires_mpy

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
    with pytest.raises(RuntimeError, match="MachineReset"):
        run_mpy("import machine\nmachine.reset()\n", check=True)


@requires_mpy
def test_libs_and_puts_reach_the_script(tmp_path):
    lib = tmp_path / "lib"
    lib.mkdir()
    (lib / "helper.py").write_text("VALUE = 41\n")
    data = tmp_path / "data.bin"
    data.write_bytes(b"\x01\x02\x03")
    script = "import helper\nf = open('/data/in.bin', 'rb')\nprint(helper.VALUE + 1, len(f.read()))\n"
    res = run_mpy(script, libs=[lib], puts=[(data, "/data/in.bin")], check=True)
    assert res.stdout.split() == ["42", "3"]


def test_without_node_the_run_says_why(monkeypatch):
    monkeypatch.setattr(runner.shutil, "which", lambda name: None)
    assert "node not found" in runner.mpy_unavailable()
    with pytest.raises(MpyUnavailable, match="node not found"):
        run_mpy("print(1)\n")


def test_cpython_path_imports_the_standin_and_the_micropython_sources():
    code = ("from device.sim.mpy.runner import cpython_path; cpython_path(); "
            "import machine, surface_link; u = machine.UART(0); u.feed(b'ab'); "
            "b = bytearray(4); print(u.readinto(b), surface_link.__name__)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=runner.ROOT, env={"PYTHONPATH": str(runner.ROOT)}, check=True)
    assert out.stdout.split() == ["2", "surface_link"]
    cpython_path()
    assert str(runner.STANDIN) in sys.path and str(runner.MPY_LIB) in sys.path
