"""host deploy to a whole robot (host/deploy/robot.py): three legs, each a real
OpenSSH server on loopback on its own port with its own PREFIX. One release goes to
every leg or to none: a leg that fails before the switch keeps every leg where it
was, and a leg that fails its health check takes every leg back.

The tests sharing the module's ``legs`` fixture are one story, in file order:
deploy r1 to all three, --status, r2 with a broken leg 2 (all back to r1), r3 with
leg 3 refusing the release before the switch (nothing switched)."""
from __future__ import annotations

import json

import pytest

from device.config import tomllib
from host.deploy.options import DeployInputError, DeployOptions
from host.deploy.robot import check_legs, read_robot
from tests.host.deploy.sshd_fixture import Pi, SshServer, missing_reason

needs_sshd = pytest.mark.skipif(missing_reason() is not None, reason=str(missing_reason()))
N_LEGS = 3


@pytest.fixture(scope="module")
def legs(tmp_path_factory):
    if missing_reason():
        pytest.skip(missing_reason())
    root = tmp_path_factory.mktemp("robot")
    pis = []
    try:
        for i in range(N_LEGS):
            srv = SshServer(root / f"leg{i + 1}")
            srv.start()
            pis.append(Pi(srv, root / f"leg{i + 1}"))
        yield pis
    finally:
        for p in pis:
            p.stop_all()
            p.srv.stop()


def _robot_file(legs, path, configs=None) -> str:
    text = ""
    for i, p in enumerate(legs):
        cfg = (configs or {}).get(i, p.config)
        text += (f'[[leg]]\nname = "leg{i + 1}"\ntarget = "{p.srv.target}:{p.srv.port}"\n'
                 f'config = "{cfg}"\nprefix = "{p.prefix}"\nidentity = "{p.srv.identity}"\n\n')
    path.write_text(text)
    return str(path)


def _argv(legs, robot, *extra):
    o = legs[0].opts()
    argv = ["deploy", "--robot", robot, "--json", "--python", o.python,
            "--service-manager", "none", "--system-site-packages", "--no-deps",
            "--camera", o.camera, "--imu", o.imu, "--serial", o.serial,
            "--runtime-arg=--fps", "--runtime-arg=15", "--signing-key", o.signing_key]
    for s in o.ssh_options:
        argv += ["--ssh-option", s]
    return argv + list(extra)


def _run(capsys, argv):
    from host.cli import main
    rc = main(argv)
    out = capsys.readouterr()
    return rc, json.loads(out.out), out.err


@needs_sshd
def test_robot_file_deploys_one_release_to_every_leg(legs, capsys, tmp_path):
    robot = _robot_file(legs, tmp_path / "robot.toml")
    rc, res, err = _run(capsys, _argv(legs, robot, "--release", "r1", "--env", "TAG=r1",
                                      "--health-timeout-s", "30"))
    assert rc == 0 and res["ok"], (json.dumps(res)[-3000:], err[-3000:])
    # the sdist was built once, for every leg
    assert sum(1 for l in res["legs"] for s in l["steps"] if s["step"] == "build") == 1
    for p, leg in zip(legs, res["legs"]):
        assert leg["ok"] and leg["health"]["ok"], leg.get("error")
        assert p.link("current") == "releases/r1"
        pid = p.pid()
        assert pid == leg["health"]["pid"] and p.tag(pid) == "r1" and p.packets_flow(pid)
        # each leg got its own config, carrying the host's public key
        cfg = tomllib.loads((p.prefix / "current" / "config" / "leg.toml").read_text())
        assert cfg["signing"]["public_key"] and cfg["signing"]["allow_unsigned"] is False
    # every leg's log line names its leg
    assert all(f"[{p.srv.target}:{p.srv.port}] [deploy] switch" in err for p in legs)


