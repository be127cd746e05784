"""host deploy (host/deploy/release.py) against a real OpenSSH server on loopback.

The deploy tests start sshd (tests/host/deploy/sshd_fixture.py) and deploy into a temporary
PREFIX with --service-manager none (tacfootctl + pid file), a venv seeded from
this interpreter (--system-site-packages --no-deps), and the real runtime on
simulated hardware (sim://walk, loop://). The systemd path runs against a stand-in
systemctl; the rendered unit is checked in tests/host/deploy/test_scripts.py.

The tests that share the module's ``pi`` fixture are one story, in file order:
deploy r1, deploy r2, a broken r3 rolled back, a killed copy, a failing prepare,
--rollback to r1. Each says which earlier step it needs when run alone.
"""
from __future__ import annotations
from tests import REPO_ROOT

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.host.deploy.sshd_fixture import Pi, SshServer, missing_reason  # noqa: E402
from tests.wheel import clean_env  # noqa: E402

from host.deploy.options import DeployError, project_version  # noqa: E402
from host.deploy.release import Deployer, run  # noqa: E402

REPO = REPO_ROOT

# -- against a real sshd --------------------------------------------------------------

needs_sshd = pytest.mark.skipif(missing_reason() is not None, reason=str(missing_reason()))

@pytest.fixture(scope="module")
def pi(tmp_path_factory):
    if missing_reason():
        pytest.skip(missing_reason())
    root = tmp_path_factory.mktemp("pi")
    srv = SshServer(root)
    srv.start()
    p = Pi(srv, root)
    yield p
    p.stop_all()
    srv.stop()


def _quiet(msg):
    pass


@needs_sshd
def test_dry_run_touches_nothing(pi, capsys):
    from host.cli import main
    o = pi.opts()
    argv = ["deploy", o.target, "--dry-run", "--json", "--port", str(o.port), "--identity",
            o.identity, "--prefix", str(pi.prefix), "--python", o.python,
            "--service-manager", "systemd", "--config", str(pi.config),
            "--signing-key", o.signing_key]
    assert main(argv) == 0
    res = json.loads(capsys.readouterr().out)
    names = [s["step"] for s in res["steps"]]
    assert names[:3] == ["probe", "build", "stage"]
    assert {"prepare", "copy", "install", "switch", "service", "health"} <= set(names)
    assert any("systemctl restart tacfoot" in s["command"] for s in res["steps"])
    assert not any("rc" in s for s in res["steps"]), "a dry run ran a step"
    assert not pi.prefix.exists()
    # a port nobody listens on: a dry run never connects, so it still plans
    argv[argv.index("--port") + 1] = "1"
    assert main(argv) == 0
    assert not pi.prefix.exists()


@needs_sshd
def test_first_deploy_runs_and_packets_flow(pi, capsys):
    from host.cli import main
    o = pi.opts()
    argv = ["deploy", o.target, "--json", "--port", str(o.port), "--identity", o.identity,
            "--prefix", str(pi.prefix), "--python", o.python, "--service-manager", "none",
            "--system-site-packages", "--no-deps", "--config", str(pi.config),
            "--camera", o.camera, "--imu", o.imu, "--serial", o.serial,
            "--health-timeout-s", "20", "--release", "r1", "--env", "TAG=r1",
            "--runtime-arg=--fps", "--runtime-arg=15", "--signing-key", o.signing_key]
    for s in o.ssh_options:
        argv += ["--ssh-option", s]
    rc = main(argv)
    out = capsys.readouterr()
    res = json.loads(out.out)
    assert rc == 0 and res["ok"], (json.dumps(res)[-3000:], out.err[-3000:])
    assert res["health"]["ok"] and res["health"]["packets_per_s"] > 0
    assert res["release"] == "r1" and pi.link("current") == "releases/r1"
    assert pi.link("previous") is None
    assert (pi.prefix / "releases" / "r1" / ".complete").is_file()
    pid = pi.pid()
    assert pid == res["health"]["pid"] and pi.tag(pid) == "r1"
    assert pi.packets_flow(pid)
    # every remote step was logged with its command
    assert "[deploy] install (remote)" in out.err and "[deploy] switch (remote)" in out.err
    # the venv runs the installed copy of the code, not this checkout
    r = subprocess.run([str(pi.prefix / "current" / "venv" / "bin" / "python"), "-c",
                        "import device.pi.runtime.sdnotify as m; print(m.__file__)"],
                       capture_output=True, text=True, cwd=pi.root, env=clean_env())
    assert r.stdout.startswith(str(pi.prefix / "current" / "venv" / "lib")), r.stdout + r.stderr
    assert str(REPO) not in r.stdout
    # pip compiled the frame core on the leg, into the release's venv (listed in its RECORD)
    if shutil.which("cc"):
        r = subprocess.run([str(pi.prefix / "current" / "venv" / "bin" / "python"), "-m",
                            "device.pi.vision.native", "status"],
                           capture_output=True, text=True, cwd=pi.root,
                           env={k: v for k, v in clean_env().items()
                                if not k.startswith("TACFOOT_NATIVE")})
        assert r.returncode == 0, r.stdout + r.stderr
        lib = Path(r.stdout.split("compiled (", 1)[1].rsplit(")", 1)[0]).resolve()
        assert lib.is_relative_to((pi.prefix / "releases" / "r1" / "venv").resolve()), r.stdout
        record, = (pi.prefix / "releases" / "r1" / "venv").glob(
            "lib/python*/site-packages/tacfoot-*.dist-info/RECORD")
        assert f"device/pi/vision/{lib.name}," in record.read_text()
    # the release ships the source distribution (a wheel built here would carry this
    # machine's library), and the install step no longer runs a separate build
    assert sorted(p.name for p in (pi.prefix / "releases" / "r1").glob("tacfoot-*")) == [
        f"tacfoot-{project_version()}.tar.gz"]
    install = next(s for s in res["steps"] if s["step"] == "install")
    assert "./tacfoot-*.tar.gz" in install["command"]
    assert "native build" not in install["command"]


