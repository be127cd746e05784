"""``host deploy``: install the Pi runtime on a Raspberry Pi over SSH.

One deploy is a list of steps, each either local (build, stage) or one ``ssh``
command running a small POSIX shell script on the Pi (:mod:`host.deploy.ssh`).
Every step is logged with its command; ``--dry-run`` prints the same list and runs
none of it. The staged models and ``release.json`` are signed with the host's key
(:mod:`host.deploy.signing`).

Layout on the Pi (``PREFIX`` defaults to /opt/tacfoot)::

    PREFIX/releases/<release>/        one folder per deploy, never changed after
        tacfoot-<ver>.tar.gz          the source distribution (pip compiles its C on the Pi)
        venv/                         the runtime's virtualenv, the package installed
        models/  config/              the models (manifests signed) and the config it
                                      runs with (holding the public key)
        tacfoot.service  tacfootctl   the systemd unit and the no-systemd starter
        release.json(.sig)            every file's SHA-256, signed
        .complete                     written last
        .healthy                      written when it passes a health check
    PREFIX/current  -> releases/<r>   what the service runs (switched atomically)
    PREFIX/previous -> releases/<r>   what ``--rollback`` goes back to
    PREFIX/run/status.json            the runtime's status file (health check)

Order: probe, build (the sdist), stage, prepare, copy, install (venv + pip install of
the sdist, which compiles the frame core's C library for the Pi's CPU, then
``.complete``), switch (``current``), service (unit + restart), health (the
service is active and ``packets_sent`` in the status file grows, from the
service's own pid; a pass writes ``.healthy`` in the release folder). The service
runs with ``TACFOOT_RELEASE=<release>`` in its environment, so ``--status`` can tell
which release the running process belongs to. A failed health check switches ``current`` back and
restarts the old release. Everything before the switch writes only inside the
new release's folder, so an interrupted deploy leaves the old release running.
The phases (:meth:`Deployer.begin`, ``install``, ``switch``, ``commit``,
``revert``) are what :mod:`host.deploy.robot` runs across legs.
"""
from __future__ import annotations

import json
import secrets
from dataclasses import replace
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from device.pi.models.artefact import sha256_file
from host.deploy.options import (PACKAGED, REPO, SOURCE_FILES, DeployError, DeployInputError,
                                 DeployOptions, check_source, project_version, source_file)
from host.deploy.scripts import (HEALTH_PY, SUDO, VERIFY_RELEASE_PY, q, render_ctl,
                                 render_unit, runtime_argv, status_path)
from host.deploy.models import check_models_profile, config_profile_file, fuse_release_models
from host.deploy.signing import SigningKey, config_with_key, default_key_path, sign_models
from host.deploy.ssh import SshSession


def new_release_name() -> str:
    """VERSION-UTCSTAMP-RAND: a release folder name that sorts by time."""
    return (f"{project_version()}-{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}-"
            f"{secrets.token_hex(2)}")


