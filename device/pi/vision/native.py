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

The package's own build compiles the library (``setup.py``: a setuptools extension
with no Python API, opened here with ctypes): ``pip install .`` and ``pip install -e
.`` (``make install``) put ``_tacfoot_core-<tag>.so`` into the package, and ``host
deploy`` installs the source distribution on each leg, so pip compiles it there.
``pip uninstall tacfoot`` removes it with the rest. Without a C compiler, or with
``TACFOOT_NATIVE=0`` in the environment, the tracker uses numpy: the same numbers,
slower. The library's name carries a hash of the C files (:data:`SOURCES`), the
flags and the machine, computed again here from the files at import, so a library
from older C files (an editable checkout edited since its install) or another
machine is never loaded::

    python -m device.pi.vision.native status    # which matcher the tracker uses

``TACFOOT_NATIVE_DIR`` names another folder, whose library (``_match-<tag>.so``) is
then the only one looked at: ``python -m device.pi.vision.native build`` compiles
into it, with ``TACFOOT_NATIVE_CFLAGS`` added (a developer's tool, used by the tests
for a sanitizer build; it never writes into the package).

Before the library is opened, :func:`check_library` reads its ELF headers without
loading it: a file cut short (``dlopen`` maps past its end, and the first touch of
a missing page kills the process with SIGBUS), a file built for another CPU, or
anything that is not a shared library is refused with a one-line reason
(:func:`refused`), and the tracker runs on numpy. ``native build`` syncs the library
to disk before renaming it into place, and the folder after, so a power cut leaves
the old state or the whole new file (pip writes the packaged one).
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import os
import platform
import shutil
import stat
import struct
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from device.errors import TacfootError

__all__ = ["SOURCE", "CFLAGS", "packaged_path", "rebuild_hint", "NativeBuildError",
           "NativeFolderError", "library_path", "check_library", "build", "kernel", "load",
           "match_into", "grow_into", "active", "status", "refused", "detect_fn", "winfeat_fn",
           "grid_fn", "advance_fn", "shear_fn", "track_fn", "frame_fn", "SOURCES"]

SOURCE = Path(__file__).with_name("match.c")
#: every C file of the library: the tracker's kernels, the pin detection
#: (``detect.c``, :mod:`device.pi.vision.core`), the window features and the usual
#: frame in one call (``frame.c``, :mod:`device.pi.vision.frame`)
SOURCES = tuple(SOURCE.with_name(n) for n in ("match.c", "detect.c", "winfeat.c", "frame.c"))
#: the kernel's ABI; tf_abi_version() must return it
ABI_VERSION = 8
#: the compiler's flags: no fused multiply-add, so distances are numpy's to the bit;
#: -O3 vectorises detect.c's integer loops (the same integers in every lane).
#: setup.py reads SOURCE, SOURCES and CFLAGS from this file without importing it:
#: their values may use Path, __file__, SOURCE, tuple, list and sorted only
CFLAGS = ("-O3", "-ffp-contract=off", "-std=c99")
#: what ``native build`` adds (setuptools adds its own for the packaged library)
_SHARED = ("-fPIC", "-shared")
#: the packaged library's name before its tag (setup.py's ``LIBRARY``)
PACKAGED_PREFIX = "_tacfoot_core-"


def _cflags() -> tuple[str, ...]:
    """``native build``'s flags: CFLAGS plus ``TACFOOT_NATIVE_CFLAGS`` (the tests'
    sanitizer build: its library gets its own name)."""
    return CFLAGS + tuple(os.environ.get("TACFOOT_NATIVE_CFLAGS", "").split())


class NativeBuildError(TacfootError, RuntimeError):
    """The kernel could not be compiled (no compiler, or it failed)."""


class NativeFolderError(NativeBuildError):
    """The library's folder cannot be created or written (read-only, or not a folder)."""


