"""Run code on real MicroPython (the WebAssembly port from npm, under Node) from a
test, and import the same MicroPython modules under CPython.

    from tests.mpyrun import run_mpy, requires_mpy, MPY_LIB
    res = run_mpy(script_path, libs=[MPY_LIB / "..."], args=["42"])
    assert res.returncode == 0, res.stderr

``make test`` installs the npm package (``npm ci``); without Node or the package the
MicroPython runs skip with the reason.
"""

from __future__ import annotations
from tests import REPO_ROOT

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = REPO_ROOT
RUNNER = ROOT / "tests" / "mpy" / "run.mjs"
#: the ``machine`` stand-in (tests/mpy/machine.py)
STANDIN = ROOT / "tests" / "mpy"
#: tacfoot's MicroPython sources
MPY_LIB = ROOT / "device" / "micropython"
PACKAGE = ROOT / "node_modules" / "@micropython" / "micropython-webassembly-pyscript"


def mpy_unavailable() -> str | None:
    """Why MicroPython cannot run here, or None."""
    if shutil.which("node") is None:
        return "node not found (install Node.js; make test then installs the MicroPython npm package)"
    if not (PACKAGE / "micropython.mjs").is_file():
        return ("@micropython/micropython-webassembly-pyscript not installed: run `npm ci` "
                "in the repository (make test does)")
    return None


requires_mpy = pytest.mark.skipif(mpy_unavailable() is not None, reason=mpy_unavailable() or "")


def run_mpy(script, libs=(), puts=(), args=(), timeout: float = 300, heap: int = 262144,
            check: bool = False) -> subprocess.CompletedProcess:
    """Run ``script`` (a path, or source text) on MicroPython. ``libs`` are folders
    copied onto sys.path (the machine stand-in always is); ``puts`` are (host path,
    MicroPython path) pairs; ``args`` reach the script as ``mpy_args.ARGV[1:]``."""
    why = mpy_unavailable()
    if why:
        pytest.skip(why)
    tmp = None
    p = Path(script) if not isinstance(script, str) or "\n" not in script else None
    if p is None:
        import tempfile
        tmp = tempfile.NamedTemporaryFile("w", suffix=".py", delete=False)
        tmp.write(script)
        tmp.close()
        p = Path(tmp.name)
    cmd = ["node", str(RUNNER), "--heap", str(heap), "--lib", str(STANDIN)]
    for d in libs:
        cmd += ["--lib", str(d)]
    for host, mp in puts:
        cmd += ["--put", f"{host}={mp}"]
    cmd += [str(p), *map(str, args)]
    try:
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=ROOT)
    finally:
        if tmp is not None:
            Path(tmp.name).unlink(missing_ok=True)
    if check and res.returncode != 0:
        raise AssertionError(f"MicroPython run failed ({res.returncode}):\n{res.stderr}\n{res.stdout}")
    return res


def cpython_path() -> None:
    """Put the machine stand-in and device/micropython on sys.path for CPython runs."""
    for d in (STANDIN, MPY_LIB):
        if str(d) not in sys.path:
            sys.path.insert(0, str(d))
