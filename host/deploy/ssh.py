"""One SSH session to a Pi for ``host deploy``: every step is one ``ssh`` command
running a small POSIX shell script (``sh -c``, ``set -eu``), over one shared
connection (ControlMaster), logged with its command; a dry run only records them.
:meth:`SshSession.copy` streams a local folder as a tar over the same connection.

A signal (SIGTERM, SIGHUP, SIGINT) during a deploy trips the shared :class:`Stop`:
a step that only waits (install, health) is cut short, the copy's stream ends where
it is (its ssh is then let finish: see :meth:`SshSession.copy`), any other step is
let finish, and the next step raises :class:`DeployInterrupted`, so the deploy unwinds
as after a failed step (the steps that put the old release back still run). Every
``ssh`` runs in its own session, so Ctrl-C in the terminal reaches only ``host``."""
from __future__ import annotations

import logging
import os
import re
import select
import shutil
import signal
import subprocess
import tarfile
import tempfile
import threading
import time
from pathlib import Path

from host.deploy.options import DeployError, DeployOptions
from host.deploy.scripts import HEALTH_PY, VERIFY_RELEASE_PY, q


class DeployInterrupted(DeployError):
    """A signal stopped the deploy; the message names the signal and the step."""


class Stop:
    """Set by a signal handler, shared by every leg's session: which signal asked the
    deploy to stop (None: none), and the running ``ssh`` processes that may be cut
    short when it does."""

    def __init__(self):
        self.signal_name: str | None = None
        self._procs: set = set()
        self._lock = threading.Lock()

    def trip(self, name: str) -> bool:
        """Stop (the first signal counts); True the first time. Safe in a signal handler."""
        first = self.signal_name is None
        if first:
            self.signal_name = name
        for proc in list(self._procs):
            try:
                proc.terminate()
            except OSError:
                pass
        return first

    def track(self, proc, on: bool) -> None:
        with self._lock:
            (self._procs.add if on else self._procs.discard)(proc)
        if on and self.signal_name is not None:
            proc.terminate()


