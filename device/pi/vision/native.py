"""The tracker's compiled kernels (``match.c``), built on the machine that runs it.

Two kernels, each the C twin of numpy code that remains the specification and the
fallback:

- ``tf_match``: :func:`device.pi.vision.matching._match_finite`, one-to-one matching
  within a gate. The same candidate pairs (squared distances to the bit, because
  the C file is compiled with ``-ffp-contract=off``), taken shortest first. Only
  pairs at exactly the same distance may be taken in another order, which the
  matching's contract leaves open.
- ``tf_grow``: :func:`device.pi.vision.neighbours.match_and_grow`, the tracker's
  per-frame matching and growth into lost pins, step for step (the same
  neighbour medians, predictions and matches, the same doubles).

A wheel built on the host cannot carry a library for the Pi, so the library is
compiled where it runs:

    python -m device.pi.vision.native build     # cc, about a second
    python -m device.pi.vision.native status    # which matcher the tracker uses

``make install`` builds it on a development machine, and ``host deploy`` on each
leg, after the release is installed. Without a C compiler, or with
``TACFOOT_NATIVE=0`` in the environment, the tracker uses numpy: the same
numbers, slower. The library's file name carries a hash of ``match.c`` and the
machine, so a library from an older source or another machine is never loaded.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

__all__ = ["SOURCE", "NativeBuildError", "library_path", "build", "kernel", "load", "match_into",
           "grow_into", "active", "status"]

SOURCE = Path(__file__).with_name("match.c")
#: the kernel's ABI; tf_abi_version() must return it
ABI_VERSION = 2
#: the compiler's flags: no fused multiply-add, so distances are numpy's to the bit
CFLAGS = ("-O2", "-ffp-contract=off", "-fPIC", "-shared", "-std=c99")


class NativeBuildError(RuntimeError):
    """The kernel could not be compiled (no compiler, or it failed)."""


def _tag() -> str:
    h = hashlib.sha256(SOURCE.read_bytes())
    h.update(platform.machine().encode())
    return h.hexdigest()[:12]


def library_path(folder: Path | None = None) -> Path:
    """Where the library for this source and machine lives (next to ``match.c``
    unless ``TACFOOT_NATIVE_DIR`` or ``folder`` names another folder)."""
    base = folder or os.environ.get("TACFOOT_NATIVE_DIR") or SOURCE.parent
    return Path(base) / f"_match-{_tag()}.so"


def build(folder: Path | None = None, cc: str | None = None, force: bool = False) -> Path:
    """Compile ``match.c`` into :func:`library_path` (unless it is there already and
    loads, or ``force``); returns the path. The file appears whole or not at all
    (compiled to a temporary name, checked, then renamed)."""
    out = library_path(folder)
    if out.exists() and not force:
        try:
            kernel(out)
            return out
        except (OSError, AttributeError, NativeBuildError):
            pass                                # rebuild a broken file
    compiler = cc or os.environ.get("CC") or "cc"
    exe = shutil.which(compiler)
    if exe is None:
        raise NativeBuildError(f"no C compiler {compiler!r} on PATH (install gcc, or set CC); "
                               "the tracker runs on numpy meanwhile")
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".match-", suffix=".so", dir=out.parent)
    os.close(fd)
    try:
        run = subprocess.run([exe, *CFLAGS, "-o", tmp, str(SOURCE), "-lm"],
                             capture_output=True, text=True, timeout=120)
        if run.returncode != 0:
            raise NativeBuildError(f"{compiler} failed on {SOURCE.name}: {run.stderr.strip()[-400:]}")
        kernel(Path(tmp))                       # refuse a library that does not load
        os.replace(tmp, out)
        for old in out.parent.glob("_match-*.so"):  # libraries of an older match.c
            if old != out:
                old.unlink(missing_ok=True)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return out


def kernel(path: Path):
    """The matching function of the library at ``path``:
    ``fn(r_ptr, m, c_ptr, n, max_d2, idx_ptr) -> 0 | -1`` (see ``match.c``).
    Raises OSError for a file that is not a library, NativeBuildError for another ABI."""
    lib = ctypes.CDLL(str(Path(path).resolve()))
    if lib.tf_abi_version() != ABI_VERSION:
        raise NativeBuildError(f"{path} is ABI {lib.tf_abi_version()}, expected {ABI_VERSION}")
    fn = lib.tf_match
    fn.argtypes = [ctypes.c_void_p, ctypes.c_int64, ctypes.c_void_p, ctypes.c_int64,
                   ctypes.c_double, ctypes.c_void_p]
    fn.restype = ctypes.c_int
    grow = lib.tf_grow
    grow.argtypes = [ctypes.c_void_p, ctypes.c_int64, ctypes.c_void_p, ctypes.c_int64,
                     ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int64,
                     ctypes.c_double, ctypes.c_int64, ctypes.c_int64, ctypes.c_int64,
                     ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p]
    grow.restype = ctypes.c_int
    fn.grow = grow
    return fn


_FN = None
_WHY = "not loaded yet"


def load():
    """The kernel's function, or None (not built, disabled, or broken; see :func:`status`)."""
    global _FN, _WHY
    if os.environ.get("TACFOOT_NATIVE", "1") == "0":
        _FN, _WHY = None, "disabled by TACFOOT_NATIVE=0"
        return None
    path = library_path()
    if not path.exists():
        _FN, _WHY = None, f"not built ({path.name} missing: python -m device.pi.vision.native build)"
        return None
    try:
        _FN, _WHY = kernel(path), f"compiled ({path})"
    except (OSError, AttributeError, NativeBuildError) as exc:
        _FN, _WHY = None, f"{path.name} does not load: {exc}"
    return _FN


