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


@pytest.mark.parametrize("target", ["pi;x@host", "p i@leg1", "pi@leg1;reboot", "pi@-leg1",
                                    "pi@leg_1", "pi@leg1.", "pi@", "@leg1", "$(id)@leg1",
                                    "pi@leg1..local", "pi@" + "a" * 64, "pi@[::1", "x@y@z"])
def test_target_user_and_host_must_be_names(target):
    with pytest.raises(DeployInputError, match="target"):
        _opts(target=target).check()


@pytest.mark.parametrize("target", ["pi@leg1", "leg1", "pi@leg-1.local", "pi@192.168.0.7",
                                    "ubuntu@::1", "pi@[fe80::1]", "_tacfoot@leg1", "pi.x@leg1"])
def test_good_targets_pass(target):
    _opts(target=target).check()


def test_service_user_must_be_a_user_name():
    with pytest.raises(DeployInputError, match="--service-user"):
        _opts(service_user="pi;x").check()


@pytest.mark.parametrize("field", ["camera", "imu", "serial", "python"])
def test_an_empty_runtime_source_is_refused_before_any_step(field, tmp_path, capsys):
    """An empty --camera/--imu/--serial (or a blank one in a robot file) was shipped:
    the runtime refused it on the leg, found only by the health check after the switch."""
    with pytest.raises(DeployInputError, match=f"--{field} must not be empty"):
        _opts(**{field: " "}).check()
    from host.cli import main
    robot = tmp_path / "robot.toml"
    robot.write_text(f'[[leg]]\ntarget = "pi@leg1"\n{field} = ""\n')
    if field != "python":                   # not a per-leg key
        assert main(["deploy", "--robot", str(robot), "--dry-run"]) == 2
        err = capsys.readouterr().err
        assert f"{robot}: leg 1 (pi@leg1): {field} must not be empty" in err, err
