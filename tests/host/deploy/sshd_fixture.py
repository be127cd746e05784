"""A real OpenSSH server on loopback for the deploy tests (no conftest needed).

    with SshServer(tmp_path) as srv:
        subprocess.run(srv.ssh_argv("true"))
        srv.target, srv.port, srv.identity, srv.ssh_options

``Pi`` is a deploy target made of such a server and a PREFIX under a temporary
folder, with what the tests ask of it (links, the service's pid, packets flowing).

It generates its own host key and client key, an authorized_keys file and an
sshd config (high port, StrictModes no, no PAM, keys only) and runs
``sshd -D -e -f CONFIG``. Logging in works as the user running the tests: as
root sshd may log in anyone; as another user, only that user.
"""
from __future__ import annotations

import getpass
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from host.deploy.options import DeployOptions
from tests import REPO_ROOT as REPO

SSHD_CANDIDATES = ("/usr/sbin/sshd", "/usr/local/sbin/sshd", "/sbin/sshd")


def find_sshd() -> str | None:
    for p in SSHD_CANDIDATES:
        if os.access(p, os.X_OK):
            return p
    return None


def missing_reason() -> str | None:
    """Why the tests cannot run a server here, or None if they can."""
    if find_sshd() is None:
        return "OpenSSH server not installed (apt-get install openssh-server)"
    for tool in ("ssh", "ssh-keygen"):
        if shutil.which(tool) is None:
            return f"{tool} not found (apt-get install openssh-client)"
    return None


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class SshServer:
    def __init__(self, workdir: Path, env: dict | None = None):
        """env: variables sshd sets in every session (SetEnv), e.g. a PATH."""
        self.dir = Path(workdir) / "sshd"
        self.env = dict(env or {})
        self.user = getpass.getuser()
        self.proc: subprocess.Popen | None = None
        self.port = 0

    @property
    def target(self) -> str:
        return f"{self.user}@127.0.0.1"

    @property
    def identity(self) -> str:
        return str(self.dir / "client_key")

    ssh_options = ["StrictHostKeyChecking=no", "UserKnownHostsFile=/dev/null",
                   "LogLevel=ERROR"]

    def ssh_argv(self, command: str) -> list[str]:
        argv = ["ssh", "-p", str(self.port), "-i", self.identity, "-o", "BatchMode=yes",
                "-o", "IdentitiesOnly=yes"]
        for o in self.ssh_options:
            argv += ["-o", o]
        return argv + [self.target, command]

    def _keygen(self, path: Path):
        subprocess.run(["ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-C", "tacfoot-test",
                        "-f", str(path)], check=True, capture_output=True)

    def start(self, timeout_s: float = 10.0):
        self.dir.mkdir(parents=True, exist_ok=True)
        self._keygen(self.dir / "host_key")
        self._keygen(self.dir / "client_key")
        shutil.copy(self.dir / "client_key.pub", self.dir / "authorized_keys")
        if os.geteuid() == 0:           # sshd as root insists on its privsep folder
            Path("/run/sshd").mkdir(mode=0o755, exist_ok=True)
        last = ""
        for _ in range(5):              # the free port may be taken in between: retry
            self.port = _free_port()
            cfg = self.dir / "sshd_config"
            cfg.write_text(
                f"Port {self.port}\nListenAddress 127.0.0.1\n"
                f"HostKey {self.dir / 'host_key'}\nPidFile {self.dir / 'sshd.pid'}\n"
                f"AuthorizedKeysFile {self.dir / 'authorized_keys'}\n"
                "StrictModes no\nUsePAM no\nPubkeyAuthentication yes\n"
                "PasswordAuthentication no\nKbdInteractiveAuthentication no\n"
                "PermitRootLogin prohibit-password\nMaxStartups 50\nMaxSessions 50\n"
                "LogLevel ERROR\nSubsystem sftp internal-sftp\n"
                # one SetEnv line: sshd keeps the first value of each keyword
                + ("SetEnv " + " ".join(f"{k}={v}" for k, v in self.env.items()) + "\n"
                   if self.env else ""))
            log = open(self.dir / "sshd.log", "ab")
            self.proc = subprocess.Popen([find_sshd(), "-D", "-e", "-f", str(cfg)],
                                         stdout=log, stderr=log, stdin=subprocess.DEVNULL)
            log.close()
            t0 = time.monotonic()
            while time.monotonic() - t0 < timeout_s and self.proc.poll() is None:
                r = subprocess.run(self.ssh_argv("echo ok"), capture_output=True, text=True,
                                   timeout=timeout_s)
                if r.stdout.strip() == "ok":
                    return self
                last = r.stderr.strip()
                time.sleep(0.1)
            self.stop()
        raise RuntimeError(f"sshd did not come up: {last} / "
                           f"{(self.dir / 'sshd.log').read_text()[-500:]}")

    def stop(self):
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.proc = None

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()


class Pi:
    """The deploy target: sshd on loopback plus a PREFIX under tmp."""

    def __init__(self, srv: SshServer, root: Path):
        self.srv = srv
        self.root = root
        self.prefix = root / "opt" / "tacfoot"
        self.config = root / "leg.toml"
        self.key_path = root / "signing-key.pem"
        src = REPO / "device" / "leg.toml"
        self.config.write_text(src.read_text() if src.is_file() else "# default\n")

    def opts(self, **kw) -> DeployOptions:
        base = dict(target=self.srv.target, port=self.srv.port, identity=self.srv.identity,
                    ssh_options=list(self.srv.ssh_options), prefix=str(self.prefix),
                    python=sys.executable, service_manager="none",
                    system_site_packages=True, no_deps=True, config=str(self.config),
                    # an endless-enough source: 720 frames paced at 15 fps (48 s)
                    camera="sim://walk?realtime=1&fps=15", imu="sim://walk", serial="loop://",
                    runtime_args=["--fps", "15"], health_timeout_s=20.0,
                    signing_key=str(self.key_path))
        base.update(kw)
        return DeployOptions(**base)

    def link(self, name) -> str | None:
        p = self.prefix / name
        return os.readlink(p) if p.is_symlink() else None

    def pid(self) -> int | None:
        try:
            pid = int((self.prefix / "run" / "tacfoot.pid").read_text())
            os.kill(pid, 0)
            return pid
        except (OSError, ValueError):
            return None

    def tag(self, pid: int) -> str | None:
        env = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
        for kv in env:
            if kv.startswith(b"TAG="):
                return kv[4:].decode()
        return None

    def packets_flow(self, pid: int, within_s: float = 15.0) -> bool:
        """The status file is from pid and its packets_sent grows."""
        first = None
        t0 = time.monotonic()
        while time.monotonic() - t0 < within_s:
            try:
                st = json.loads((self.prefix / "run" / "status.json").read_text())
            except (OSError, ValueError):
                st = {}
            if st.get("pid") == pid:
                if first is None:
                    first = st["packets_sent"]
                elif st["packets_sent"] > first:
                    return True
            time.sleep(0.1)
        return False

    def stop_all(self):
        ctl = self.prefix / "current" / "tacfootctl"
        if ctl.exists():
            subprocess.run([str(ctl), "stop"], capture_output=True, timeout=30)
        pid = self.pid()
        if pid:
            os.kill(pid, signal.SIGKILL)
