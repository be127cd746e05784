"""device.shipped: the shipped files (default models, trial files, Foxglove layout,
the source files host deploy rebuilds from) are found from a checkout and from an
installed wheel, which carries them inside the package; the wheel's runtime finds
its models from any folder."""
from __future__ import annotations

import json
import subprocess
import sys
import zipfile

import pytest

from device import shipped
from device.pi.runtime.load import default_models_dir
from tests import REPO_ROOT
from tests.wheel import build_wheel, clean_env, unpack


def test_a_checkout_finds_its_own_files():
    assert shipped.is_checkout()
    assert shipped.models_dir() == REPO_ROOT / "models" == default_models_dir()
    assert shipped.trials_dir() == REPO_ROOT / "trials"
    assert shipped.layout_file() == REPO_ROOT / "docs" / "foxglove-layout.json"
    for name, rel in shipped.SHIPPED.items():
        assert shipped.shipped(name) == REPO_ROOT / rel and (REPO_ROOT / rel).exists(), name
    with pytest.raises(KeyError, match="'nope' is not a shipped file"):
        shipped.shipped("nope")


def test_the_packaged_copy_wins_and_an_install_never_looks_above_the_package(tmp_path,
                                                                             monkeypatch):
    data = tmp_path / "site" / "device" / "data"
    (data / "models").mkdir(parents=True)
    monkeypatch.setattr(shipped, "packaged_dir", lambda: data)
    assert shipped.models_dir() == data / "models"
    # no copy: a checkout falls back to its own file ...
    assert shipped.layout_file() == REPO_ROOT / "docs" / "foxglove-layout.json"
    # ... an install (no pyproject.toml above the package) names the missing copy
    monkeypatch.setattr(shipped, "CHECKOUT", tmp_path / "site")
    assert not shipped.is_checkout()
    assert shipped.trials_dir() == data / "trials"


def test_setup_py_copies_what_device_shipped_names():
    import importlib.util
    spec = importlib.util.spec_from_file_location("tacfoot_setup", REPO_ROOT / "setup.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod.shipped_files() == (shipped.PACKAGED, shipped.SHIPPED)


@pytest.fixture(scope="module")
def wheel(tmp_path_factory):
    return build_wheel(tmp_path_factory.mktemp("wheel"))


def test_the_wheel_carries_the_models_layout_profiles_scenes_trials_and_licence(wheel):
    with zipfile.ZipFile(wheel) as z:
        names = set(z.namelist())
    data = f"device/{shipped.PACKAGED}"
    want = {f"{data}/foxglove-layout.json", f"{data}/source/LICENSE",
            f"{data}/source/setup.py", f"{data}/source/pyproject.toml"}
    models = sorted(p for p in (REPO_ROOT / "models").iterdir() if p.is_dir())
    assert {"surface", "texture", "slip", "pressure", "fused"} <= {p.name for p in models}
    for m in models:
        assert (m / "manifest.json").is_file(), m
        want |= {f"{data}/models/{m.name}/{f.name}" for f in m.iterdir()
                 if f.name.startswith("manifest") or f.suffix == ".onnx"}
    for folder, pattern in ((REPO_ROOT / "trials", f"{data}/trials/{{}}"),
                            (REPO_ROOT / "device" / "profiles", "device/profiles/{}"),
                            (REPO_ROOT / "device" / "sim" / "scenes", "device/sim/scenes/{}")):
        files = sorted(folder.glob("*.toml"))
        assert files, folder
        want |= {pattern.format(f.name) for f in files}
    assert want <= names, sorted(want - names)
    assert any(n.endswith(".dist-info/licenses/LICENSE") for n in names)
    with zipfile.ZipFile(wheel) as z:
        assert z.read(f"{data}/foxglove-layout.json") == \
            (REPO_ROOT / "docs" / "foxglove-layout.json").read_bytes()


def test_an_installed_wheel_finds_its_models_from_any_folder(wheel, tmp_path):
    site = unpack(wheel, tmp_path / "site")
    empty = tmp_path / "empty"
    empty.mkdir()
    env = clean_env(PYTHONPATH=str(site))
    run = subprocess.run([sys.executable, "-m", "device.shipped"], cwd=empty, env=env,
                         capture_output=True, text=True, timeout=60, check=True)
    where = json.loads(run.stdout)
    assert where["checkout"] is False
    assert where["models"] == str(site / "device" / shipped.PACKAGED / "models")
    run = subprocess.run([sys.executable, "-m", "device.pi", "run", "--camera", "sim://walk",
                          "--imu", "sim://walk", "--serial", "loop://", "--frames", "10",
                          "--json"], cwd=empty, env=env, capture_output=True, text=True,
                         timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]
    assert set(json.loads(run.stdout)["models"]) >= {"surface", "slip", "pressure"}
    assert list(empty.iterdir()) == []
