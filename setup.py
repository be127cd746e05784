"""The package's one compiled part: the frame core's C library, built by ``pip install``;
and the shipped files (models, trial files, the Foxglove layout, the source files host
deploy rebuilds from) copied into the package (``BuildShipped``, device/shipped.py).

Everything else about the package is in pyproject.toml. The C files
(``device.pi.vision.native.SOURCES``) hold no Python API: they are compiled into a
plain shared library that ``device/pi/vision/native.py`` opens with ctypes. So the
setuptools extension below only borrows setuptools' compiler driver: no Python
headers are needed (a Pi without ``python3-dev`` builds it), and without a C compiler
the install still succeeds, prints one line, and the tracker runs on numpy.

The library's file name carries a hash of the C files, the flags and the machine
(``_tacfoot_core-<tag>.so``, the same hash native.py computes from the files it
finds), so a library left from older C files is never loaded: an editable install
(``pip install -e .``) builds it next to the C files and removes older ones there.
"""
from __future__ import annotations

import ast
import hashlib
import os
import platform
import shutil
import sys
from pathlib import Path

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext
from setuptools.command.build_py import build_py
from setuptools.errors import BaseError, CCompilerError

HERE = Path(__file__).resolve().parent
NATIVE_PY = HERE / "device" / "pi" / "vision" / "native.py"
SHIPPED_PY = HERE / "device" / "shipped.py"
#: the extension's dotted name; the file it makes is named by library_name()
LIBRARY = "device.pi.vision._tacfoot_core"


def native_settings(native_py: Path = NATIVE_PY) -> dict:
    """``SOURCE``, ``SOURCES`` and ``CFLAGS`` as native.py defines them, read from its
    module-level assignments without importing it (the build has no numpy). Those
    assignments may use ``Path``, ``__file__``, each other, ``tuple``, ``list`` and
    ``sorted`` only."""
    names = ("SOURCE", "SOURCES", "CFLAGS")
    scope = {"__builtins__": {"tuple": tuple, "list": list, "sorted": sorted},
             "Path": Path, "__file__": str(native_py)}
    for node in ast.parse(native_py.read_text(), str(native_py)).body:
        target = node.targets[0] if isinstance(node, ast.Assign) and len(node.targets) == 1 else (
            node.target if isinstance(node, ast.AnnAssign) and node.value is not None else None)
        if isinstance(target, ast.Name) and target.id in names:
            try:
                scope[target.id] = eval(compile(ast.Expression(node.value), str(native_py), "eval"),
                                        scope)
            except Exception as exc:
                raise SystemExit(f"setup.py: cannot read {target.id} from {native_py} (line "
                                 f"{node.lineno}): {exc}; it may use Path, __file__, SOURCE, tuple, list and sorted only")
    missing = [n for n in names if n not in scope]
    if missing:
        raise SystemExit(f"setup.py: {native_py} defines no {', '.join(missing)}")
    return {n: scope[n] for n in names}


def library_tag(sources, cflags) -> str:
    """The hash in the library's name; native.py's ``_tag`` computes the same."""
    h = hashlib.sha256()
    for src in sources:
        h.update(Path(src).read_bytes())
    h.update(" ".join(cflags).encode())
    h.update(platform.machine().encode())
    return h.hexdigest()[:12]


def library_name(settings: dict) -> str:
    return f"_tacfoot_core-{library_tag(settings['SOURCES'], settings['CFLAGS'])}.so"


class BuildCore(build_ext):
    """build_ext for a ctypes library: its own file name, and one line (not a failed
    install) when it cannot be compiled."""

    def get_ext_filename(self, fullname: str) -> str:
        filename = super().get_ext_filename(fullname)   # asked with and without the package
        if fullname.rpartition(".")[2] == LIBRARY.rpartition(".")[2]:
            return os.path.join(os.path.dirname(filename), library_name(native_settings()))
        return filename

    def get_export_symbols(self, ext):
        return []                       # no PyInit_: it is never imported as a module

    def build_extension(self, ext) -> None:
        # a library of older C files left in build/ would go into the wheel too
        # (install_lib copies the whole folder)
        out = Path(self.get_ext_fullpath(ext.name))
        for old in out.parent.glob("_tacfoot_core-*.so"):
            if old.name != out.name:
                old.unlink()
        try:
            super().build_extension(ext)
        except (BaseError, CCompilerError, OSError) as exc:   # no compiler, or it failed
            why = " ".join(str(exc).split())[-300:]
            print(f"tacfoot: the C library was not compiled ({why}); the tracker and the pin "
                  "detection run on numpy (install gcc and reinstall for the compiled core)",
                  file=sys.stderr)

    def copy_extensions_to_source(self) -> None:
        super().copy_extensions_to_source()      # editable install: next to the C files
        name = library_name(native_settings())
        folder = NATIVE_PY.parent
        if (folder / name).exists():
            for old in folder.glob("_tacfoot_core-*.so"):
                if old.name != name:
                    old.unlink()


def shipped_files(shipped_py: Path = SHIPPED_PY) -> tuple[str, dict]:
    """``PACKAGED`` and ``SHIPPED`` as device/shipped.py defines them (literals, read
    without importing the package): the folder inside ``device`` and {name there: path
    in the source tree} of the files a wheel carries beside the code."""
    found = {}
    for node in ast.parse(shipped_py.read_text(), str(shipped_py)).body:
        target = node.targets[0] if isinstance(node, ast.Assign) and len(node.targets) == 1 else None
        if isinstance(target, ast.Name) and target.id in ("PACKAGED", "SHIPPED"):
            found[target.id] = ast.literal_eval(node.value)
    if set(found) != {"PACKAGED", "SHIPPED"}:
        raise SystemExit(f"setup.py: {shipped_py} defines no PACKAGED or SHIPPED literal")
    return found["PACKAGED"], found["SHIPPED"]


class BuildShipped(build_py):
    """build_py that also copies the shipped files (the default models, the trial
    files, the Foxglove layout, the source files host deploy rebuilds from) into the
    package, under ``device/<PACKAGED>/``, so an installed wheel finds them from any
    folder (device/shipped.py). An editable install reads them from the checkout; a
    tree without one of them (host deploy's copy has no models) builds without it."""

    def run(self) -> None:
        super().run()
        if getattr(self, "editable_mode", False):
            return
        packaged, shipped = shipped_files()
        root = Path(self.build_lib) / "device" / packaged
        for name, rel in shipped.items():
            src, dst = HERE / rel, root / name
            if src.is_dir():
                shutil.copytree(src, dst, dirs_exist_ok=True,
                                ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
            elif src.is_file():
                self.mkpath(str(dst.parent))
                self.copy_file(str(src), str(dst))


def core_extension() -> Extension:
    s = native_settings()
    return Extension(
        LIBRARY,
        sources=[os.path.relpath(p, HERE) for p in s["SOURCES"]],
        # setuptools adds -fPIC and links with -shared; -ffp-contract=off keeps the
        # distances numpy's to the bit (native.py's CFLAGS)
        extra_compile_args=list(s["CFLAGS"]),
        libraries=["m"],
        optional=True,
    )


if __name__ == "__main__":
    setup(ext_modules=[core_extension()], cmdclass={"build_ext": BuildCore, "build_py": BuildShipped})