#: e_machine numbers of the CPUs a leg or a development machine may have, for messages
_MACHINES = {3: "i386", 8: "mips", 20: "ppc", 21: "ppc64", 22: "s390x", 40: "arm", 62: "x86_64",
             183: "aarch64", 243: "riscv"}
_MACHINE_OF = {"x86_64": 62, "amd64": 62, "i386": 3, "i686": 3, "aarch64": 183, "arm64": 183,
               "armv6l": 40, "armv7l": 40, "armv8l": 40, "riscv64": 243, "ppc64le": 21,
               "ppc64": 21, "s390x": 22}
_ET_DYN = 3


def _machine_name(e_machine: int) -> str:
    return _MACHINES.get(e_machine, f"ELF machine {e_machine}")


def _elf_ident(head: bytes):
    """``(is64, little, e_machine)`` of an ELF header, or None for anything else."""
    if len(head) < 20 or head[:4] != b"\x7fELF" or head[4] not in (1, 2) or head[5] not in (1, 2):
        return None
    little = head[5] == 1
    return head[4] == 2, little, struct.unpack_from("<H" if little else ">H", head, 18)[0]


@functools.lru_cache(maxsize=1)
def _this_machine():
    """``(is64, little, e_machine)`` a library must have to load into this process: the
    interpreter's own ELF header (a 32-bit Python on a 64-bit kernel, as on many
    Raspberry Pi systems, loads 32-bit libraries only), else the word size, byte order
    and ``platform.machine()``; e_machine None when it cannot be told."""
    for exe in (os.path.realpath(sys.executable or ""), "/proc/self/exe"):
        try:
            with open(exe, "rb") as f:
                ident = _elf_ident(f.read(20))
        except OSError:
            continue
        if ident is not None:
            return ident
    return (struct.calcsize("P") == 8, sys.byteorder == "little",
            _MACHINE_OF.get(platform.machine().lower()))


def check_library(path) -> str | None:
    """Why the library at ``path`` must not be loaded, in one line, or None when its
    structure allows it. Reads only the ELF headers, never maps or runs the file:
    a regular file; an ELF shared library of this process's word size, byte order
    and CPU; its program headers, every segment (``p_offset + p_filesz``), the
    section header table and every section's bytes inside the file. ``dlopen`` on
    a file cut short maps pages past its end and the process dies of SIGBUS at the
    first touch, so this runs before any ``ctypes.CDLL``."""
    path = Path(path)
    try:
        st = os.stat(path)
        if not stat.S_ISREG(st.st_mode):
            return "is not a regular file"
        size = st.st_size
        with open(path, "rb") as f:
            return _check_elf(f, size)
    except OSError as exc:
        return f"cannot be read ({exc.strerror or exc})"


