"""Run a script on real MicroPython (the WebAssembly port from npm, under Node), and
put the same MicroPython modules on CPython's path.

    from device.sim.mpy.runner import run_mpy, MPY_LIB
    res = run_mpy(script_path, libs=[MPY_LIB], args=["42"])
    assert res.returncode == 0, res.stderr

``run.mjs`` (beside this module) loads ``@micropython/micropython-webassembly-pyscript``
from the ``node_modules`` folder of the repository (``npm ci``). The ``machine``
stand-in (``lib/machine.py``, :data:`STANDIN`) is always on MicroPython's path.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from device.errors import TacfootError

__all__ = ["MpyUnavailable", "RUNNER", "STANDIN", "MPY_LIB", "PACKAGE", "mpy_unavailable",
           "run_mpy", "cpython_path"]

HERE = Path(__file__).resolve().parent
#: the Node script that runs one MicroPython script
RUNNER = HERE / "run.mjs"
#: the folder holding the ``machine`` stand-in
STANDIN = HERE / "lib"
#: tacfoot's MicroPython sources
MPY_LIB = HERE.parents[1] / "micropython"
#: the repository root, whose node_modules holds the MicroPython npm package
ROOT = HERE.parents[2]
PACKAGE = ROOT / "node_modules" / "@micropython" / "micropython-webassembly-pyscript"


class MpyUnavailable(TacfootError, RuntimeError):
    """Node or the MicroPython npm package is missing; the message says which."""


def mpy_unavailable() -> str | None:
    """Why MicroPython cannot run here, or None."""
    if shutil.which("node") is None:
        return "node not found (install Node.js; make test then installs the MicroPython npm package)"
    if not (PACKAGE / "micropython.mjs").is_file():
        return ("@micropython/micropython-webassembly-pyscript not installed: run `npm ci` "
                "in the repository (make test does)")
    return None


def run_mpy(script, libs=(), puts=(), args=(), timeout: float = 300, heap: int = 262144,
            check: bool = False) -> subprocess.CompletedProcess:
    """Run ``script`` (a path, or source text with a newline) on MicroPython.

    ``libs`` are folders copied onto sys.path (the machine stand-in always is);
    ``puts`` are (host path, MicroPython path) pairs; ``args`` reach the script as
    ``mpy_args.ARGV[1:]``. Raises :class:`MpyUnavailable` when MicroPython cannot
    run here; with ``check`` an exit status other than 0 raises ``RuntimeError``
    with the script's stderr and stdout.
    """
    why = mpy_unavailable()
    if why:
        raise MpyUnavailable(why)
    tmp = None
    p = Path(script) if not isinstance(script, str) or "\n" not in script else None
    if p is None:
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
        raise RuntimeError(f"MicroPython run failed ({res.returncode}):\n{res.stderr}\n{res.stdout}")
    return res


def cpython_path() -> None:
    """Put the machine stand-in and device/micropython on sys.path for CPython runs."""
    for d in (STANDIN, MPY_LIB):
        if str(d) not in sys.path:
            sys.path.insert(0, str(d))
