"""host/deploy/options.py: bad deploy options are refused with the field named."""
from __future__ import annotations

import pytest

from host.deploy.options import DeployInputError, DeployOptions


def _opts(**kw) -> DeployOptions:
    base = dict(target="pi@leg1", camera="sim://walk", imu="sim://walk", serial="loop://")
    base.update(kw)
    return DeployOptions(**base)


def test_control_characters_are_refused():
    for kw in (dict(camera="sim://walk\nExecStartPre=/bin/rm"), dict(env=["A=1\n[Install]"]),
               dict(runtime_args=["--x\ty"]), dict(imu="i2c://1/0x68\x85")):
        with pytest.raises(DeployInputError, match="control characters"):
            _opts(**kw).check()


def test_bad_options_name_the_field():
    for kw, field in ((dict(port=0), "--port"), (dict(prefix="opt/x"), "--prefix"),
                      (dict(prefix="/"), "--prefix"), (dict(env=["NOEQUALS"]), "--env"),
                      (dict(service_manager="upstart"), "--service-manager"),
                      (dict(target="-oProxyCommand=x"), "target"), (dict(keep=1), "--keep"),
                      (dict(models="/nonexistent/models"), "--models"),
                      (dict(release="../x"), "--release"), (dict(release="a'b"), "--release"),
                      (dict(health_timeout_s=float("nan")), "--health-timeout-s")):
        with pytest.raises(DeployInputError, match=field.replace("-", r"\-")):
            _opts(**kw).check()


def test_cli_bad_input_exits_2(capsys):
    from host.cli import main
    assert main(["deploy", "pi@leg1", "--port", "70000", "--dry-run"]) == 2
    assert "--port must be 1..65535, got 70000" in capsys.readouterr().err