class Deployer(SshSession):
    """Runs (or, with dry_run, only lists) the steps of one deploy or rollback.
    ``key`` (a :class:`host.deploy.signing.SigningKey`) signs what is staged."""

    def __init__(self, opts: DeployOptions, dry_run: bool = False, log=None, key=None):
        super().__init__(opts, dry_run=dry_run, log=log)
        self.manager = opts.service_manager
        self.release = opts.release or ""
        self.key = key
        self.old: str | None = None          # the release current pointed at before
        self.created = False     # the release's folder is this deploy's (prepare found it free)
        self.switched = False

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

    def _health_script(self, marker: str | None = None) -> str:
        """The health check; ``marker``: the file it writes when the check passes."""
        o = self.o
        # systemd restarts a failed runtime (Restart=on-failure): wait the whole
        # timeout; with a pid file nothing will, so 2 s not running is final
        dead_s = 0 if self.manager == "systemd" else 2
        return (f"{q(o.python)} -c {q(HEALTH_PY)} {q(status_path(o))} {q(self._pid_cmd())} "
                f"{o.health_timeout_s:g} {dead_s}" + (f" {q(marker)}" if marker else "") + "\n")

    # -- local steps -------------------------------------------------------------
    def build_sdist(self, out_dir: Path) -> Path:
        """Build the tacfoot source distribution from a clean copy of the source tree
        (setuptools' PEP 517 hook, no build isolation, as ``pip wheel`` was): a wheel
        built here would carry a library for this machine's CPU, so the Pi's pip
        builds the wheel, and compiles the C, from this. From an installed toolkit the
        tree is the installed packages (without the shipped data) and the source files
        the wheel carries: the same files a checkout gives."""
        check_source()
        cmd = [sys.executable, "-c", "import sys, setuptools.build_meta as b; "
               "b.build_sdist(sys.argv[1])", str(out_dir / "dist")]
        step = self.record("build", "local", f"cd {shlex.quote(str(out_dir / 'src'))} && "
                           + shlex.join(cmd))
        if self.dry_run:
            return out_dir / "dist" / "tacfoot.tar.gz"
        t0 = time.monotonic()
        src = out_dir / "src"
        src.mkdir(parents=True)
        ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info", "build", "*.so")
        for name in SOURCE_FILES:
            if source_file(name).is_file():
                shutil.copy2(source_file(name), src / name)
        packaged = (REPO / "device" / PACKAGED).resolve()

        def skip(folder, names):           # the wheel's shipped data: not in the sdist
            return set(ignore(folder, names)) | (
                {PACKAGED} if Path(folder).resolve() == packaged.parent else set())
        for pkg in ("device", "host"):
            shutil.copytree(REPO / pkg, src / pkg, ignore=skip)
        r = subprocess.run(cmd, capture_output=True, text=True, start_new_session=True, cwd=src)
        step.update(rc=r.returncode, seconds=round(time.monotonic() - t0, 3))
        self.check_stop("build")
        sdists = sorted((out_dir / "dist").glob("tacfoot-*.tar.gz"))
        if r.returncode != 0 or not sdists:
            raise DeployError(f"step build failed: {r.stderr.strip()[-500:]}")
        return sdists[0]

    def stage(self, sdist: Path, out_dir: Path) -> Path:
        """The release folder, built locally: the sdist, the models (the per-frame
        models fused into one graph, ``models/fused``; each manifest signed), the config (with the public key), the unit, tacfootctl and
        release.json (the SHA-256 of every file; signed)."""
        o = self.o
        st = out_dir / "stage"
        models, cfg = o.models_dir(), o.config_file()
        prof = config_profile_file(cfg) if cfg is not None else None
        check_models_profile(models, cfg)
        self.record("stage", "local", f"stage {sdist.name}"
                    + (f", models {models}" if models else "")
                    + (f", config {cfg}" if cfg else "")
                    + (f", profile {prof.name}" if prof else "") + ", tacfoot.service, tacfootctl"
                    + (f"; sign with key {self.key.key_id} ({self.key.path})" if self.key
                       else "; sign with the host key"))
        if self.dry_run:
            return st
        st.mkdir()
        shutil.copy2(sdist, st / sdist.name)
        if models is not None:
            shutil.copytree(models, st / "models",
                            ignore=shutil.ignore_patterns("__pycache__", "*.pyc", "*.sig"))
            fuse_release_models(st / "models")
            if self.key is not None:
                sign_models(st / "models", self.key)
        if cfg is not None:
            (st / "config").mkdir()
            text = cfg.read_text()
            if self.key is not None:
                text = config_with_key(text, self.key, o.allow_unsigned, str(cfg))
            (st / "config" / cfg.name).write_text(text)
            if prof is not None:       # a calibrated profile named beside the config
                shutil.copy2(prof, st / "config" / prof.name)
        named = replace(o, release=self.release)      # TACFOOT_RELEASE in the service
        (st / "tacfoot.service").write_text(render_unit(named))
        (st / "tacfootctl").write_text(render_ctl(named))
        (st / "tacfootctl").chmod(0o755)
        files = {p.relative_to(st).as_posix(): sha256_file(p)
                 for p in sorted(st.rglob("*")) if p.is_file()}
        (st / "release.json").write_text(json.dumps({
            "release": self.release, "sdist": sdist.name,
            "sdist_sha256": files[sdist.name],
            "built_unix": round(time.time(), 3), "runtime_argv": runtime_argv(o),
            "service_manager": self.manager, "files": files,
            "signed_by": self.key.key_id if self.key else None}, indent=1) + "\n")
        if self.key is not None:
            self.key.sign_file(st / "release.json")
        return st

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

    def resolve_manager(self, info: dict):
        if self.manager == "auto":
            self.manager = info.get("manager") or "systemd"

    # -- the phases of a deploy (host/deploy/robot.py runs them leg by leg) ---------
    def begin(self, res: dict) -> None:
        """Probe the Pi; the release name is made here unless one was given."""
        info = self.probe()
        if self.dry_run and self.manager == "auto":
            res["note"] = "service manager auto: the probe decides; plan shown for systemd"
        self.resolve_manager(info)
        res["service_manager"] = self.manager
        self.old = info["current"] or None
        res["previous"] = self.old
        if not self.release:
            self.release = new_release_name()
        res["release"] = self.release

    def install(self, sdist: Path, tmp: Path) -> None:
        """Stage, prepare, copy and install the new release: everything here writes
        only inside its own folder, so the running release is untouched."""
        o = self.o
        staged = self.stage(sdist, tmp)
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
        # from here the folder is ours to remove (a copy cut short, a failed install);
        # a release of that name that was already there is never touched
        self.created = True
        self.copy(staged, f"{o.prefix}/releases/{self.release}")
        self.remote("install", self._install_script(f"{o.prefix}/releases/{self.release}"),
                    interruptible=True)

    def switch(self, res: dict) -> bool:
        """Point current at the new release, restart the service and check its
        health; True when it is healthy. From the first command on, a failure
        must be undone (:meth:`revert`)."""
        relname = f"releases/{self.release}"
        self.switched = True        # undo from here, even if the switch itself broke off
        self.remote("switch", f"cd {q(self.o.prefix)}\n"
                    f"[ -f {q(relname + '/.complete')} ] || "
                    f"{{ echo 'release {self.release} is incomplete' >&2; exit 3; }}\n"
                    + self._link_script("current", relname))
        self.remote("service", self._service_script())
        h = self.health("health", marker=f"{self.o.prefix}/{relname}/.healthy")
        res["health"] = h
        return bool(self.dry_run or h.get("ok"))

    def commit(self, res: dict) -> None:
        """The new release runs: set previous and prune (a failure is a warning; a
        signal no longer stops anything: the deploy is done)."""
        self.unwinding = True
        relname = f"releases/{self.release}"
        if self.old and self.old != relname:
            st = self.remote("previous", self._link_script("previous", self.old), check=False)
            if st.get("rc"):
                res.setdefault("warnings", []).append("could not set previous")
        st = self.remote("prune", self._prune_script(), check=False)
        if st.get("rc"):
            res.setdefault("warnings", []).append("could not prune old releases")
        res["ok"] = True

    def revert(self, res: dict, exc: BaseException | None) -> None:
        """Put the old release back after a switch (the runtime's last words kept)."""
        self.unwinding = True
        if exc is not None:
            res.setdefault("error", str(exc) or type(exc).__name__)
        if not self.switched:
            return
        try:        # what the new release's runtime said before it is replaced
            res["log_tail"] = self.log_tail()
        except BaseException:
            res["log_tail"] = []
        if res["log_tail"] and (exc is None or isinstance(exc, DeployError)):
            res["error"] = res.get("error", "") + f"; the runtime said: {res['log_tail'][-1]}"
        res["rolled_back"] = True
        res["rollback"] = self._undo(self.old, f"releases/{self.release}")

    def discard(self) -> None:
        """Remove the new release's folder when it never became current (and this
        deploy made it: a release of the same name found on the Pi is kept). The copy
        has ended by then, its writer on the Pi too (:meth:`SshSession.copy`)."""
        self.unwinding = True
        if self.release and self.created and not self.switched:
            rel = f"releases/{self.release}"
            # removed until it stays gone: a writer that outlived its ssh (a stand-in,
            # or a copy whose ssh had to be killed) is given two seconds to end
            self.remote("discard", f"cd {q(self.o.prefix)}\n"
                        f"[ \"$(readlink current || true)\" = {q(rel)} ] || "
                        f"for i in 1 2 3 4 5 6 7 8 9 10; do rm -rf {q(rel)}; sleep 0.2; "
                        f"[ -e {q(rel)} ] || break; done\n",
                        check=False)

    def deploy(self) -> dict:
        o = self.o
        res = {"target": o.target, "prefix": o.prefix, "dry_run": self.dry_run,
               "ok": False, "rolled_back": False}
        self.begin(res)
        with tempfile.TemporaryDirectory(prefix="tacfoot-deploy-") as tmp:
            sdist = self.build_sdist(Path(tmp))
            res["sdist"] = sdist.name
            try:
                self.install(sdist, Path(tmp))
            except DeployError:
                self.discard()
                raise
        try:
            if self.switch(res):
                self.commit(res)
                return res
            raise DeployError(f"health check failed: "
                              f"{res['health'].get('reason', 'unknown')}")
        except BaseException as exc:          # Ctrl-C too: never leave a half switch
            self.revert(res, exc)
            if not isinstance(exc, DeployError):
                raise
            return res

    def _install_script(self, rel: str) -> str:
        o = self.o
        r = q(rel)
        venv_flags = " --system-site-packages --without-pip" if o.system_site_packages else ""
        # offline, pip cannot fetch the build backend either: it builds with the
        # setuptools the venv sees (--system-site-packages)
        pip_flags = " --no-deps --no-index --no-build-isolation" if o.no_deps else ""
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
              "./tacfoot-*.tar.gz\n"
              # the installed code must import before this release may become current
              "venv/bin/python -c 'import device.pi, device.pi.runtime.sdnotify'\n"
              # every file as release.json lists it, and release.json signed with the
              # key the release's config trusts
              f"venv/bin/python -c {q(VERIFY_RELEASE_PY)}\n"
              # pip compiled the frame core for this leg; without a compiler it
              # installed without it and the tracker runs on numpy (same numbers)
              "venv/bin/python -m device.pi.vision.native status >/dev/null || "
              "echo 'tacfoot: no compiled core on this leg (apt install gcc, then deploy "
              "again); the tracker runs on numpy' >&2\n"
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
                out["health"] = self.health("rollback-health",
                                            marker=f"{self.o.prefix}/{old}/.healthy")
                out["ok"] = bool(out["health"].get("ok"))
            else:
                self.remote("rollback-stop", self._stop_script()
                            + f"cd {q(self.o.prefix)}\n" + self._link_script("current", None)
                            + f"touch {q(failed + '/.failed')}\n")
                out["ok"] = True
        except DeployError as exc:
            out.update(ok=False, error=str(exc))
        return out

    def health(self, name: str, marker: str | None = None) -> dict:
        """Whether packets flow from the service (see HEALTH_PY); ``marker`` is
        written on the Pi when they do."""
        step = self.remote(name, self._health_script(marker), check=False,
                           timeout_s=self.o.health_timeout_s + 60, interruptible=True)
        if self.dry_run:
            return {"ok": None}
        try:
            return json.loads(step.get("stdout", "").strip().splitlines()[-1])
        except (ValueError, IndexError):
            return {"ok": False, "reason": "health check gave no answer: "
                    + step.get("stderr", "").strip()[-300:]}

    def running_release(self) -> dict:
        """What runs on the Pi: the release ``current`` names, whether it passed a
        health check (its ``.healthy``), the service's pid and the release that
        process was started from (its ``TACFOOT_RELEASE``; "" when unknown)."""
        o = self.o
        st = self.remote("running", SUDO + f"cd {q(o.prefix)}\n"
                         "cur=$(readlink current || true)\n"
                         "echo current=${cur##*/}\n"
                         "if [ -n \"$cur\" ] && [ -f \"$cur/.healthy\" ]; then echo healthy=yes; "
                         "else echo healthy=no; fi\n"
                         f"pid=$({self._pid_cmd()} 2>/dev/null) || pid=\n"
                         "echo pid=$pid\n"
                         "if [ -n \"$pid\" ]; then\n"
                         "  rel=$( { cat /proc/$pid/environ 2>/dev/null || "
                         "$SUDO cat /proc/$pid/environ 2>/dev/null || true; } | tr '\\0' '\\n' | "
                         "sed -n 's/^TACFOOT_RELEASE=//p')\n"
                         "  echo running=$rel\n"
                         "fi\n", check=False)
        info = {"current": "", "healthy": "", "pid": "", "running": ""}
        for line in st.get("stdout", "").splitlines():
            k, _, v = line.partition("=")
            if k in info:
                info[k] = v.strip()
        return {"current": info["current"] or None, "healthy": info["healthy"] == "yes",
                "pid": int(info["pid"]) if info["pid"].isdigit() else None,
                "running": info["running"] or None}

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
        """Switch current back to previous (and previous to the one we left). A
        failure or a signal after the swap began puts both links back as they were
        and restarts that release (:meth:`_unswap`): never half a rollback."""
        o = self.o
        res = {"target": o.target, "prefix": o.prefix, "dry_run": self.dry_run, "ok": False}
        info = self.probe()
        self.resolve_manager(info)
        res["service_manager"] = self.manager
        cur, prev = info["current"] or None, info["previous"] or None
        if not self.dry_run and not prev:
            raise DeployError(f"no previous release under {o.prefix} to roll back to")
        res.update(release=prev, previous=cur)
        p = q(o.prefix)
        try:
            self.switched = True        # undo from here, even if the swap broke off
            self.remote("switch", f"cd {p}\nprev=$(readlink previous)\ncur=$(readlink current)\n"
                        "[ -f \"$prev/.complete\" ] || "
                        "{ echo \"previous release $prev is incomplete\" >&2; exit 3; }\n"
                        "ln -sfn \"$prev\" .current.tmp\nmv -T .current.tmp current\n"
                        "ln -sfn \"$cur\" .previous.tmp\nmv -T .previous.tmp previous\n")
            self.remote("service", self._service_script())
            res["health"] = self.health("health",
                                        marker=f"{o.prefix}/{prev}/.healthy" if prev else None)
        except BaseException as exc:          # a signal or Ctrl-C too
            res["error"] = str(exc) or type(exc).__name__
            res["undone"] = self._unswap(cur, prev)
            if not isinstance(exc, DeployError):
                raise
            return res
        res["ok"] = True if self.dry_run else bool(res["health"].get("ok"))
        if not res["ok"]:
            res["error"] = f"health check failed: {res['health'].get('reason', 'unknown')}"
        return res

    def _unswap(self, cur: str | None, prev: str | None) -> dict:
        """Undo a rollback's swap: current back to cur, previous back to prev, and
        cur's release restarted and health-checked (the service stopped when there
        was no current). Never interrupted."""
        self.unwinding = True
        p = q(self.o.prefix)
        out = {"to": cur}
        try:
            if cur:
                self.remote("undo-switch", f"cd {p}\n" + self._link_script("current", cur)
                            + self._link_script("previous", prev))
                self.remote("undo-service", self._service_script())
                out["health"] = self.health("undo-health",
                                            marker=f"{self.o.prefix}/{cur}/.healthy")
                out["ok"] = bool(self.dry_run or out["health"].get("ok"))
            else:
                self.remote("undo-stop", self._stop_script() + f"cd {p}\n"
                            + self._link_script("current", None)
                            + self._link_script("previous", prev))
                out["ok"] = True
        except DeployError as exc:
            out.update(ok=False, error=str(exc))
        return out