def _check_elf(f, size: int) -> str | None:
    head = f.read(64)
    ident = _elf_ident(head)
    if ident is None:
        return f"is not an ELF library ({size} bytes)" if size else "is empty"
    is64, little, e_machine = ident
    want64, want_little, want_machine = _this_machine()
    if is64 != want64:
        return f"is a {64 if is64 else 32}-bit library, this Python is {64 if want64 else 32}-bit"
    if little != want_little:
        return (f"is {'little' if little else 'big'}-endian, this machine is "
                f"{'little' if want_little else 'big'}-endian")
    if want_machine is not None and e_machine != want_machine:
        return f"built for {_machine_name(e_machine)}, this machine is {_machine_name(want_machine)}"
    e = "<" if little else ">"
    ehsize = 64 if is64 else 52
    if len(head) < ehsize:
        return f"is cut short: {size} bytes, less than its {ehsize}-byte ELF header"
    (e_type, _, _, _, phoff, shoff, _, _, phentsize, phnum, shentsize, shnum, _) = struct.unpack_from(
        e + ("HHIQQQIHHHHHH" if is64 else "HHIIIIIHHHHHH"), head, 16)
    if e_type != _ET_DYN:
        return f"is not a shared library (ELF type {e_type})"
    ph_size, sh_size = (56, 64) if is64 else (32, 40)
    sec = e + ("IIQQQQIIQQ" if is64 else "IIIIIIIIII")

    def read(off: int, n: int) -> bytes:
        f.seek(off)
        return f.read(n)

    if shoff and (shnum == 0 or phnum == 0xFFFF):          # extended numbering: section 0 holds it
        if shentsize != sh_size or shoff + sh_size > size:
            return f"is cut short: its section header table starts at byte {shoff}, the file has {size} bytes"
        s0 = struct.unpack(sec, read(shoff, sh_size))
        shnum = shnum or s0[5]
        phnum = s0[7] if phnum == 0xFFFF else phnum
    if phnum == 0:
        return "has no program headers"
    if phentsize != ph_size:
        return f"has {phentsize}-byte program headers, expected {ph_size}"
    if phoff + phnum * ph_size > size:
        return (f"is cut short: its program headers end at byte {phoff + phnum * ph_size}, "
                f"the file has {size} bytes")
    table = read(phoff, phnum * ph_size)
    for i in range(phnum):
        if is64:
            _, _, p_offset, _, _, p_filesz, _, _ = struct.unpack_from(e + "IIQQQQQQ", table, i * ph_size)
        else:
            _, p_offset, _, _, p_filesz, _, _, _ = struct.unpack_from(e + "IIIIIIII", table, i * ph_size)
        if p_offset + p_filesz > size:
            return (f"is cut short: segment {i} ends at byte {p_offset + p_filesz}, "
                    f"the file has {size} bytes")
    if shoff == 0:
        return None
    if shnum and shentsize != sh_size:
        return f"has {shentsize}-byte section headers, expected {sh_size}"
    if shoff + shnum * sh_size > size:
        return (f"is cut short: its section headers end at byte {shoff + shnum * sh_size}, "
                f"the file has {size} bytes")
    table = read(shoff, shnum * sh_size)
    for i in range(1, shnum):
        _, sh_type, _, _, sh_offset, sh_bytes, *_ = struct.unpack_from(sec, table, i * sh_size)
        if sh_type != 8 and sh_offset + sh_bytes > size:          # SHT_NOBITS has no bytes
            return (f"is cut short: section {i} ends at byte {sh_offset + sh_bytes}, "
                    f"the file has {size} bytes")
    return None


def _tag(flags: tuple[str, ...] | None = None) -> str:
    """The hash of the C files, ``flags`` (``native build``'s by default) and the
    machine; setup.py's ``library_tag`` computes the same for the packaged library."""
    h = hashlib.sha256()
    for src in SOURCES:
        try:
            h.update(src.read_bytes())
        except OSError:                 # an install without its C files: nothing loads
            h.update(b"missing " + src.name.encode())
    h.update(" ".join(_cflags() if flags is None else flags).encode())
    h.update(platform.machine().encode())
    return h.hexdigest()[:12]


def packaged_path() -> Path:
    """Where the package's own library is for these C files and this machine: next
    to ``match.c``, written there by pip (site-packages, or the checkout of an
    editable install)."""
    return SOURCE.parent / f"{PACKAGED_PREFIX}{_tag(CFLAGS)}.so"


def library_path(folder: Path | None = None) -> Path:
    """The library the tracker loads: ``_match-<tag>.so`` in ``folder`` or in
    ``TACFOOT_NATIVE_DIR`` when either is given, else :func:`packaged_path`."""
    base = folder or os.environ.get("TACFOOT_NATIVE_DIR")
    return Path(base) / f"_match-{_tag()}.so" if base else packaged_path()


def rebuild_hint() -> str:
    """How to rebuild the library the tracker looks for, for one-line messages."""
    if os.environ.get("TACFOOT_NATIVE_DIR"):
        return "rebuild: python -m device.pi.vision.native build"
    return "rebuild: reinstall tacfoot where a C compiler is, e.g. pip install . or make install"


