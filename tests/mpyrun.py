"""The MicroPython runner (:mod:`device.sim.mpy.runner`) for tests: a run skips,
with the reason, where Node or the npm package is missing, and the test-only
stand-ins in ``tests/mpy`` (``fake_mpu_regs``) are on the path beside ``machine``.

    from tests.mpyrun import run_mpy, requires_mpy, MPY_LIB
    res = run_mpy(script_path, libs=[MPY_LIB / "..."], args=["42"])
    assert res.returncode == 0, res.stderr

``make test`` installs the npm package (``npm ci``).
"""

from __future__ import annotations

import contextlib
import importlib
import io
import os
import subprocess
import sys
import types

import pytest

from device.sim.mpy import runner
from device.sim.mpy.runner import MPY_LIB, PACKAGE, ROOT, RUNNER, STANDIN, mpy_unavailable
from tests import REPO_ROOT

__all__ = ["run_mpy", "run_cpython", "run_both", "requires_mpy", "mpy_unavailable",
           "cpython_path", "MPY_LIB", "STANDIN", "TEST_LIB", "RUNNER", "PACKAGE", "ROOT"]

#: test-only MicroPython stand-ins (``fake_mpu_regs``)
TEST_LIB = REPO_ROOT / "tests" / "mpy"

#: set while mutmut runs (``make mutate``): its mutated modules import mutmut, so only
#: CPython runs them, and ``surface_link`` is imported under its package name, the
#: name mutmut switches its mutants by
MUTATING = "MUTANT_UNDER_TEST" in os.environ

requires_mpy = pytest.mark.skipif(mpy_unavailable() is not None, reason=mpy_unavailable() or "")


def run_mpy(script, libs=(), puts=(), args=(), timeout: float = 300, heap: int = 262144,
            check: bool = False) -> subprocess.CompletedProcess:
    """:func:`device.sim.mpy.runner.run_mpy`, skipping the test where MicroPython
    cannot run; with ``check`` a failed run fails the test with its output."""
    why = "mutation testing runs CPython only" if MUTATING else mpy_unavailable()
    if why:
        pytest.skip(why)
    res = runner.run_mpy(script, libs=[TEST_LIB, *libs], puts=puts, args=args, timeout=timeout, heap=heap)
    if check and res.returncode != 0:
        raise AssertionError(f"MicroPython run failed ({res.returncode}):\n{res.stderr}\n{res.stdout}")
    return res


def cpython_path() -> None:
    """Put the machine stand-in, ``tests/mpy`` and device/micropython on sys.path."""
    runner.cpython_path()
    if str(TEST_LIB) not in sys.path:
        sys.path.insert(0, str(TEST_LIB))
    if MUTATING and "surface_link" not in sys.modules:
        sys.modules["surface_link"] = importlib.import_module("device.micropython.surface_link")


def run_cpython(src: str, args=()) -> str:
    """stdout of the MicroPython script ``src`` run under CPython, in this process,
    the way run.mjs runs it (its arguments in ``mpy_args.ARGV``)."""
    cpython_path()
    sys.modules["mpy_args"] = types.SimpleNamespace(ARGV=["script", *map(str, args)])
    out = io.StringIO()
    try:
        with contextlib.redirect_stdout(out):
            exec(compile(src, "<mpy-script>", "exec"), {"__name__": "__main__"})
    finally:
        del sys.modules["mpy_args"]
    return out.getvalue()


def run_both(src: str, args=(), puts=(), timeout=120) -> tuple[str, str]:
    """(MicroPython stdout, CPython stdout) of ``src`` with ``MPY_LIB`` on the path
    (paths in ``args`` are the MicroPython paths of ``puts``; CPython gets the host
    paths)."""
    host_args = [dict((m, h) for h, m in puts).get(a, a) for a in map(str, args)]
    cp = run_cpython(src, host_args)
    if MUTATING:
        return cp, cp
    res = run_mpy(src, libs=[MPY_LIB], puts=puts, args=args, timeout=timeout)
    assert res.returncode == 0, res.stderr[-3000:]
    return res.stdout, cp