@needs_sshd
def test_status_shows_each_legs_release_and_health(legs, capsys, tmp_path):
    assert all(p.link("current") == "releases/r1" for p in legs), "needs the r1 deploy"
    robot = _robot_file(legs, tmp_path / "robot.toml")
    rc, res, _ = _run(capsys, _argv(legs, robot, "--status"))
    assert rc == 0 and res["ok"] and res["same_release"], res
    assert [l["release"] for l in res["legs"]] == ["r1"] * N_LEGS
    assert all(l["health"]["ok"] and l["health"]["packets_per_s"] > 0 for l in res["legs"])
    assert all(l["signed"] is True for l in res["legs"]), res
    # without --json: one line per leg
    from host.cli import main
    argv = [a for a in _argv(legs, robot, "--status") if a != "--json"]
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert text.count("release r1, signed by this host healthy") == N_LEGS, text
    assert "same release" in text
    # a release.json altered on one leg no longer carries this host's signature
    rj = legs[1].prefix / "current" / "release.json"
    rj.write_text(rj.read_text().replace('"r1"', '"r1 "', 1))
    rc, res, _ = _run(capsys, _argv(legs, robot, "--status"))
    assert [l["signed"] for l in res["legs"]] == [True, False, True]


@needs_sshd
def test_a_leg_failing_its_health_check_takes_every_leg_back(legs, capsys, tmp_path):
    before = [p.pid() for p in legs]
    assert all(before) and all(p.link("current") == "releases/r1" for p in legs)
    broken = tmp_path / "broken.toml"
    broken.write_text(legs[1].config.read_text() + "\n[broken_section]\nbroken = true\n")
    robot = _robot_file(legs, tmp_path / "robot.toml", configs={1: broken})
    rc, res, err = _run(capsys, _argv(legs, robot, "--release", "r2", "--env", "TAG=r2",
                                      "--health-timeout-s", "8"))
    assert rc == 1 and not res["ok"] and res["rolled_back"], json.dumps(res)[-2000:]
    assert legs[1].srv.target in res["error"] and "went back" in res["error"]
    assert "broken_section" in res["legs"][1]["error"]
    for p, leg in zip(legs, res["legs"]):
        assert leg["rolled_back"] and leg["rollback"]["ok"], leg
        assert p.link("current") == "releases/r1"
        pid = p.pid()
        assert pid and p.tag(pid) == "r1" and p.packets_flow(pid)
    # the healthy legs did run r2 before they went back
    assert res["legs"][0]["health"]["ok"] and res["legs"][2]["health"]["ok"]


@needs_sshd
def test_a_leg_failing_before_the_switch_switches_no_leg(legs, capsys, tmp_path):
    before = [p.pid() for p in legs]
    assert all(before) and all(p.link("current") == "releases/r1" for p in legs)
    # leg 3 already holds a release named r3: it refuses it before anything switches
    (legs[2].prefix / "releases" / "r3").mkdir()
    (legs[2].prefix / "releases" / "r3" / ".complete").write_text("x")
    robot = _robot_file(legs, tmp_path / "robot.toml")
    rc, res, _ = _run(capsys, _argv(legs, robot, "--release", "r3", "--env", "TAG=r3"))
    assert rc == 1 and not res["ok"] and not res["rolled_back"], res
    assert "already exists" in res["error"] and "no leg was switched" in res["error"]
    for p, leg in zip(legs, res["legs"]):
        assert "switch" not in [s["step"] for s in leg["steps"]]
        assert p.link("current") == "releases/r1" and p.pid() in before
    # the legs that had copied r3 removed it again
    assert not (legs[0].prefix / "releases" / "r3").exists()
    assert not (legs[1].prefix / "releases" / "r3").exists()


@needs_sshd
def test_targets_on_the_command_line_are_legs_too(legs, capsys):
    """Two legs as targets: one is unreachable, so the other is not touched."""
    from host.cli import main
    p = legs[0]
    pid = p.pid()
    assert pid and p.link("current") == "releases/r1"
    o = p.opts()
    argv = ["deploy", f"{p.srv.target}:{p.srv.port}", f"{p.srv.target}:1", "--json",
            "--identity", p.srv.identity, "--prefix", str(p.prefix), "--python", o.python,
            "--service-manager", "none", "--signing-key", o.signing_key, "--release", "r4"]
    for s in o.ssh_options:
        argv += ["--ssh-option", s]
    assert main(argv) == 1
    res = json.loads(capsys.readouterr().out)
    assert "probe failed" in res["error"] and "no leg was switched" in res["error"]
    assert [l["target"] for l in res["legs"]] == [argv[1], argv[2]]
    assert p.link("current") == "releases/r1" and p.pid() == pid
    assert not (p.prefix / "releases" / "r4").exists()