def build(folder: Path | None = None, cc: str | None = None, force: bool = False) -> Path:
    """Compile :data:`SOURCES` into :func:`library_path` in ``folder`` or
    ``TACFOOT_NATIVE_DIR`` (unless it is there already and loads, or ``force``);
    returns the path. Never into the package: pip builds that one. The file appears
    whole or not at all, power cuts included: compiled to a temporary name, checked,
    synced to disk, renamed, then the folder synced. No folder named, or one that
    cannot be made or written, raises :class:`NativeFolderError`."""
    if not (folder or os.environ.get("TACFOOT_NATIVE_DIR")):
        raise NativeFolderError("native build writes only into TACFOOT_NATIVE_DIR, which is not "
                                "set; the package's own library is compiled by pip install "
                                "(pip install . or make install)")
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
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".match-", suffix=".so", dir=out.parent)
        os.close(fd)
    except OSError as exc:
        raise NativeFolderError(f"cannot write the library into {out.parent}: "
                                f"{exc.strerror or exc}; the tracker runs on numpy") from None
    try:
        run = subprocess.run([exe, *_cflags(), *_SHARED, "-o", tmp, *map(str, SOURCES), "-lm"],
                             capture_output=True, text=True, timeout=120)
        if run.returncode != 0:
            raise NativeBuildError(f"{compiler} failed on {SOURCE.name}: {run.stderr.strip()[-400:]}")
        _fsync(tmp, os.O_RDONLY)                # the compiler wrote it under its own descriptor
        kernel(Path(tmp))                       # refuse a library that does not load
        os.replace(tmp, out)
        try:                                    # the rename itself survives a power cut
            _fsync(out.parent, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
        except OSError:
            pass                                # a file system that cannot sync a folder
        for old in out.parent.glob("_match-*.so"):  # libraries of an older match.c
            if old != out:
                old.unlink(missing_ok=True)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return out


def _fsync(path, flags: int) -> None:
    fd = os.open(path, flags)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def kernel(path: Path):
    """The matching function of the library at ``path``:
    ``fn(r_ptr, m, c_ptr, n, max_d2, idx_ptr) -> 0 | -1`` (see ``match.c``).
    Raises NativeBuildError for a file :func:`check_library` refuses (never opened)
    or another ABI, OSError for one the dynamic loader refuses."""
    why = check_library(path)
    if why is not None:
        raise NativeBuildError(f"{path} {why}")
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
    for attr, (symbol, argtypes, restype, slots) in _KERNELS.items():
        f = getattr(lib, symbol)
        f.argtypes, f.restype = argtypes, restype
        if slots is not None and getattr(lib, symbol + "_slots")() != slots:
            raise NativeBuildError(f"{symbol} has {getattr(lib, symbol + '_slots')()} context "
                                   f"slots, expected {slots}")
        setattr(fn, attr, f)
    return fn


#: the contact grid's context slots (detect.c's TF_G_*)
GRID_SLOTS = 15
#: the pin detection's context slots (detect.c's TF_D_*; device.pi.vision.core.S_SLOTS)
DETECT_SLOTS = 43
#: the window features' context slots per model (winfeat.c; device.pi.models.winfeat)
WINFEAT_SLOTS = 12

#: the tracker's update contexts (match.c's TF_T_* integer and TF_TD_* double slots)
TRACK_SLOTS = (22, 7)
#: the fused frame's contexts (frame.c's TF_F_* integer and TF_FD_* double slots)
FRAME_SLOTS = (17, 17)

_P, _I, _D = ctypes.c_void_p, ctypes.c_int64, ctypes.c_double
#: the per-frame kernels besides the matching: the attribute of the kernel function
#: that holds each, its C symbol, argument and result types, and its context's slot
#: count (checked against the library's ``<symbol>_slots()``) for one-context kernels
_KERNELS = {
    "detect": ("tf_detect", [_P], ctypes.c_int64, DETECT_SLOTS),
    "winfeat": ("tf_winfeat", [_P], ctypes.c_int, WINFEAT_SLOTS),
    "grid": ("tf_grid", [_P], ctypes.c_int64, GRID_SLOTS),
    "advance": ("tf_advance", [_P, _P, _P, _P, _I, _D, _D, _I, _D], None, None),
    "shear": ("tf_shear", [_P, _P, _I, _D, _P, _P], ctypes.c_int64, None),
    "track": ("tf_track", [_P, _P], ctypes.c_int64, 100 * TRACK_SLOTS[0] + TRACK_SLOTS[1]),
    "frame": ("tf_frame", [_P], ctypes.c_int64, 100 * FRAME_SLOTS[0] + FRAME_SLOTS[1]),
}


def _kernel(attr: str):
    fn = _FN
    return None if fn is None else getattr(fn, attr)


def detect_fn():
    """``tf_detect`` of the loaded library (:mod:`device.pi.vision.core`), or None."""
    return _kernel("detect")


def winfeat_fn():
    """``tf_winfeat`` of the loaded library (:mod:`device.pi.models.winfeat`), or None."""
    return _kernel("winfeat")


def grid_fn():
    """``tf_grid`` (:class:`~device.pi.vision.features.ContactGrid`), or None."""
    return _kernel("grid")


def advance_fn():
    """``tf_advance`` (the tracker's prediction state, Tracker._advance), or None."""
    return _kernel("advance")


def track_fn():
    """``tf_track`` (Tracker.update's usual frame), or None."""
    return _kernel("track")


def frame_fn():
    """``tf_frame`` (the marker pipeline's usual frame in one call), or None."""
    return _kernel("frame")


def shear_fn():
    """``tf_shear`` (features.shear_and_sum over the rows not lost), or None."""
    return _kernel("shear")


_FN = None
_WHY = "not loaded yet"
_REFUSED: str | None = None


def load():
    """The kernel's function, or None (not built, disabled, or refused; see :func:`status`
    and :func:`refused`)."""
    global _FN, _WHY, _REFUSED
    _FN, _REFUSED = None, None
    if os.environ.get("TACFOOT_NATIVE", "1") == "0":
        _WHY = "disabled by TACFOOT_NATIVE=0"
        return None
    path = library_path()
    if not path.exists():
        others = [] if os.environ.get("TACFOOT_NATIVE_DIR") else sorted(
            path.parent.glob(PACKAGED_PREFIX + "*.so"))
        if others:                      # an editable checkout whose C files changed since
            _REFUSED = (f"{others[0]} was built from other C files or for another machine "
                        f"(these need {path.name})")
            _WHY = f"does not load: {_REFUSED} ({rebuild_hint()})"
        else:
            _WHY = f"not built ({path.name} missing; {rebuild_hint()})"
        return None
    try:
        _FN, _WHY = kernel(path), f"compiled ({path})"
    except (OSError, AttributeError, NativeBuildError) as exc:
        _REFUSED = " ".join(str(exc).split()) or f"{path}: {type(exc).__name__}"  # one line
        _WHY = f"does not load: {_REFUSED} ({rebuild_hint()})"
    return _FN


def active() -> bool:
    """True when the tracker's matching runs compiled."""
    return _FN is not None


def status() -> str:
    """``"compiled (path)"`` or why the numpy matcher runs."""
    return _WHY


def refused() -> str | None:
    """Why a library that is there was not loaded (cut short, another CPU, another
    ABI, the loader's error), in one line; None when it loaded, is not built, or
    the kernel is disabled."""
    return _REFUSED


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
    except NativeFolderError as exc:
        print(f"native build: error: {exc}", file=sys.stderr)
        return 2
    except NativeBuildError as exc:
        print(f"native build: {exc}", file=sys.stderr)
        return 1
    if not a.quiet:
        print(f"built {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