@needs_sshd
def test_the_release_is_signed_and_the_leg_checks_it(pi):
    from device.config import tomllib
    from device.pi.models.signature import check_manifest
    from device.pi.runtime.config import load_leg_config
    from device.pi.runtime.load import load_models
    from host.deploy.signing import SigningKey
    rel = pi.prefix / "releases" / "r1"
    assert (rel / "release.json").is_file(), "needs the first deploy"
    assert os.stat(pi.key_path).st_mode & 0o777 == 0o600      # made on first use
    key = SigningKey.load(pi.key_path, create=False)
    key.verify_file(rel / "release.json")
    doc = json.loads((rel / "release.json").read_text())
    assert doc["signed_by"] == key.key_id and doc["files"]["config/leg.toml"]
    cfg = tomllib.loads((rel / "config" / "leg.toml").read_text())
    assert cfg["signing"] == {"public_key": key.public_key, "allow_unsigned": False}
    manifests = sorted((rel / "models").glob("*/manifest*.json"))
    assert manifests and all(check_manifest(m, key.public_key, False) for m in manifests)
    # the shipped config loads the shipped models only because they are signed
    leg = load_leg_config(rel / "config" / "leg.toml")
    m = load_models(rel / "models", "int8", 133, leg)
    assert "surface" in m.loaded
    # the release fused its per-frame models, and signed the graph with them
    assert rel / "models" / "fused" / "manifest.json" in manifests
    assert m.fused is not None and set(m.fused.tasks) == set(m.loaded) - {"localiser-roboskin"}


@needs_sshd
def test_second_deploy_keeps_the_first_as_previous(pi):
    old_pid = pi.pid()
    assert old_pid, "needs the first deploy"
    res = run(pi.opts(release="r2", env=["TAG=r2"]), log=_quiet)
    assert res["ok"], res
    assert pi.link("current") == "releases/r2" and pi.link("previous") == "releases/r1"
    pid = pi.pid()
    assert pid != old_pid and pi.tag(pid) == "r2" and pi.packets_flow(pid)
    assert not Path(f"/proc/{old_pid}").exists() or b"Z" in Path(
        f"/proc/{old_pid}/stat").read_bytes().split(b") ")[1][:1]


@needs_sshd
def test_failed_health_check_rolls_back(pi, tmp_path):
    assert pi.link("current") == "releases/r2", "needs the second deploy"
    broken = tmp_path / "leg.toml"
    broken.write_text(pi.config.read_text() + "\n[broken_section]\nbroken = true\n")
    res = run(pi.opts(release="r3", env=["TAG=r3"], config=str(broken),
                         health_timeout_s=6.0), log=_quiet)
    assert not res["ok"] and res["rolled_back"], res
    assert "health check failed" in res["error"]
    # the runtime's own complaint about the config comes back with it
    assert "broken_section" in res["error"] and res["log_tail"]
    assert res["rollback"]["ok"] and res["rollback"]["to"] == "releases/r2"
    assert pi.link("current") == "releases/r2" and pi.link("previous") == "releases/r1"
    assert (pi.prefix / "releases" / "r3" / ".failed").is_file()
    pid = pi.pid()
    assert pid and pi.tag(pid) == "r2" and pi.packets_flow(pid)


