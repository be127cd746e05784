"""``host deploy``: install the Pi runtime on a Raspberry Pi over SSH.

One deploy is a list of steps, each either local (build, stage) or one ``ssh``
command running a small POSIX shell script on the Pi. Every step is logged with
its command; ``--dry-run`` prints the same list and runs none of it.

Layout on the Pi (``PREFIX`` defaults to /opt/tacfoot)::

    PREFIX/releases/<release>/        one folder per deploy, never changed after
        tacfoot-<ver>-py3-none-any.whl
        venv/                         the runtime's virtualenv, wheel installed
        models/  config/              the models and the config it runs with
        tacfoot.service  tacfootctl   the systemd unit and the no-systemd starter
        release.json  .complete       metadata; .complete is written last
    PREFIX/current  -> releases/<r>   what the service runs (switched atomically)
    PREFIX/previous -> releases/<r>   what ``--rollback`` goes back to
    PREFIX/run/status.json            the runtime's status file (health check)

Order: probe, build, stage, prepare, copy, install (venv + wheel, then
``.complete``), switch (``current``), service (unit + restart), health (the
service is active and ``packets_sent`` in the status file grows, from the
service's own pid). A failed health check switches ``current`` back and
restarts the old release. Everything before the switch writes only inside the
new release's folder, so an interrupted deploy leaves the old release running.
"""
from __future__ import annotations

import hashlib
import json
import os
import secrets
import shlex
import shutil
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

from device.config import ConfigError, read_toml
from host.deploy.options import REPO, DeployError, DeployOptions, project_version
from host.deploy.scripts import (HEALTH_PY, SUDO, q, render_ctl, render_unit, runtime_argv,
                                 status_path)



def config_profile_file(cfg: Path) -> Path | None:
    """The sensor profile file a leg config names by a relative path (``[models]
    profile = "my-sensor.toml"``), which must sit beside the config; None for a
    built-in profile. A missing file is a ConfigError naming it."""
    doc = read_toml(cfg)
    prof = (doc.get("models") or {}).get("profile") if isinstance(doc, dict) else None
    if not isinstance(prof, str) or not prof.endswith(".toml") or Path(prof).is_absolute():
        return None
    if Path(prof).parent != Path("."):
        raise ConfigError(f"{cfg}: models.profile {prof!r}: put the profile file beside the "
                          f"config and name it without a folder")
    path = cfg.parent / prof
    if not path.is_file():
        raise ConfigError(f"{cfg}: models.profile {prof!r}: no such file {path}")
    return path

