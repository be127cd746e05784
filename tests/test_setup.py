"""setup.py: the package's own build compiles the frame core's C library into the
package (the wheel carries it, RECORD lists it, ``pip uninstall`` removes it), the
source distribution carries the C files (host deploy's pip compiles them on the
leg), and without a C compiler the build succeeds with one line."""
from __future__ import annotations

import importlib.util
import os
import re
import shutil
import subprocess
import sys
import tarfile
import zipfile
from pathlib import Path

import pytest

from device.pi.vision import native
from tests import REPO_ROOT

needs_cc = pytest.mark.skipif(shutil.which(os.environ.get("CC", "cc")) is None,
                              reason="no C compiler here: the package builds without its library")
NOT_COMPILED = "tacfoot: the C library was not compiled ("


def _setup_module():
    """setup.py as a module (its ``setup()`` call runs only as ``__main__``)."""
    spec = importlib.util.spec_from_file_location("tacfoot_setup", REPO_ROOT / "setup.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_setup_reads_the_c_files_and_flags_from_native_py_and_names_the_library_alike():
    """The extension compiles native.SOURCES with native.CFLAGS, and its file name is
    the one the loader looks for (the same hash of the C files, flags and machine)."""
    s = _setup_module()
    got = s.native_settings()
    assert got["SOURCES"] == native.SOURCES and got["CFLAGS"] == native.CFLAGS
    assert s.library_name(got) == native.packaged_path().name
    ext = s.core_extension()
    assert [REPO_ROOT / p for p in ext.sources] == list(native.SOURCES)
    assert ext.optional and tuple(ext.extra_compile_args) == native.CFLAGS


def test_a_c_file_added_to_sources_is_compiled_and_a_bad_sources_is_one_line(tmp_path):
    """SOURCES is read, not copied: a third C file named there is compiled too; an
    expression setup.py cannot evaluate stops the build with one line naming it."""
    s = _setup_module()
    text = (REPO_ROOT / "device/pi/vision/native.py").read_text()
    old = re.search(r"^SOURCES = .*$", text, re.M).group(0)
    names = [p.name for p in native.SOURCES]
    fake = tmp_path / "native.py"
    listed = ", ".join(f'SOURCE.with_name("{n}")' for n in names)
    fake.write_text(text.replace(old, f'SOURCES = ({listed}, SOURCE.with_name("extra.c"))'))
    assert [p.name for p in s.native_settings(fake)["SOURCES"]] == names + ["extra.c"]
    fake.write_text(text.replace(old, "SOURCES = tuple(SOURCE.with_name(n) for n in "
                                      f"{tuple(names + ['extra.c'])!r})"))
    assert [p.name for p in s.native_settings(fake)["SOURCES"]] == names + ["extra.c"]
    fake.write_text(text.replace(old, "SOURCES = tuple(sorted(HERE.glob('*.c')))"))
    with pytest.raises(SystemExit) as exc:
        s.native_settings(fake)
    msg = str(exc.value)
    assert "\n" not in msg and msg.startswith(f"setup.py: cannot read SOURCES from {fake} (line ")
    assert "name 'HERE' is not defined" in msg


@pytest.fixture
def tree(tmp_path) -> Path:
    """A clean copy of what the build reads (as host deploy copies it): builds write
    build/ and egg-info there, never into the checkout."""
    src = tmp_path / "tree"
    src.mkdir()
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info", "build", "*.so")
    for name in ("pyproject.toml", "setup.py", "README.md"):
        shutil.copy2(REPO_ROOT / name, src / name)
    for pkg in ("device", "host"):
        shutil.copytree(REPO_ROOT / pkg, src / pkg, ignore=ignore)
    return src


def _pip(*args, **env) -> subprocess.CompletedProcess:
    """pip, blind to the checkout (a PYTHONPATH naming it would show pip this tree's
    egg-info as an installed tacfoot)."""
    clean = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    return subprocess.run([sys.executable, "-m", "pip", "--disable-pip-version-check", *args],
                          capture_output=True, text=True, timeout=300,
                          env=dict(clean, PYTHONWARNINGS="ignore", **env))


def _wheel(tree: Path, out: Path, **env) -> tuple[subprocess.CompletedProcess, Path | None]:
    run = _pip("wheel", "-v", "--no-deps", "--no-build-isolation", "-w", str(out), str(tree), **env)
    wheels = sorted(out.glob("tacfoot-*.whl"))
    return run, (wheels[0] if wheels else None)


@pytest.mark.slow
@needs_cc
def test_the_wheel_carries_the_library_record_lists_it_and_uninstall_removes_it(tree, tmp_path):
    """pip wheel compiles the C into the package: the library (the name the loader
    looks for) is in the wheel and its RECORD, it passes check_library and loads;
    installed into a fresh venv it is there, and ``pip uninstall`` leaves nothing."""
    run, whl = _wheel(tree, tmp_path / "dist")
    assert run.returncode == 0 and whl is not None, run.stderr[-2000:]
    assert NOT_COMPILED not in run.stdout + run.stderr
    lib = f"device/pi/vision/{native.packaged_path().name}"
    with zipfile.ZipFile(whl) as z:
        names = z.namelist()
        record = z.read(next(n for n in names if n.endswith(".dist-info/RECORD"))).decode()
        assert lib in names and f"\n{lib},sha256=" in f"\n{record}"
        assert [n for n in names if n.endswith(".so")] == [lib]
        z.extract(lib, tmp_path / "x")
    assert native.check_library(tmp_path / "x" / lib) is None
    assert native.kernel(tmp_path / "x" / lib).detect is not None

    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120)
    py = venv / "bin" / "python"
    site = Path(subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()"
                                "['platlib'])"], capture_output=True, text=True,
                               check=True).stdout.strip())
    run = _pip("--python", str(py), "install", "--no-deps", "--no-index", str(whl))
    assert run.returncode == 0, run.stderr[-2000:]
    assert (site / lib).is_file()
    run = _pip("--python", str(py), "uninstall", "-y", "tacfoot")
    assert run.returncode == 0, run.stderr[-2000:]
    left = sorted(str(p.relative_to(site)) for p in site.rglob("*")
                  if "device" in p.parts or "host" in p.parts or "tacfoot" in p.name)
    assert left == []

    # the C files change and the same tree builds again: the wheel carries the new
    # library alone (the old one, left in build/, would go into it too)
    with open(tree / "device/pi/vision/match.c", "a") as f:
        f.write("/* changed */\n")
    s = _setup_module()
    new = f"device/pi/vision/{s.library_name(s.native_settings(tree / 'device/pi/vision/native.py'))}"
    assert new != lib and (tree / "build").is_dir()
    run, whl = _wheel(tree, tmp_path / "dist2")
    assert run.returncode == 0 and whl is not None, run.stderr[-2000:]
    with zipfile.ZipFile(whl) as z:
        assert [n for n in z.namelist() if n.endswith(".so")] == [new]


