"""Every exception tacfoot defines derives from one root (issue 31): the root, the
standard bases kept beside it, and the one-line form the entry points print."""
from __future__ import annotations

import importlib
import inspect
import pkgutil

import pytest

from device.errors import InputError, TacfootError, one_line
from tests import REPO_ROOT

#: MicroPython modules: they run on the gait MCU, where the tacfoot package does not
#: exist, so their exceptions cannot derive from the root (device/errors.py says so)
MICROPYTHON = ("device/micropython", "device/sim/mpy/lib")


def _exception_classes():
    """(module name, class) of every exception class defined in device and host."""
    found = []
    for top in ("device", "host"):
        pkg = importlib.import_module(top)
        for info in pkgutil.walk_packages(pkg.__path__, top + "."):
            if info.name.endswith("__main__"):      # running one would start a command
                continue
            if not info.name.rpartition(".")[2].isidentifier():
                continue                            # the built C library (_tacfoot_core-TAG.so)
            try:
                mod = importlib.import_module(info.name)
            except ModuleNotFoundError as exc:      # an extra this install lacks
                pytest.skip(f"{info.name}: {exc}")
            for obj in vars(mod).values():
                if (inspect.isclass(obj) and issubclass(obj, BaseException)
                        and obj.__module__ == mod.__name__):
                    found.append((info.name, obj))
    return found


def test_every_exception_class_of_device_and_host_derives_from_the_root():
    found = _exception_classes()
    assert len(found) >= 40                         # the walk reached the packages
    stray = [f"{m}.{c.__name__}" for m, c in found if not issubclass(c, TacfootError)]
    assert stray == []


def test_the_walk_sees_every_module_but_the_micropython_ones():
    """A module the walk cannot reach (no package) could hide a class: only the
    MicroPython folders may be outside the packages."""
    unreached = []
    for path in sorted((REPO_ROOT / "device").rglob("*.py")) + sorted(
            (REPO_ROOT / "host").rglob("*.py")):
        rel = path.relative_to(REPO_ROOT).as_posix()
        if rel.startswith(MICROPYTHON):
            continue
        if not (path.parent / "__init__.py").is_file():
            unreached.append(rel)
    assert unreached == []


@pytest.mark.parametrize("name, kind", [
    ("device.config:ConfigError", ValueError), ("device.profile:ProfileError", ValueError),
    ("device.pi.models.spec:SpecError", ValueError),
    ("device.pi.models.artefact:ModelError", ValueError),
    ("host.data.errors:DataError", ValueError), ("host.learn.tasks:TrainError", ValueError),
    ("device.errors:InputError", ValueError),
    ("device.pi.sources.camera:CameraError", OSError),
    ("device.pi.runtime.link:LinkError", OSError),
    ("device.pi.runtime.mcapfiles:McapLogError", OSError),
    ("device.pi.sources.mpu6050:IMUError", RuntimeError),
    ("host.extras:MissingExtra", ModuleNotFoundError),
])
def test_each_error_keeps_its_standard_base(name, kind):
    mod, cls = name.split(":")
    c = getattr(importlib.import_module(mod), cls)
    assert issubclass(c, TacfootError) and issubclass(c, kind)


def test_source_and_argument_errors_are_input_errors():
    from device.checks import whole_number
    from device.pi.sources.camera import open_camera
    from device.pi.sources.imu import open_imu
    for bad in (lambda: open_camera("nope://x"), lambda: open_imu("i2c://1/0x01"),
                lambda: whole_number("k", 0, lo=1)):
        with pytest.raises(InputError):
            bad()


def test_one_line_names_the_file_of_an_io_error_without_errno():
    from device.pi.sources.camera import CameraError
    assert one_line(CameraError(2, "No such file or directory", "clip.avi")) == \
        "clip.avi: No such file or directory"
    assert one_line(InputError("k must be >= 1, got k=0")) == "k must be >= 1, got k=0"