@needs_sshd
def test_killed_copy_leaves_the_old_release_running(pi):
    pid = pi.pid()
    assert pi.link("current") == "releases/r2" and pid
    d = Deployer(pi.opts(release="r4", env=["TAG=r4"]), log=_quiet)
    killed = []

    def kill_mid_copy(proc, sent):
        if not killed:
            killed.append(sent)
            proc.kill()

    d.copy_hook = kill_mid_copy
    with pytest.raises(DeployError, match="step copy failed"):
        d.deploy()
    assert killed
    steps = [s["step"] for s in d.steps]
    # the half-copied release is discarded: nothing was switched, nothing is left
    assert steps[-2:] == ["copy", "discard"] and "switch" not in steps, steps
    assert pi.link("current") == "releases/r2" and pi.pid() == pid and pi.packets_flow(pid)
    assert not (pi.prefix / "releases" / "r4").exists()


class _ChangedInTransit(Deployer):
    """Changes a file of the staged release after release.json was written."""

    def stage(self, wheel, out_dir):
        st = super().stage(wheel, out_dir)
        (st / "tacfootctl").write_text((st / "tacfootctl").read_text() + "# changed\n")
        return st


class _SignedByAnother(Deployer):
    """Signs release.json with another key than the one the config names."""

    def stage(self, wheel, out_dir):
        from host.deploy.signing import SigningKey
        st = super().stage(wheel, out_dir)
        SigningKey.load(out_dir / "other.pem").sign_file(st / "release.json")
        return st


@needs_sshd
def test_the_pi_installs_only_a_release_that_matches_its_signed_list(pi):
    from host.deploy.release import load_key
    pid = pi.pid()
    assert pi.link("current") == "releases/r2" and pid, "needs the second deploy"
    for cls, name, why in ((_ChangedInTransit, "r5", "release files differ from release.json"
                            ": tacfootctl"),
                           (_SignedByAnother, "r6", "signature does not verify")):
        opts = pi.opts(release=name)
        d = cls(opts, log=_quiet, key=load_key(opts))
        with pytest.raises(DeployError, match="step install failed") as exc:
            d.deploy()
        assert why in str(exc.value)
        assert "switch" not in [s["step"] for s in d.steps]
        assert not (pi.prefix / "releases" / name / ".complete").exists()
        assert pi.link("current") == "releases/r2" and pi.pid() == pid


@needs_sshd
def test_failing_step_before_switch_changes_nothing(pi):
    pid = pi.pid()
    assert pi.link("current") == "releases/r2" and pid
    res = run(pi.opts(release="r2"), log=_quiet)   # r2 exists: prepare refuses
    assert not res["ok"] and "prepare" in res["error"] and "already exists" in res["error"]
    assert not res.get("rolled_back")
    assert pi.link("current") == "releases/r2" and pi.pid() == pid and pi.packets_flow(pid)
    # ... and it cleared what the killed copy left behind
    assert not (pi.prefix / "releases" / "r4").exists()


@needs_sshd
def test_rollback_switches_to_previous_and_restarts(pi, capsys):
    from host.cli import main
    assert pi.link("current") == "releases/r2"
    o = pi.opts()
    argv = ["deploy", o.target, "--rollback", "--json", "--port", str(o.port), "--identity",
            o.identity, "--prefix", str(pi.prefix), "--python", o.python,
            "--service-manager", "none", "--health-timeout-s", "20"]
    for s in o.ssh_options:
        argv += ["--ssh-option", s]
    assert main(argv) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["ok"] and res["release"] == "releases/r1", res
    assert pi.link("current") == "releases/r1" and pi.link("previous") == "releases/r2"
    pid = pi.pid()
    assert pi.tag(pid) == "r1" and pi.packets_flow(pid)


# -- the systemd path, with a stand-in systemctl ----------------------------------------
# There is no systemd in the test container; this systemctl does what the deploy
# asks of the real one (install, daemon-reload, enable, restart, stop, is-active,
# show MainPID) by running the installed unit's ExecStart= and Environment= lines,
# so the systemd-mode commands and the unit's command line are exercised for real.

