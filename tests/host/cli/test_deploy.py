"""host deploy from the command line (host/cli/deploy.py): a signal during a deploy
to a robot takes every leg back to the release it had, prints a summary, exits
128 + the signal and leaves no ssh process behind; --status checks that the running
process is the release current names and that it passed its health check.

The legs are two PREFIXes on this machine reached through the stand-in ssh of
tests/host/deploy/local_ssh.py (no OpenSSH server needed), running the real runtime
on simulated hardware. The module's ``robot`` fixture deploys release r0 once and
builds the sdist once; each signal case deploys another release on top of it."""
from __future__ import annotations

import json
import os
import shutil
import signal
import sys
import time
from pathlib import Path

import pytest

from host.deploy.options import DeployOptions
from host.deploy.release import Deployer
from tests import REPO_ROOT
from tests.host.deploy.local_ssh import LocalSsh


class Robot:
    def __init__(self, root: Path, ssh: LocalSsh):
        self.root, self.ssh = root, ssh
        self.prefixes = [root / f"leg{i}" / "opt" / "tacfoot" for i in (1, 2)]
        self.config = root / "leg.toml"
        self.config.write_text((REPO_ROOT / "device" / "leg.toml").read_text())
        # one small real model: a leg refuses to start with none (--rules-only aside)
        self.models = root / "models"
        self.models.mkdir()
        shutil.copytree(REPO_ROOT / "models" / "pressure", self.models / "pressure")
        self.key = root / "key.pem"
        self.file = root / "robot.toml"
        self.file.write_text("".join(
            f'[[leg]]\ntarget = "pi@127.0.0.1:22{i}"\nprefix = "{p}"\n\n'
            for i, p in enumerate(self.prefixes)))

    def argv(self, *extra):
        return ["deploy", "--robot", str(self.file), "--json", "--python", sys.executable,
                "--service-manager", "none", "--system-site-packages", "--no-deps",
                "--config", str(self.config), "--models", str(self.models),
                "--camera", "sim://walk?realtime=1&fps=15", "--imu", "none",
                "--serial", "loop://", "--runtime-arg=--fps", "--runtime-arg=15",
                "--signing-key", str(self.key), "--health-timeout-s", "20", *extra]

    def pid(self, prefix) -> int | None:
        try:
            pid = int((prefix / "run" / "tacfoot.pid").read_text())
            os.kill(pid, 0)
            return pid
        except (OSError, ValueError):
            return None

    def running(self, prefix) -> str | None:
        pid = self.pid(prefix)
        if pid is None:
            return None
        env = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
        return next((kv[16:].decode() for kv in env if kv.startswith(b"TACFOOT_RELEASE=")),
                    None)

    def stop_all(self):
        for p in self.prefixes:
            ctl = p / "current" / "tacfootctl"
            if ctl.exists():
                os.system(f"{ctl} stop >/dev/null 2>&1")


def _main(capsys, argv):
    from host.cli import main
    rc = main(argv)
    out = capsys.readouterr()
    return rc, out.out, out.err


@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    if shutil.which("tar") is None:
        pytest.skip("tar not found")
    root = tmp_path_factory.mktemp("robot")
    ssh = LocalSsh(root / "ssh")
    mp = pytest.MonkeyPatch()
    mp.setenv("PATH", ssh.env()["PATH"])
    sdist = Deployer(DeployOptions(target="pi@a"), log=lambda m: None).build_sdist(
        root / "sdist")

    def prebuilt(self, out_dir):
        self.record("build", "local", "prebuilt sdist (test)")
        (out_dir / "dist").mkdir(parents=True, exist_ok=True)
        return Path(shutil.copy2(sdist, out_dir / "dist" / sdist.name))

    mp.setattr(Deployer, "build_sdist", prebuilt)
    (root / "r").mkdir()
    r = Robot(root / "r", ssh)
    try:
        yield r
    finally:
        r.stop_all()
        mp.undo()


def test_first_deploy_runs_on_both_legs_and_status_is_ok(robot, capsys):
    rc, out, err = _main(capsys, robot.argv("--release", "r0"))
    res = json.loads(out)
    assert rc == 0 and res["ok"], (out[-2000:], err[-2000:])
    for p in robot.prefixes:
        assert os.readlink(p / "current") == "releases/r0" and robot.running(p) == "r0"
        assert (p / "releases" / "r0" / ".healthy").is_file()
    assert robot.ssh.live() == [], "an ssh process outlived the deploy"
    rc, out, _ = _main(capsys, robot.argv("--status"))
    assert rc == 0 and json.loads(out)["ok"], out


PHASES = {"copy": "tar -xzf", "switch": "is incomplete", "health": "packets_sent"}

