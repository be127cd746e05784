"""device/config.py: reading a TOML file, and the typed, range-checked fields of a table."""
from __future__ import annotations

import os

import pytest

from device.config import ConfigError, Fields, read_toml


def test_a_toml_file_is_read(tmp_path):
    (tmp_path / "a.toml").write_text('name = "café"\n[vision]\nblock = 11\n')
    assert read_toml(tmp_path / "a.toml") == {"name": "café", "vision": {"block": 11}}


@pytest.mark.parametrize("make, why", [
    (lambda p: None, r"a\.toml: file not found"),
    (lambda p: p.mkdir(), r"a\.toml: is a folder, not a TOML file"),
    (lambda p: p.write_bytes(b'name = "caf\xe9"\n'), r"a\.toml: not UTF-8 text \(byte 11\)"),
    (lambda p: p.write_text("name = \n"), r"a\.toml: not valid TOML"),
])
def test_every_file_that_is_not_toml_is_one_config_error_naming_it(tmp_path, make, why):
    make(tmp_path / "a.toml")
    with pytest.raises(ConfigError, match=why):
        read_toml(tmp_path / "a.toml")


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads any file")
def test_an_unreadable_file_is_a_config_error(tmp_path):
    (tmp_path / "a.toml").write_text("x = 1\n")
    (tmp_path / "a.toml").chmod(0)
    with pytest.raises(ConfigError, match=r"a\.toml: cannot read"):
        read_toml(tmp_path / "a.toml")


def test_fields_name_the_file_the_field_and_the_value():
    f = Fields({"gate_px": 1e308, "typo": 1}, "vision", "p.toml")
    with pytest.raises(ConfigError, match=r"p\.toml: vision\.gate_px must be <= 10, got 1e\+308"):
        f.number("gate_px", max=10)
    with pytest.raises(ConfigError, match=r"vision\.typo is not a known key"):
        f.done()