@pytest.mark.slow
def test_without_a_compiler_the_build_succeeds_with_one_line(tree, tmp_path):
    """CC names no compiler: the wheel builds, without a library, and the build says
    so in one line; the package then runs on numpy (test_native's not-built case)."""
    run, whl = _wheel(tree, tmp_path / "dist", CC="no-such-cc-here")
    assert run.returncode == 0 and whl is not None, run.stderr[-2000:]
    lines = [ln.strip() for ln in (run.stdout + run.stderr).splitlines() if NOT_COMPILED in ln]
    assert len(lines) == 1, lines
    assert "'no-such-cc-here'" in lines[0] and lines[0].endswith(
        "the tracker and the pin detection run on numpy (install gcc and reinstall for the "
        "compiled core)")
    with zipfile.ZipFile(whl) as z:
        assert not [n for n in z.namelist() if n.endswith(".so")]


def test_the_sdist_carries_setup_py_and_every_c_file(tree, tmp_path):
    """What host deploy ships: the leg's pip compiles the library from it."""
    out = tmp_path / "sdist"
    subprocess.run([sys.executable, "-c", "import sys, setuptools.build_meta as b; "
                    "b.build_sdist(sys.argv[1])", str(out)], cwd=tree, check=True,
                   capture_output=True, timeout=120, env=dict(os.environ, PYTHONWARNINGS="ignore"))
    sdist, = out.glob("tacfoot-*.tar.gz")
    with tarfile.open(sdist) as t:
        names = {n.split("/", 1)[1] for n in t.getnames() if "/" in n}
    want = {"setup.py", "pyproject.toml", "device/pi/vision/native.py",
            *(p.relative_to(REPO_ROOT).as_posix() for p in native.SOURCES)}
    assert want <= names, want - names
    assert not [n for n in names if n.endswith(".so")]