#: the copy's other landing points (each with a signal that trips as the copy starts):
#: "copied": once the Pi's tar has extracted everything, before its ssh exits;
#: "copy-outlived": the copy's ssh behaves as OpenSSH does when it is killed (its
#: remote tar is not ended and runs on, here as late as it could: after the next
#: command to that leg, the removal of the folder). Before the copy waited for its
#: ssh, "copy-outlived" left the release folder behind every time.
COPY_LANDINGS = {"copied": {"TRIP_AT": "end"}, "copy-outlived": {"TRIP_REMOTE": "stays"}}


#: every signal in the copy phase (2 s each); after the switch each case restarts the
#: runtime twice (about 15 s), so one case per signal there unless
#: TACFOOT_FULL_SIGNAL_MATRIX=1 asks for all nine
CASES = [(ph, sg) for ph in PHASES for sg in ("SIGTERM", "SIGHUP", "SIGINT")
         if os.environ.get("TACFOOT_FULL_SIGNAL_MATRIX") or ph == "copy"
         or (ph, sg) in {("switch", "SIGHUP"), ("health", "SIGTERM"), ("health", "SIGINT")}]
CASES[3:3] = [(ph, "SIGTERM") for ph in COPY_LANDINGS]


@pytest.mark.parametrize("phase, sig", CASES)
def test_a_signal_during_a_deploy_takes_every_leg_back(robot, capsys, monkeypatch, sig,
                                                       phase):
    assert all(robot.running(p) == "r0" for p in robot.prefixes), "needs the r0 deploy"
    robot.ssh.reset_trip()
    monkeypatch.setenv("TRIP_SIGNAL", sig)
    monkeypatch.setenv("TRIP_WHEN", PHASES.get(phase, PHASES["copy"]))
    for k, v in COPY_LANDINGS.get(phase, {}).items():
        monkeypatch.setenv(k, v)
    rel = f"r-{sig}-{phase}"
    t0 = time.monotonic()
    rc, out, err = _main(capsys, robot.argv("--release", rel))
    res = json.loads(out)
    assert (robot.ssh.folder / "tripped").exists(), "the signal was never sent"
    robot.ssh.held_commands()       # what a killed copy left running on a leg has run
    assert rc == 128 + getattr(signal, sig), (rc, out[-2000:])
    assert res["interrupted"] == sig and not res["ok"]
    assert f"{sig}: stopping" in err and "Traceback" not in err
    assert f"stopped by {sig}" in res["error"]
    for p, leg in zip(robot.prefixes, res["legs"]):
        assert os.readlink(p / "current") == "releases/r0", leg
        assert robot.running(p) == "r0", leg          # the old release's process runs
        if phase.startswith("cop"):
            assert not (p / "releases" / rel).exists() and not leg["rolled_back"]
        else:
            assert leg["rolled_back"] and leg["rollback"]["ok"], leg
    assert res["rolled_back"] is not phase.startswith("cop")
    # no ssh left: the masters were closed, no client runs on
    assert robot.ssh.masters() and robot.ssh.live() == []
    # the old handlers are back
    assert signal.getsignal(getattr(signal, sig)) is not None
    assert time.monotonic() - t0 < 40


def test_status_names_a_process_of_another_release_and_an_unchecked_release(robot, capsys):
    assert all(robot.running(p) == "r0" for p in robot.prefixes), "needs the r0 deploy"
    p = robot.prefixes[1]
    # current switched to another complete release, the r0 process left running
    shutil.copytree(p / "releases" / "r0", p / "releases" / "rX", symlinks=True)
    (p / "releases" / "rX" / ".healthy").unlink()
    os.symlink("releases/rX", p / ".tmp-link")
    os.replace(p / ".tmp-link", p / "current")
    try:
        rc, out, _ = _main(capsys, robot.argv("--status"))
        res = json.loads(out)
        assert rc == 1 and not res["ok"], out
        problems = " ".join(res["legs"][1]["problems"])
        assert "is release r0, not rX" in problems and "rX never passed its health" in problems
        assert res["legs"][0].get("problems") == []
        rc, text, _ = _main(capsys, [a for a in robot.argv("--status") if a != "--json"])
        assert rc == 1 and "NOT OK" in text and "never passed its health check" in text
    finally:
        os.symlink("releases/r0", p / ".tmp-link")
        os.replace(p / ".tmp-link", p / "current")