def run(opts: DeployOptions, dry_run: bool = False, rollback: bool = False,
        log=None, key=None, stop=None) -> dict:
    """Deploy (or roll back); the result dict has ok, release, steps, health.
    ``key`` signs the release (default: the host key of ``opts.signing_key``,
    created on first use; a dry run creates none). ``stop``
    (:class:`host.deploy.ssh.Stop`): a signal that trips it unwinds the deploy;
    ``interrupted`` then names it."""
    if key is None and not rollback:
        key = load_key(opts, dry_run)
    d = Deployer(opts, dry_run=dry_run, log=log, key=key)
    d.stop = stop
    try:
        d.open_connection()
        res = d.rollback() if rollback else d.deploy()
    except DeployError as exc:
        res = {"target": opts.target, "ok": False, "dry_run": dry_run, "error": str(exc)}
    finally:
        d.close_connection()
    res["steps"] = d.steps
    if stop is not None and stop.signal_name:
        res["interrupted"] = stop.signal_name
    return res


def load_key(opts: DeployOptions, dry_run: bool = False):
    """The host's signing key for ``opts`` (None in a dry run when there is none
    yet), and a check that the config can carry its public key; DeployInputError
    if not."""
    path = opts.signing_key or default_key_path()
    key = SigningKey.load(path, create=not dry_run) if (
        not dry_run or Path(path).exists()) else None
    cfg = opts.config_file()
    if key is not None and cfg is not None:
        try:
            text = cfg.read_text()
        except (OSError, UnicodeDecodeError) as exc:
            raise DeployInputError(f"--config {cfg}: cannot read it ({exc})") from None
        config_with_key(text, key, opts.allow_unsigned, str(cfg))
    return key


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
    if "undone" in res:
        un = res["undone"]
        msg += (f"; rollback undone, back on {un.get('to') or 'nothing (service stopped)'}"
                f" ({'ok' if un.get('ok') else 'undo FAILED'})")
    if res.get("rolled_back"):
        rb = res.get("rollback", {})
        msg += (f"; rolled back to {rb.get('to') or 'nothing (service stopped)'}"
                f" ({'ok' if rb.get('ok') else 'rollback FAILED'})")
    return msg