def test_a_dry_run_plans_every_leg_and_touches_nothing(capsys, tmp_path):
    from host.cli import main
    key = tmp_path / "key.pem"
    argv = ["deploy", "pi@leg1", "pi@leg2:2222", "--dry-run", "--prefix", str(tmp_path / "p"),
            "--signing-key", str(key), "--service-manager", "none"]
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "# leg pi@leg1" in text and "# leg pi@leg2:2222" in text
    assert text.count("# switch (remote)") == 2 and text.count("# build (local)") == 1
    assert not (tmp_path / "p").exists() and not key.exists()


def test_robot_file_is_read_and_checked(tmp_path):
    base = DeployOptions(target="robot", camera="sim://walk")
    (tmp_path / "leg1.toml").write_text("")
    f = tmp_path / "robot.toml"
    f.write_text('[[leg]]\ntarget = "pi@leg1"\nconfig = "leg1.toml"\n'
                 '[[leg]]\ntarget = "pi@leg2:2222"\nname = "rear left"\n')
    legs = read_robot(f, base)
    assert [(o.target, o.config, o.ssh_port) for o in legs] == [
        ("pi@leg1", str(tmp_path / "leg1.toml"), None), ("pi@leg2:2222", None, 2222)]
    assert legs[0].camera == "sim://walk"
    check_legs(legs)
    for text, match in (('[[leg]]\nconfig = "x"\n', "lacks target"),
                        ('[[leg]]\ntarget = "pi@a"\nfps = 3\n', "unknown key 'fps'"),
                        ('[[leg]]\ntarget = "pi@a"\nport = "22"\n', "port must be a whole number"),
                        ('legs = 3\n', "unknown key 'legs'"), ("", "needs one"),
                        ("[[leg\n", "not valid TOML")):
        f.write_text(text)
        with pytest.raises(DeployInputError, match=match):
            read_robot(f, base)
    f.write_text('[[leg]]\ntarget = "pi;x@a"\n')
    with pytest.raises(DeployInputError, match="target must be"):
        check_legs(read_robot(f, base))
    with pytest.raises(DeployInputError, match="same install"):
        check_legs([DeployOptions(target="pi@a"), DeployOptions(target="pi@a:22")])


def test_cli_refuses_bad_leg_lists(capsys, tmp_path):
    from host.cli import main
    assert main(["deploy", "--dry-run"]) == 2
    assert "name the Pi" in capsys.readouterr().err
    assert main(["deploy", "pi@a", "--robot", str(tmp_path / "r.toml")]) == 2
    assert "not both" in capsys.readouterr().err
    assert main(["deploy", "pi@a", "pi@b", "--rollback"]) == 2
    assert "--rollback takes one target" in capsys.readouterr().err


def test_a_robot_file_error_names_the_file_and_the_field(tmp_path):
    """A bad value in a [[leg]] is named by the file, the leg and its key, not as if it
    were a command-line flag; a bad flag given for every leg still names the flag."""
    f = tmp_path / "robot.toml"
    f.write_text('[[leg]]\ntarget = "pi@a"\n[[leg]]\ntarget = "pi@b"\ncamera = "x\\ny"\n')
    with pytest.raises(DeployInputError) as exc:
        read_robot(f, DeployOptions(target="robot"))
    msg = str(exc.value)
    assert msg.startswith(f"{f}: leg 2 (pi@b): camera must not hold control") and "--" not in msg
    f.write_text('[[leg]]\ntarget = "pi@a"\nmodels = "nope"\n')
    with pytest.raises(DeployInputError, match=r"leg 1 \(pi@a\): models: .*nope not found"):
        read_robot(f, DeployOptions(target="robot"))
    f.write_text('[[leg]]\ntarget = "pi@a"\n')
    with pytest.raises(DeployInputError, match="^--imu must not"):
        read_robot(f, DeployOptions(target="robot", imu="a\tb"))
