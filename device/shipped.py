"""Where the files that ship beside the code are: the default models, the rig's trial
files, the Foxglove layout, and the source files host deploy rebuilds the leg's
source distribution from.

In a checkout they are where the repository keeps them (``models/``, ``trials/``,
``docs/foxglove-layout.json``, ``pyproject.toml``, ...). A wheel carries them inside
the package, under ``device/data/`` (setup.py's ``build_py`` copies them there, as
:data:`SHIPPED` names them), so an installed toolkit finds them from any folder::

    python -m device.shipped        # prints each one's path, as JSON

The profiles (``device/profiles``), the leg config (``device/leg.toml``) and the
simulator's scenes (``device/sim/scenes``) already live in the package.
"""
from __future__ import annotations

import importlib.resources
import json
import sys
from pathlib import Path

#: each shipped file or folder: its name under ``device/data/`` in a wheel -> its path
#: in a checkout. setup.py reads this literal (without importing the package).
SHIPPED = {
    "models": "models",
    "trials": "trials",
    "foxglove-layout.json": "docs/foxglove-layout.json",
    "source/pyproject.toml": "pyproject.toml",
    "source/setup.py": "setup.py",
    "source/README.md": "README.md",
    "source/LICENSE": "LICENSE",
    "source/MANIFEST.in": "MANIFEST.in",
}
#: the folder of the package that holds them in a wheel
PACKAGED = "data"
#: the checkout: the folder above the package
CHECKOUT = Path(__file__).resolve().parent.parent


def packaged_dir() -> Path:
    """``device/data`` of the imported package (it exists only in an installed wheel)."""
    return Path(str(importlib.resources.files("device"))) / PACKAGED


def is_checkout() -> bool:
    """The package is imported from a source tree (this repository's pyproject.toml is
    beside it), not from an installed wheel."""
    return (CHECKOUT / "pyproject.toml").is_file() and (CHECKOUT / "setup.py").is_file()


def shipped(name: str) -> Path:
    """The path of a shipped file or folder (a key of :data:`SHIPPED`): the wheel's copy
    when the package carries one, else the checkout's. It may not exist (e.g. a checkout
    whose ``models/`` was removed); callers say so in their own words."""
    if name not in SHIPPED:
        raise KeyError(f"shipped: {name!r} is not a shipped file; one of {sorted(SHIPPED)}")
    packaged = packaged_dir() / name
    if packaged.exists() or not is_checkout():
        return packaged
    return CHECKOUT / SHIPPED[name]


def models_dir() -> Path:
    """The shipped default models (``models/``)."""
    return shipped("models")


def trials_dir() -> Path:
    """The shipped rig trial files (``trials/``)."""
    return shipped("trials")


def layout_file() -> Path:
    """The Foxglove layout (``docs/foxglove-layout.json``)."""
    return shipped("foxglove-layout.json")


def main(argv=None) -> int:
    del argv
    print(json.dumps({"checkout": is_checkout(), "models": str(models_dir()),
                      "trials": str(trials_dir()), "layout": str(layout_file())}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