def test_status_names_an_unreachable_leg(robot, capsys, tmp_path):
    f = tmp_path / "robot.toml"
    f.write_text(robot.file.read_text() + '[[leg]]\ntarget = "pi@127.0.0.1:1"\n')
    argv = robot.argv("--status")
    argv[argv.index("--robot") + 1] = str(f)
    rc, out, _ = _main(capsys, argv)
    res = json.loads(out)
    assert rc == 1 and res["unreachable"] == ["pi@127.0.0.1:1"]
    rc, text, _ = _main(capsys, [a for a in argv if a != "--json"])
    assert rc == 1 and "pi@127.0.0.1:1: UNREACHABLE" in text, text
    assert "DIFFERENT" not in text and "release None" not in text
    assert "the 2 reached run the same release" in text


def test_status_refuses_a_dry_run_without_connecting(robot, capsys):
    rc, out, err = _main(capsys, robot.argv("--status", "--dry-run"))
    assert rc == 2 and "no --dry-run" in err and len(err.strip().splitlines()) == 1
    assert robot.ssh.live() == []


def _leg1_argv(robot, *extra):
    argv = robot.argv(*extra)
    i = argv.index("--robot")
    argv[i:i + 2] = ["pi@127.0.0.1:220", "--prefix", str(robot.prefixes[0])]
    return argv


#: a text in the first remote command of each phase of a rollback
ROLLBACK_PHASES = {"switch": "prev=$(readlink previous)", "service": "tacfootctl restart",
                   "health": "packets_sent"}
ROLLBACK_CASES = [(ph, sg) for ph in ROLLBACK_PHASES for sg in ("SIGTERM", "SIGHUP", "SIGINT")
                  if os.environ.get("TACFOOT_FULL_SIGNAL_MATRIX")
                  or (ph, sg) in {("switch", "SIGTERM"), ("service", "SIGHUP"),
                                  ("health", "SIGINT")}]


@pytest.fixture(scope="module")
def leg1_on_r1(robot):
    """Leg 1 on release r1 with r0 as previous (what --rollback goes back to)."""
    from host.cli import main
    p = robot.prefixes[0]
    if os.readlink(p / "current") != "releases/r1":
        with pytest.MonkeyPatch.context() as mp:
            mp.delenv("TRIP_SIGNAL", raising=False)
            assert main(_leg1_argv(robot, "--release", "r1")) == 0
    assert robot.running(p) == "r1" and os.readlink(p / "previous") == "releases/r0"
    return p


@pytest.mark.parametrize("phase, sig", ROLLBACK_CASES)
def test_a_signal_during_a_rollback_puts_the_links_and_the_process_back(
        robot, leg1_on_r1, capsys, monkeypatch, phase, sig):
    """--rollback swaps current and previous; a signal in its switch, service or
    health step puts both links back and restarts the release that ran, prints a
    summary, closes ssh and exits 128 + N (before: the links stayed swapped with
    the old process running, or the service never restarted)."""
    p = leg1_on_r1
    capsys.readouterr()
    robot.ssh.reset_trip()
    monkeypatch.setenv("TRIP_SIGNAL", sig)
    monkeypatch.setenv("TRIP_WHEN", ROLLBACK_PHASES[phase])
    rc, out, err = _main(capsys, _leg1_argv(robot, "--rollback"))
    assert (robot.ssh.folder / "tripped").exists(), "the signal was never sent"
    res = json.loads(out)
    assert rc == 128 + getattr(signal, sig), (rc, out[-2000:], err[-2000:])
    assert res["interrupted"] == sig and not res["ok"] and "Traceback" not in err
    assert f"stopped by {sig}" in res["error"]
    assert os.readlink(p / "current") == "releases/r1"
    assert os.readlink(p / "previous") == "releases/r0"
    assert robot.running(p) == "r1"
    assert res["undone"]["ok"] and res["undone"]["to"] == "releases/r1", res["undone"]
    assert robot.ssh.live() == []
    from host.deploy.release import summary_text
    assert "rollback undone, back on releases/r1 (ok)" in summary_text(res)



def test_a_release_name_already_on_the_leg_is_refused_and_that_release_kept(
        robot, leg1_on_r1, capsys, monkeypatch):
    """--release naming a release the leg already has (here previous, r0) fails at
    prepare and leaves that release whole: the deploy removes only a folder it made
    (before: the failed deploy's clean-up deleted previous)."""
    p = leg1_on_r1
    monkeypatch.delenv("TRIP_SIGNAL", raising=False)
    before = sorted(x.name for x in (p / "releases" / "r0").iterdir())
    rc, out, err = _main(capsys, _leg1_argv(robot, "--release", "r0"))
    res = json.loads(out)
    assert rc == 1 and "release r0 already exists" in res["error"], (out[-2000:], err)
    assert "discard" not in [s["step"] for s in res["steps"]]
    assert sorted(x.name for x in (p / "releases" / "r0").iterdir()) == before
    assert os.readlink(p / "previous") == "releases/r0"
    assert os.readlink(p / "current") == "releases/r1" and robot.running(p) == "r1"
