"""A wheel of this checkout, built as a user's ``pip wheel`` would, and "installed" by
unpacking it into a folder that then stands for site-packages: for the tests that
check what an installed toolkit finds (the shipped models, trial files, layout)."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

from device.shipped import SHIPPED
from tests import REPO_ROOT


def source_tree(dst: Path) -> Path:
    """A clean copy of what the build reads (builds write build/ and egg-info there,
    never into the checkout): the packages and every shipped file."""
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info", "build", "*.so")
    dst.mkdir(parents=True)
    for pkg in ("device", "host"):
        shutil.copytree(REPO_ROOT / pkg, dst / pkg, ignore=ignore)
    for rel in SHIPPED.values():
        src = REPO_ROOT / rel
        (dst / rel).parent.mkdir(parents=True, exist_ok=True)
        if src.is_dir():
            shutil.copytree(src, dst / rel, ignore=ignore)
        elif src.is_file():
            shutil.copy2(src, dst / rel)
    return dst


def clean_env(**extra) -> dict:
    """The environment without PYTHONPATH (which would show pip or Python this checkout)."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    return dict(env, PYTHONWARNINGS="ignore", **extra)


def build_wheel(tmp: Path) -> Path:
    """``pip wheel --no-deps`` of a copy of the checkout, into ``tmp/dist``; no C
    compiler (CC names none), so no library: a few seconds."""
    tree = source_tree(tmp / "tree")
    run = subprocess.run([sys.executable, "-m", "pip", "--disable-pip-version-check", "wheel",
                          "--no-deps", "--no-build-isolation", "-w", str(tmp / "dist"),
                          str(tree)], capture_output=True, text=True, timeout=300,
                         env=clean_env(CC="no-such-cc-here"))
    wheels = sorted((tmp / "dist").glob("tacfoot-*.whl"))
    assert run.returncode == 0 and wheels, run.stderr[-2000:]
    return wheels[0]


def unpack(whl: Path, site: Path) -> Path:
    """The wheel's files in ``site`` (what pip install puts in site-packages)."""
    with zipfile.ZipFile(whl) as z:
        z.extractall(site)
    return site