FAKE_SYSTEMCTL = r'''#!{python}
import os, shlex, signal, socket, subprocess, sys, time
state = os.environ["FAKE_SYSTEMD_DIR"]
with open(os.path.join(state, "calls.log"), "a") as fh:
    fh.write(" ".join(sys.argv[1:]) + "\n")
words = [a for a in sys.argv[1:] if not a.startswith("-")]
cmd, name = words[0], (words[-1] if len(words) > 1 else "")
pidfile = os.path.join(state, name + ".pid")

def unescape(w):
    return w.replace("%%", "%").replace("$$", "$")

def alive(pid):
    try:
        os.kill(pid, 0)
        with open("/proc/%d/stat" % pid) as fh:
            return fh.read().split(") ")[1][0] != "Z"
    except (OSError, IndexError):
        return False

def main_pid():
    try:
        pid = int(open(pidfile).read())
    except (OSError, ValueError):
        return 0
    return pid if alive(pid) else 0

def stop():
    pid = main_pid()
    if pid:
        os.kill(pid, signal.SIGTERM)
        t0 = time.monotonic()
        while alive(pid) and time.monotonic() - t0 < 10:
            time.sleep(0.05)
        if alive(pid):
            os.kill(pid, signal.SIGKILL)

def start():
    unit = open(os.path.join(state, "units", name + ".service")).read().splitlines()
    env = dict(os.environ)
    argv = None
    notify = watchdog_s = None
    for line in unit:
        if line == "Type=notify":
            notify = os.path.join(state, "notify.sock")
        elif line.startswith("WatchdogSec="):
            watchdog_s = int(line.split("=", 1)[1])
        elif line.startswith("ExecStart="):
            argv = [unescape(w) for w in shlex.split(line[len("ExecStart="):])]
        elif line.startswith("Environment="):
            for kv in shlex.split(line[len("Environment="):]):
                k, _, v = unescape(kv).partition("=")
                env[k] = v
    sock = None
    if notify:          # like systemd: a notify socket, and wait for READY=1
        if os.path.exists(notify):
            os.unlink(notify)
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        sock.bind(notify)
        env["NOTIFY_SOCKET"] = notify
        if watchdog_s:
            env["WATCHDOG_USEC"] = str(watchdog_s * 1000000)
    log = open(os.path.join(state, name + ".log"), "ab")
    p = subprocess.Popen(argv, env=env, stdin=subprocess.DEVNULL, stdout=log, stderr=log,
                         start_new_session=True)
    open(pidfile, "w").write(str(p.pid))
    if sock is not None:
        got, t0 = [], time.monotonic()
        sock.settimeout(0.5)
        # wait for READY=1 and, with a watchdog, the first WATCHDOG=1 after it
        while time.monotonic() - t0 < 30 and p.poll() is None:
            try:
                got += sock.recv(4096).decode().split("\n")
            except socket.timeout:
                continue
            if "READY=1" in got and (not watchdog_s or "WATCHDOG=1" in
                                     got[got.index("READY=1"):]):
                break
        with open(os.path.join(state, "notify.log"), "a") as fh:
            fh.write("\n".join(got) + "\n")
        if "READY=1" not in got:
            sys.exit("fake systemctl: %s did not send READY=1" % name)

if cmd in ("daemon-reload", "reset-failed", "enable"):
    pass
elif cmd == "restart":
    stop(); start()
elif cmd == "stop":
    stop()
elif cmd == "is-active":
    sys.exit(0 if main_pid() else 3)
elif cmd == "show":
    print(main_pid())
else:
    sys.exit("fake systemctl: unsupported " + cmd)
'''