class SshSession:
    """Runs (or, with dry_run, only records) remote steps on ``opts``' target."""


    def __init__(self, opts: DeployOptions, dry_run: bool = False, log=None):
        opts.check()
        self.o = opts
        self.dry_run = dry_run
        self.log = log if log is not None else logging.getLogger(__name__).info
        self.steps: list[dict] = []
        self.copy_hook = None          # called (proc, bytes_sent) while copying
        self._cm_dir: str | None = None          # ssh ControlMaster socket folder
        self.stop: Stop | None = None            # shared by the legs of one deploy
        self.unwinding = False                   # putting things back: never interrupted

    def check_stop(self, name: str) -> None:
        """DeployInterrupted when a signal stopped the deploy (unless unwinding)."""
        if self.stop is not None and self.stop.signal_name and not self.unwinding:
            raise DeployInterrupted(f"stopped by {self.stop.signal_name} at step {name}")

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
                               stderr=subprocess.DEVNULL, timeout=60, start_new_session=True)
            ok = r.returncode == 0 and os.path.exists(f"{d}/cm")
        except subprocess.TimeoutExpired:
            ok = False
        if ok:
            self._cm_dir = d
        else:
            shutil.rmtree(d, ignore_errors=True)

    def close_connection(self):
        """Close the shared connection: ``ssh -O exit``; a master that does not go
        is killed (its pid from ``ssh -O check``)."""
        if self._cm_dir is None:
            return
        d, self._cm_dir = self._cm_dir, None
        base = self._ssh_base() + ["-o", f"ControlPath={d}/cm"]

        def ctl(op):
            try:
                return subprocess.run(base + ["-O", op, self.o.ssh_target],
                                      stdin=subprocess.DEVNULL, capture_output=True,
                                      text=True, timeout=15, start_new_session=True)
            except subprocess.TimeoutExpired:
                return None
        ctl("exit")
        t0 = time.monotonic()
        while os.path.exists(f"{d}/cm") and time.monotonic() - t0 < 2:
            time.sleep(0.05)
        if os.path.exists(f"{d}/cm"):
            r = ctl("check")
            m = re.search(r"pid=(\d+)", (r.stderr + r.stdout) if r else "")
            if m:
                try:
                    os.kill(int(m[1]), signal.SIGKILL)
                except OSError:
                    pass
        shutil.rmtree(d, ignore_errors=True)

    def ssh_argv(self, script: str) -> list[str]:
        return self._ssh_base() + [self.o.ssh_target, "--", "sh -c " + q("set -eu\n" + script)]

    def record(self, name, where, command, **extra) -> dict:
        step = {"step": name, "where": where, "command": command, **extra}
        self.steps.append(step)
        shown = command.replace(q(HEALTH_PY), '"$HEALTH_CHECK_PY"').replace(
            q(VERIFY_RELEASE_PY), '"$VERIFY_RELEASE_PY"')
        self.log(f"[deploy] {name} ({where}): " + shown.strip().replace("\n", "; "))
        return step

    def remote(self, name: str, script: str, check: bool = True, timeout_s: float = 600,
               keep_chars: int = 2000, interruptible: bool = False):
        """Run ``script`` on the Pi; the step records the last ``keep_chars`` of its
        output. DeployError naming the step when it fails and ``check``;
        DeployInterrupted when a signal stopped the deploy (an ``interruptible``
        step is cut short then, any other is let finish first)."""
        self.check_stop(name)
        step = self.record(name, "remote", script)
        if self.dry_run:
            return step
        t0 = time.monotonic()
        proc = subprocess.Popen(self.ssh_argv(script), stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True,
                                start_new_session=True)
        if interruptible and self.stop is not None and not self.unwinding:
            self.stop.track(proc, True)
        try:
            out, err = proc.communicate(timeout=timeout_s)
            rc = proc.returncode
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()
            rc, out, err = -1, "", f"timed out after {timeout_s:.0f} s"
        finally:
            if self.stop is not None:
                self.stop.track(proc, False)
        step.update(rc=rc, seconds=round(time.monotonic() - t0, 3), stdout=out[-keep_chars:],
                    stderr=err[-2000:])
        self.check_stop(name)
        if rc != 0:
            self.log(f"[deploy] {name}: exit {rc}: {err.strip()[-500:]}")
            if check:
                raise DeployError(f"step {name} failed (exit {rc}): "
                                  f"{err.strip().splitlines()[-1] if err.strip() else ''}")
        return step


    #: how long a copy cut short by a signal waits for the Pi's tar to end (it ends
    #: at once on the cut stream) before its ssh is killed
    COPY_END_S = 15.0

    def copy(self, staged: Path, rel: str):
        """Stream the local folder ``staged`` as a tar over one ssh into the remote
        folder ``rel`` (made if missing).

        A signal ends the stream where it is, and the ssh is then let finish: it exits
        only once the Pi's tar has, so when the deploy removes the folder nothing is
        still writing into it. (Killing the ssh would not stop that tar: OpenSSH leaves
        a remote command running when its client dies, and it would go on extracting
        what had reached it, beside or after the removal.) Only a Pi that does not
        answer within ``COPY_END_S`` after the signal gets its ssh killed."""
        script = f"mkdir -p {q(rel)}\ntar -xzf - -C {q(rel)}\n"
        self.check_stop("copy")
        step = self.record("copy", "remote", f"tar -czf - -C {staged} . | ssh ... "
                            + script.strip().replace("\n", "; "))
        if self.dry_run:
            return
        t0 = time.monotonic()
        with tempfile.TemporaryFile() as err:
            proc = subprocess.Popen(self.ssh_argv(script), stdin=subprocess.PIPE,
                                    stdout=subprocess.DEVNULL, stderr=err,
                                    start_new_session=True)
            fd = proc.stdin.fileno()
            os.set_blocking(fd, False)      # a stalled link never keeps a signal waiting
            sent = 0
            hook = self.copy_hook
            try:
                class _Counting:
                    def write(_self, b):
                        nonlocal sent
                        view = memoryview(b)
                        while view:
                            self.check_stop("copy")
                            select.select([], [fd], [], 0.2)
                            try:
                                n = os.write(fd, view)
                            except BlockingIOError:
                                continue
                            view, sent = view[n:], sent + n
                        if hook is not None:
                            hook(proc, sent)
                        return len(b)

                    def flush(_self):
                        pass

                with tarfile.open(fileobj=_Counting(), mode="w|gz") as tar:
                    tar.add(staged, arcname=".")
            except (OSError, ValueError, DeployInterrupted):
                pass        # the stream ends here; how the ssh exits says the rest
            finally:
                try:
                    proc.stdin.close()      # the end of the stream: the Pi's tar ends
                except OSError:
                    pass
                rc, note = self._wait_copy(proc)
            err.seek(0)
            msg = err.read().decode(errors="replace").strip()
        step.update(rc=rc, bytes=sent, seconds=round(time.monotonic() - t0, 3),
                    stderr=(msg + note)[-2000:])
        self.check_stop("copy")
        if rc != 0:
            raise DeployError(f"step copy failed (exit {rc}) after {sent} bytes"
                              + (f": {(msg + note).splitlines()[-1]}" if msg + note else ""))

    def _wait_copy(self, proc) -> tuple[int, str]:
        """The copy's exit status once its ssh ended (so the Pi's tar has), and a note
        when it had to be killed: 600 s after the end of the stream, or ``COPY_END_S``
        after a signal."""
        t0, stopped_at = time.monotonic(), None
        while True:
            try:
                return proc.wait(timeout=0.2), ""
            except subprocess.TimeoutExpired:
                pass
            now = time.monotonic()
            if stopped_at is None and self.stop is not None and self.stop.signal_name:
                stopped_at = now
            if now - t0 > 600 or (stopped_at is not None
                                  and now - stopped_at > self.COPY_END_S):
                proc.kill()
                why = (f"{self.COPY_END_S:g} s after {self.stop.signal_name}"
                       if stopped_at is not None else "600 s")
                return proc.wait(), f"\nthe Pi's tar had not ended {why}; its ssh was killed"