class Deployer:
    """Runs (or, with dry_run, only lists) the steps of one deploy or rollback."""

    def __init__(self, opts: DeployOptions, dry_run: bool = False, log=None):
        opts.check()
        self.o = opts
        self.dry_run = dry_run
        self.log = log if log is not None else (lambda msg: print(msg, file=sys.stderr))
        self.steps: list[dict] = []
        self.copy_hook = None          # called (proc, bytes_sent) while copying
        self.manager = opts.service_manager
        self.release = opts.release or ""
        self._cm_dir: str | None = None          # ssh ControlMaster socket folder

    # -- plumbing --------------------------------------------------------------
    def _ssh_base(self) -> list[str]:
        o = self.o
        argv = ["ssh", "-o", "BatchMode=yes", "-o", "ConnectTimeout=15"]
        if o.ssh_port is not None:
            argv += ["-p", str(o.ssh_port)]
        if o.identity:
            argv += ["-i", o.identity, "-o", "IdentitiesOnly=yes"]
        for opt in o.ssh_options:
            argv += ["-o", opt]
        if self._cm_dir is not None:
            argv += ["-o", f"ControlPath={self._cm_dir}/cm", "-o", "ControlMaster=no"]
        return argv

    def open_connection(self):
        """One SSH connection that every step reuses (ControlMaster); without it
        (it failed, or a dry run) each step connects on its own."""
        if self.dry_run or self._cm_dir is not None:
            return
        d = tempfile.mkdtemp(prefix="tfssh-")
        argv = self._ssh_base() + ["-o", f"ControlPath={d}/cm", "-o", "ControlMaster=yes",
                                   "-o", "ControlPersist=600", "-f", "-N", self.o.ssh_target]
        try:
            r = subprocess.run(argv, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                               stderr=subprocess.DEVNULL, timeout=60)
            ok = r.returncode == 0 and os.path.exists(f"{d}/cm")
        except subprocess.TimeoutExpired:
            ok = False
        if ok:
            self._cm_dir = d
        else:
            shutil.rmtree(d, ignore_errors=True)

    def close_connection(self):
        if self._cm_dir is None:
            return
        d, self._cm_dir = self._cm_dir, None
        subprocess.run(self._ssh_base() + ["-o", f"ControlPath={d}/cm", "-O", "exit",
                                           self.o.ssh_target],
                       stdin=subprocess.DEVNULL, capture_output=True, timeout=30)
        shutil.rmtree(d, ignore_errors=True)

    def ssh_argv(self, script: str) -> list[str]:
        return self._ssh_base() + [self.o.ssh_target, "--", "sh -c " + q("set -eu\n" + script)]

    def _record(self, name, where, command, **extra) -> dict:
        step = {"step": name, "where": where, "command": command, **extra}
        self.steps.append(step)
        shown = command.replace(q(HEALTH_PY), '"$HEALTH_CHECK_PY"')
        self.log(f"[deploy] {name} ({where}): " + shown.strip().replace("\n", "; "))
        return step

    def remote(self, name: str, script: str, check: bool = True, timeout_s: float = 600):
        step = self._record(name, "remote", script)
        if self.dry_run:
            return step
        t0 = time.monotonic()
        try:
            r = subprocess.run(self.ssh_argv(script), capture_output=True, text=True,
                               timeout=timeout_s, stdin=subprocess.DEVNULL)
            rc, out, err = r.returncode, r.stdout, r.stderr
        except subprocess.TimeoutExpired:
            rc, out, err = -1, "", f"timed out after {timeout_s:.0f} s"
        step.update(rc=rc, seconds=round(time.monotonic() - t0, 3), stdout=out[-2000:],
                    stderr=err[-2000:])
        if rc != 0:
            self.log(f"[deploy] {name}: exit {rc}: {err.strip()[-500:]}")
            if check:
                raise DeployError(f"step {name} failed (exit {rc}): "
                                  f"{err.strip().splitlines()[-1] if err.strip() else ''}")
        return step

    # -- scripts ---------------------------------------------------------------
    def _pid_cmd(self) -> str:
        o = self.o
        if self.manager == "systemd":
            return (f"systemctl is-active --quiet {q(o.service_name)} && "
                    f"systemctl show -p MainPID --value {q(o.service_name)}")
        return f"{q(o.prefix + '/current/tacfootctl')} pid"

    def _service_script(self) -> str:
        """Install the current release's unit and restart the service."""
        o = self.o
        cur = f"{o.prefix}/current"
        if self.manager == "systemd":
            return (SUDO +
                    f"$SUDO install -m 0644 {q(cur + '/tacfoot.service')} "
                    f"{q(o.unit_dir + '/' + o.service_name + '.service')}\n"
                    "$SUDO systemctl daemon-reload\n"
                    f"$SUDO systemctl reset-failed {q(o.service_name)} 2>/dev/null || true\n"
                    f"$SUDO systemctl enable --quiet {q(o.service_name)}\n"
                    f"$SUDO systemctl restart {q(o.service_name)}\n")
        return f"{q(cur + '/tacfootctl')} restart\n"

    def _stop_script(self) -> str:
        o = self.o
        if self.manager == "systemd":
            return SUDO + f"$SUDO systemctl stop {q(o.service_name)} || true\n"
        return (f"[ ! -x {q(o.prefix + '/current/tacfootctl')} ] || "
                f"{q(o.prefix + '/current/tacfootctl')} stop\n")

    def _link_script(self, link: str, target: str | None) -> str:
        """Point PREFIX/link at target atomically (ln -s to a temp name, mv -T);
        target None removes the link."""
        p = q(self.o.prefix)
        if target is None:
            return f"rm -f {p}/{link}\n"
        return (f"ln -sfn {q(target)} {p}/.{link}.tmp\n"
                f"mv -T {p}/.{link}.tmp {p}/{link}\n")

    def _health_script(self) -> str:
        o = self.o
        # systemd restarts a failed runtime (Restart=on-failure): wait the whole
        # timeout; with a pid file nothing will, so 2 s not running is final
        dead_s = 0 if self.manager == "systemd" else 2
        return (f"{q(o.python)} -c {q(HEALTH_PY)} {q(status_path(o))} {q(self._pid_cmd())} "
                f"{o.health_timeout_s:g} {dead_s}\n")

    # -- local steps -------------------------------------------------------------
    def build_wheel(self, out_dir: Path) -> Path:
        """Build the tacfoot wheel from a clean copy of the source tree."""
        cmd = [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
               "-q", "-w", str(out_dir / "dist"), str(out_dir / "src")]
        step = self._record("build", "local", shlex.join(cmd))
        if self.dry_run:
            return out_dir / "dist" / "tacfoot.whl"
        t0 = time.monotonic()
        src = out_dir / "src"
        src.mkdir(parents=True)
        ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info", "build")
        for name in ("pyproject.toml", "README.md"):
            shutil.copy2(REPO / name, src / name)
        for pkg in ("device", "host"):
            shutil.copytree(REPO / pkg, src / pkg, ignore=ignore)
        r = subprocess.run(cmd, capture_output=True, text=True)
        step.update(rc=r.returncode, seconds=round(time.monotonic() - t0, 3))
        wheels = sorted((out_dir / "dist").glob("tacfoot-*.whl"))
        if r.returncode != 0 or not wheels:
            raise DeployError(f"step build failed: {r.stderr.strip()[-500:]}")
        return wheels[0]

    def stage(self, wheel: Path, out_dir: Path) -> Path:
        o = self.o
        st = out_dir / "stage"
        models, cfg = o.models_dir(), o.config_file()
        prof = config_profile_file(cfg) if cfg is not None else None
        self._record("stage", "local", f"stage {wheel.name}"
                     + (f", models {models}" if models else "")
                     + (f", config {cfg}" if cfg else "")
                     + (f", profile {prof.name}" if prof else "") + ", tacfoot.service, tacfootctl")
        if self.dry_run:
            return st
        st.mkdir()
        shutil.copy2(wheel, st / wheel.name)
        if models is not None:
            shutil.copytree(models, st / "models",
                            ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        if cfg is not None:
            (st / "config").mkdir()
            shutil.copy2(cfg, st / "config" / cfg.name)
            if prof is not None:       # a calibrated profile named beside the config
                shutil.copy2(prof, st / "config" / prof.name)
        (st / "tacfoot.service").write_text(render_unit(o))
        (st / "tacfootctl").write_text(render_ctl(o))
        (st / "tacfootctl").chmod(0o755)
        (st / "release.json").write_text(json.dumps({
            "release": self.release, "wheel": wheel.name,
            "wheel_sha256": hashlib.sha256(wheel.read_bytes()).hexdigest(),
            "built_unix": round(time.time(), 3), "runtime_argv": runtime_argv(o),
            "service_manager": self.manager}, indent=1) + "\n")
        return st

    def copy(self, staged: Path):
        """Stream the staged folder as a tar over one ssh into releases/R."""
        rel = f"{self.o.prefix}/releases/{self.release}"
        script = f"mkdir -p {q(rel)}\ntar -xzf - -C {q(rel)}\n"
        step = self._record("copy", "remote", f"tar -czf - -C {staged} . | ssh ... "
                            + script.strip().replace("\n", "; "))
        if self.dry_run:
            return
        t0 = time.monotonic()
        with tempfile.TemporaryFile() as err:
            proc = subprocess.Popen(self.ssh_argv(script), stdin=subprocess.PIPE,
                                    stdout=subprocess.DEVNULL, stderr=err)
            sent = 0
            hook = self.copy_hook
            try:
                class _Counting:
                    def write(_self, b):
                        nonlocal sent
                        proc.stdin.write(b)
                        sent += len(b)
                        if hook is not None:
                            hook(proc, sent)
                        return len(b)

                    def flush(_self):
                        proc.stdin.flush()

                with tarfile.open(fileobj=_Counting(), mode="w|gz") as tar:
                    tar.add(staged, arcname=".")
                proc.stdin.close()
            except (BrokenPipeError, OSError, ValueError):
                pass
            finally:
                try:
                    rc = proc.wait(timeout=600)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    rc = proc.wait()
            err.seek(0)
            msg = err.read().decode(errors="replace").strip()
        step.update(rc=rc, bytes=sent, seconds=round(time.monotonic() - t0, 3), stderr=msg[-2000:])
        if rc != 0:
            raise DeployError(f"step copy failed (exit {rc}) after {sent} bytes"
                              + (f": {msg.splitlines()[-1]}" if msg else ""))

    # -- the deploy ----------------------------------------------------------------
    def probe(self) -> dict:
        o = self.o
        p = q(o.prefix)
        script = (
            "if [ -d /run/systemd/system ] && command -v systemctl >/dev/null; "
            "then echo manager=systemd; else echo manager=none; fi\n"
            f"echo current=$(readlink {p}/current 2>/dev/null || true)\n"
            f"echo previous=$(readlink {p}/previous 2>/dev/null || true)\n"
            "echo user=$(id -un)\n"
            f"echo python=$({q(o.python)} -c 'import sys; print(sys.version.split()[0])' "
            "2>/dev/null || echo missing)\n")
        step = self.remote("probe", script)
        info = {"manager": None, "current": "", "previous": "", "user": "", "python": ""}
        for line in step.get("stdout", "").splitlines():
            k, _, v = line.partition("=")
            if k in info:
                info[k] = v.strip()
        if not self.dry_run and info["python"] in ("", "missing"):
            raise DeployError(f"step probe: {o.python!r} does not run on {o.target} "
                              "(set --python)")
        return info

    def _resolve_manager(self, info: dict):
        if self.manager == "auto":
            self.manager = info.get("manager") or "systemd"

    def deploy(self) -> dict:
        o = self.o
        res = {"target": o.target, "prefix": o.prefix, "dry_run": self.dry_run,
               "ok": False, "rolled_back": False}
        info = self.probe()
        if self.dry_run and self.manager == "auto":
            res["note"] = "service manager auto: the probe decides; plan shown for systemd"
        self._resolve_manager(info)
        res["service_manager"] = self.manager
        old = info["current"] or None
        res["previous"] = old
        if not self.release:
            self.release = (f"{project_version()}-{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}-"
                            f"{secrets.token_hex(2)}")
        res["release"] = self.release
        rel = f"{o.prefix}/releases/{self.release}"
        relname = f"releases/{self.release}"
        with tempfile.TemporaryDirectory(prefix="tacfoot-deploy-") as tmp:
            wheel = self.build_wheel(Path(tmp))
            staged = self.stage(wheel, Path(tmp))
            res["wheel"] = wheel.name
            p = q(o.prefix)
            self.remote("prepare", SUDO +
                        f"if [ ! -d {p} ]; then $SUDO mkdir -p {p}; "
                        f"$SUDO chown \"$(id -u):$(id -g)\" {p}; fi\n"
                        f"mkdir -p {p}/releases {p}/run\n"
                        f"cd {p}/releases\n"
                        # drop what an interrupted deploy left (never current/previous)
                        "for d in *; do [ -d \"$d\" ] || continue\n"
                        "  [ -f \"$d/.complete\" ] || rm -rf \"$d\"; done\n"
                        f"[ ! -e {q(self.release)} ] || "
                        f"{{ echo 'release {self.release} already exists' >&2; exit 3; }}\n")
            self.copy(staged)
        self.remote("install", self._install_script(rel))
        # -- from here on the old release has been touched: undo on any failure
        switched = False
        try:
            switched = True         # from here undo, even if the switch itself broke off
            self.remote("switch", f"cd {q(o.prefix)}\n"
                        f"[ -f {q(relname + '/.complete')} ] || "
                        f"{{ echo 'release {self.release} is incomplete' >&2; exit 3; }}\n"
                        + self._link_script("current", relname))
            self.remote("service", self._service_script())
            h = self.health("health")
            res["health"] = h
            if self.dry_run or h.get("ok"):
                # the new release runs: from here a failure is only a warning
                if old and old != relname:
                    st = self.remote("previous", self._link_script("previous", old), check=False)
                    if st.get("rc"):
                        res.setdefault("warnings", []).append("could not set previous")
                st = self.remote("prune", self._prune_script(), check=False)
                if st.get("rc"):
                    res.setdefault("warnings", []).append("could not prune old releases")
                res["ok"] = True
                return res
            raise DeployError(f"health check failed: {h.get('reason', 'unknown')}")
        except BaseException as exc:          # Ctrl-C too: never leave a half switch
            res["error"] = str(exc) or type(exc).__name__
            if switched:
                try:        # what the new release's runtime said before it is replaced
                    res["log_tail"] = self.log_tail()
                except BaseException:
                    res["log_tail"] = []
                if res["log_tail"] and isinstance(exc, DeployError):
                    res["error"] += f"; the runtime said: {res['log_tail'][-1]}"
                res["rolled_back"] = True
                res["rollback"] = self._undo(old, relname)
            if not isinstance(exc, DeployError):
                raise
            return res

    def _install_script(self, rel: str) -> str:
        o = self.o
        r = q(rel)
        venv_flags = " --system-site-packages --without-pip" if o.system_site_packages else ""
        pip_flags = " --no-deps --no-index" if o.no_deps else ""
        s = f"cd {r}\n[ ! -e .complete ]\n{q(o.python)} -m venv{venv_flags} venv\n"
        if o.system_site_packages:
            # the venv sees every site-packages folder --python sees (its system
            # ones, and its own when --python is itself a venv); pip comes from there too
            s += (f"site=$(venv/bin/python -c 'import sysconfig; print(sysconfig.get_paths()"
                  "[\"purelib\"])')\n"
                  f"{q(o.python)} -c 'import sys; print(\"\\n\".join(p for p in sys.path "
                  "if p.endswith((\"site-packages\", \"dist-packages\"))))' "
                  "> \"$site/_tacfoot_base.pth\"\n"
                  "venv/bin/python -m pip --version >/dev/null 2>&1 || "
                  "venv/bin/python -m ensurepip --default-pip >/dev/null\n")
        s += (f"venv/bin/python -m pip install -q --disable-pip-version-check{pip_flags} "
              "./tacfoot-*.whl\n"
              # the installed code must import before this release may become current
              "venv/bin/python -c 'import device.pi, device.pi.runtime.sdnotify'\n"
              "date -u +%Y-%m-%dT%H:%M:%SZ > .complete\n")
        return s

    def _prune_script(self) -> str:
        o = self.o
        return (f"cd {q(o.prefix)}\n"
                "cur=$(readlink current || true); prev=$(readlink previous || true)\n"
                f"ls -1dt releases/*/ 2>/dev/null | sed 's#/$##' | tail -n +{o.keep + 1} | "
                "while read -r d; do\n"
                "  [ \"$d\" = \"$cur\" ] || [ \"$d\" = \"$prev\" ] || rm -rf \"$d\"; done\n")

    def _undo(self, old: str | None, failed: str) -> dict:
        """Switch current back to old (or remove it) and restart the old release."""
        out = {"to": old}
        try:
            if old:
                self.remote("rollback-switch", f"cd {q(self.o.prefix)}\n"
                            + self._link_script("current", old)
                            + f"touch {q(failed + '/.failed')}\n")
                self.remote("rollback-service", self._service_script())
                out["health"] = self.health("rollback-health")
                out["ok"] = bool(out["health"].get("ok"))
            else:
                self.remote("rollback-stop", self._stop_script()
                            + f"cd {q(self.o.prefix)}\n" + self._link_script("current", None)
                            + f"touch {q(failed + '/.failed')}\n")
                out["ok"] = True
        except DeployError as exc:
            out.update(ok=False, error=str(exc))
        return out

    def health(self, name: str) -> dict:
        step = self.remote(name, self._health_script(), check=False,
                           timeout_s=self.o.health_timeout_s + 60)
        if self.dry_run:
            return {"ok": None}
        try:
            return json.loads(step.get("stdout", "").strip().splitlines()[-1])
        except (ValueError, IndexError):
            return {"ok": False, "reason": "health check gave no answer: "
                    + step.get("stderr", "").strip()[-300:]}

    def log_tail(self, n: int = 20) -> list[str]:
        """The service's last log lines (journal, or tacfootctl's log file)."""
        o = self.o
        if self.manager == "systemd":
            script = (SUDO + f"$SUDO journalctl -u {q(o.service_name)} -n {n} --no-pager "
                      "-o cat 2>/dev/null || true\n")
        else:
            script = f"tail -n {n} {q(o.prefix + '/run/' + o.service_name + '.log')} || true\n"
        st = self.remote("logs", script, check=False)
        return [l for l in st.get("stdout", "").splitlines() if l.strip()]

    def rollback(self) -> dict:
        """Switch current back to previous (and previous to the one we left)."""
        o = self.o
        res = {"target": o.target, "prefix": o.prefix, "dry_run": self.dry_run, "ok": False}
        info = self.probe()
        self._resolve_manager(info)
        res["service_manager"] = self.manager
        cur, prev = info["current"] or None, info["previous"] or None
        if not self.dry_run and not prev:
            raise DeployError(f"no previous release under {o.prefix} to roll back to")
        res.update(release=prev, previous=cur)
        p = q(o.prefix)
        self.remote("switch", f"cd {p}\nprev=$(readlink previous)\ncur=$(readlink current)\n"
                    "[ -f \"$prev/.complete\" ] || "
                    "{ echo \"previous release $prev is incomplete\" >&2; exit 3; }\n"
                    "ln -sfn \"$prev\" .current.tmp\nmv -T .current.tmp current\n"
                    "ln -sfn \"$cur\" .previous.tmp\nmv -T .previous.tmp previous\n")
        self.remote("service", self._service_script())
        res["health"] = self.health("health")
        res["ok"] = True if self.dry_run else bool(res["health"].get("ok"))
        if not res["ok"]:
            res["error"] = f"health check failed: {res['health'].get('reason', 'unknown')}"
        return res


def run(opts: DeployOptions, dry_run: bool = False, rollback: bool = False,
        log=None) -> dict:
    """Deploy (or roll back); the result dict has ok, release, steps, health."""
    d = Deployer(opts, dry_run=dry_run, log=log)
    try:
        d.open_connection()
        res = d.rollback() if rollback else d.deploy()
    except DeployError as exc:
        res = {"target": opts.target, "ok": False, "dry_run": dry_run, "error": str(exc)}
    finally:
        d.close_connection()
    res["steps"] = d.steps
    return res


def summary_text(res: dict) -> str:
    if res.get("dry_run"):
        lines = ["plan (dry run, nothing was run):"]
        for s in res.get("steps", []):
            lines.append(f"# {s['step']} ({s['where']})")
            lines.append(s["command"].rstrip())
        if res.get("note"):
            lines.append("# " + res["note"])
        return "\n".join(lines)
    if res.get("ok"):
        h = res.get("health", {})
        return (f"{res.get('target')}: release {res.get('release')} running "
                f"(pid {h.get('pid')}, {h.get('packets_per_s')} packets/s)"
                + (f"; previous {res['previous']}" if res.get("previous") else ""))
    msg = f"{res.get('target')}: FAILED: {res.get('error')}"
    if res.get("rolled_back"):
        rb = res.get("rollback", {})
        msg += (f"; rolled back to {rb.get('to') or 'nothing (service stopped)'}"
                f" ({'ok' if rb.get('ok') else 'rollback FAILED'})")
    return msg