@needs_sshd
def test_systemd_mode_installs_the_unit_and_restarts(tmp_path):
    state = tmp_path / "systemd"
    (state / "units").mkdir(parents=True)
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    ctl = bin_dir / "systemctl"
    ctl.write_text(FAKE_SYSTEMCTL.replace("{python}", sys.executable))
    ctl.chmod(0o755)
    env = {"PATH": f"{bin_dir}:/usr/local/bin:/usr/bin:/bin:/usr/sbin:/sbin",
           "FAKE_SYSTEMD_DIR": str(state)}
    srv = SshServer(tmp_path, env=env).start()
    try:
        pi = Pi(srv, tmp_path)
        kw = dict(service_manager="systemd", unit_dir=str(state / "units"), env=["TAG=s1"],
                  release="s1", watchdog_s=2)
        res = run(pi.opts(**kw), log=_quiet)
        assert res["ok"] and res["service_manager"] == "systemd", (res.get("error"),
                                                                   res["steps"][-1])
        unit = (state / "units" / "tacfoot.service").read_text()
        assert unit == (pi.prefix / "releases" / "s1" / "tacfoot.service").read_text()
        assert "Type=notify" in unit and "WatchdogSec=2" in unit
        # the runtime spoke sd_notify through device.pi.runtime.sdnotify: ready, then watchdog
        notes = (state / "notify.log").read_text().splitlines()
        assert "READY=1" in notes and "WATCHDOG=1" in notes[notes.index("READY=1"):], notes
        calls = (state / "calls.log").read_text().splitlines()
        for want in ("daemon-reload", "enable --quiet tacfoot", "restart tacfoot",
                     "show -p MainPID --value tacfoot"):
            assert want in calls, (want, calls)
        pid = int((state / "tacfoot.pid").read_text())
        assert res["health"]["pid"] == pid and pi.tag(pid) == "s1" and pi.packets_flow(pid)
    finally:
        subprocess.run([str(ctl), "stop", "tacfoot"], env={**os.environ, **env},
                       capture_output=True, timeout=30)
        srv.stop()


@needs_sshd
def test_unreachable_pi_and_nothing_to_roll_back_give_clear_errors(pi, tmp_path):
    res = run(pi.opts(port=1, release="x"), log=_quiet)        # nobody listens on port 1
    assert not res["ok"] and res["error"].startswith("step probe failed (exit 255)")
    assert [s["step"] for s in res["steps"]] == ["probe"]
    res = run(pi.opts(prefix=str(tmp_path / "empty")), rollback=True, log=_quiet)
    assert not res["ok"] and "no previous release under" in res["error"]
    assert not (tmp_path / "empty").exists()


# -- from an installed toolkit ----------------------------------------------------------

_SDIST_NAMES = """
import json, sys, tarfile, tempfile
from pathlib import Path
from host.deploy.options import DeployOptions
from host.deploy.release import Deployer
sd = Deployer(DeployOptions(target="pi@leg1"), log=lambda *a, **k: None).build_sdist(
    Path(tempfile.mkdtemp()))
with tarfile.open(sd) as t:
    print(json.dumps([sd.name, sorted(n.split("/", 1)[1] for n in t.getnames() if "/" in n)]))
"""


def test_an_installed_toolkit_plans_and_builds_the_release_a_checkout_would(tmp_path):
    """From a wheel unpacked as site-packages, run from an empty folder: the dry run
    names the real version and the wheel's shipped models, and the leg's source
    distribution holds the same files as the checkout's. A wheel without its source
    files refuses in one line."""
    from tests.wheel import build_wheel, clean_env, unpack
    site = unpack(build_wheel(tmp_path), tmp_path / "site")
    empty = tmp_path / "empty"
    empty.mkdir()
    env = clean_env(PYTHONPATH=str(site))
    plan = subprocess.run([sys.executable, "-m", "host", "deploy", "pi@leg1", "--dry-run"],
                          cwd=empty, env=env, capture_output=True, text=True, timeout=120)
    assert plan.returncode == 0, plan.stderr[-2000:]
    assert f", models {site / 'device' / 'data' / 'models'}, config " in plan.stdout
    assert f"/releases/{project_version()}-" in plan.stdout and project_version() != "0"
    got = subprocess.run([sys.executable, "-c", _SDIST_NAMES], cwd=empty, env=env,
                         capture_output=True, text=True, timeout=120)
    assert got.returncode == 0, got.stderr[-2000:]
    want = subprocess.run([sys.executable, "-c", _SDIST_NAMES], cwd=REPO, capture_output=True,
                          text=True, timeout=120, env=clean_env(PYTHONPATH=str(REPO)))
    assert json.loads(got.stdout) == json.loads(want.stdout)
    assert "setup.py" in json.loads(got.stdout)[1]
    assert not [n for n in json.loads(got.stdout)[1] if n.startswith("device/data/")]
    shutil.rmtree(site / "device" / "data" / "source")
    plan = subprocess.run([sys.executable, "-m", "host", "deploy", "pi@leg1", "--dry-run"],
                          cwd=empty, env=env, capture_output=True, text=True, timeout=120)
    assert plan.returncode == 2 and len(plan.stderr.strip().splitlines()) == 1, plan.stderr
    assert "no pyproject.toml, setup.py beside it" in plan.stderr
