"""host/extras.py: a command that needs an extra the install lacks says which, in one
line, exit 2 (issue 32 item 4). A missing module is simulated with
``sys.modules[name] = None``, which makes its import fail as if it were absent."""
from __future__ import annotations

import sys

import pytest

from host.cli import main
from host.extras import MissingExtra, missing_extra, need


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    return err


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    ds = tmp_path_factory.mktemp("ds") / "ds"
    assert main(["simulate", "minimal", "--out", str(ds)]) == 0
    return ds


def test_simulate_and_train_without_the_host_extra_name_it(dataset, tmp_path, capsys,
                                                            monkeypatch):
    capsys.readouterr()
    real_tqdm = need("tqdm")
    monkeypatch.setitem(sys.modules, "tqdm", None)
    assert main(["simulate", "minimal", "--out", str(tmp_path / "ds2")]) == 2
    assert _one_line(capsys) == ("host simulate: error: needs the host extra (module 'tqdm' "
                                 "is not installed): pip install 'tacfoot[host]'")
    assert main(["train", "--task", "surface", "--data", str(dataset),
                 "--out", str(tmp_path / "m")]) == 2
    err = _one_line(capsys)
    assert err.startswith("host train: error: needs the host extra (module ") \
        and err.endswith("pip install 'tacfoot[host]'")
    monkeypatch.setitem(sys.modules, "tqdm", real_tqdm)
    monkeypatch.setitem(sys.modules, "sklearn", None)
    for k in [k for k in sys.modules if k.startswith("sklearn.")]:
        monkeypatch.setitem(sys.modules, k, None)
    assert main(["train", "--task", "surface", "--model", "fnn", "--data", str(dataset),
                 "--out", str(tmp_path / "m2")]) == 2
    assert "host train: error: needs the host extra (module 'sklearn'" in _one_line(capsys)


def test_need_names_the_extra_and_lets_other_missing_modules_through(monkeypatch):
    monkeypatch.setitem(sys.modules, "mcap", None)
    with pytest.raises(MissingExtra, match=r"the viz extra .*pip install 'tacfoot\[viz\]'") \
            as caught:
        need("mcap")
    assert isinstance(caught.value, ImportError) and caught.value.extra == "viz"
    assert need("json") is sys.modules["json"]
    with pytest.raises(ModuleNotFoundError) as other:     # not an extra's module: a bug
        need("tacfoot_no_such_module")
    assert not isinstance(other.value, MissingExtra)
    assert missing_extra(other.value) is None
    assert missing_extra(ModuleNotFoundError("x", name="skl2onnx.common")).extra == "host"


def test_version_prints_the_installed_version(capsys):
    """``host --version`` (issue 32 item 5): the version of the installed metadata."""
    from importlib.metadata import version
    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"host (tacfoot) {version('tacfoot')}"


def test_pyproject_has_an_spdx_licence_the_license_file_and_urls():
    try:
        import tomllib
    except ImportError:                  # Python 3.10
        import tomli as tomllib
    from tests import REPO_ROOT as root
    proj = tomllib.loads((root / "pyproject.toml").read_text())["project"]
    assert proj["license"] == "MIT" and proj["license-files"] == ["LICENSE"]
    assert "MIT License" in (root / "LICENSE").read_text()
    assert proj["classifiers"] and set(proj["urls"]) >= {"Homepage", "Source", "Issues"}