def active() -> bool:
    """True when the tracker's matching runs compiled."""
    return _FN is not None


def status() -> str:
    """``"compiled (path)"`` or why the numpy matcher runs."""
    return _WHY


def match_into(r: np.ndarray, c: np.ndarray, max_d2: float, idx: np.ndarray) -> bool:
    """Run the kernel on float64 (m, 2) ``r`` and (n, 2) ``c`` (usable rows),
    writing ``idx`` (int64, all -1 on entry). False when the kernel is not
    loaded or ran out of memory (``idx`` untouched): use the numpy path."""
    fn = _FN
    if fn is None:
        return False
    if not r.flags.c_contiguous:
        r = np.ascontiguousarray(r)
    if not c.flags.c_contiguous:
        c = np.ascontiguousarray(c)
    return fn(r.ctypes.data, r.shape[0], c.ctypes.data, c.shape[0], max_d2, idx.ctypes.data) == 0




def grow_into(r: np.ndarray, c: np.ndarray, pred: np.ndarray, nb: np.ndarray, valid: np.ndarray,
              gate: float, grow_rounds: int, min_support: int, final_rounds: int,
              disp: np.ndarray):
    """The compiled :func:`device.pi.vision.neighbours.match_and_grow` for its usual
    case (every reference pin finite): ``(idx, n_confident)``, ``disp`` written, or
    None (kernel not loaded, a predicted position beyond +-1e6 px, or no memory:
    nothing written, use the numpy path). ``r``, ``pred``, ``disp`` (m, 2) and ``c``
    (n, 2) float64, ``nb`` int64 and ``valid`` bool (m, k)."""
    fn = _FN
    if fn is None:
        return None
    m, n = r.shape[0], c.shape[0]
    if m == 0 or n == 0:
        return None
    arrs = [np.ascontiguousarray(a) for a in (r, c, pred, nb, valid)]
    if not (disp.flags.c_contiguous and disp.dtype == np.float64 and arrs[3].dtype == np.int64
            and arrs[4].dtype == np.bool_ and arrs[2].dtype == np.float64):
        return None
    r, c, pred, nb, valid = arrs
    idx = np.empty(m, np.int64)
    n_conf = ctypes.c_int64(0)            # per call: the worker thread runs it too
    rc = fn.grow(r.ctypes.data, m, c.ctypes.data, n, pred.ctypes.data, nb.ctypes.data,
                 valid.ctypes.data, nb.shape[1], gate, grow_rounds, min_support, final_rounds,
                 idx.ctypes.data, disp.ctypes.data, ctypes.addressof(n_conf))
    if rc != 0:
        return None
    return idx, int(n_conf.value)


load()


def main(argv=None) -> int:
    import argparse
    ap = argparse.ArgumentParser(prog="python -m device.pi.vision.native",
                                 description="Build or check the tracker's compiled matching kernel.")
    ap.add_argument("action", choices=("build", "status"))
    ap.add_argument("--quiet", action="store_true", help="build: no line on success")
    ap.add_argument("--force", action="store_true", help="build: compile even when the library is there")
    a = ap.parse_args(argv)
    if a.action == "status":
        print(f"matcher: {status()}")
        return 0 if active() else 1
    try:
        path = build(force=a.force)
    except NativeBuildError as exc:
        print(f"native build: {exc}", file=sys.stderr)
        return 1
    if not a.quiet:
        print(f"built {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
