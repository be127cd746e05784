"""A stand-in ``ssh`` for deploy tests on a machine without an OpenSSH server.

``LocalSsh(folder)`` writes an executable ``ssh`` into ``folder/bin``; put that
folder first on PATH (``env()``) and ``host deploy`` runs every remote step on this
machine: the command is run by ``sh -c`` in a process group of its own, stdin and
stdout passed through. What it imitates of OpenSSH:

- ``-o ControlMaster=yes -o ControlPath=P -f -N``: a master process in the
  background (its own session) listening on the socket P; its pid is written to
  ``folder/masters/<pid>``; ``-O exit`` ends it, ``-O check`` prints its pid;
- port 1 (``-p 1``): ``Connection refused``, exit 255;
- a signal to the client (SIGTERM, SIGHUP, SIGINT) ends the remote command's group,
  whenever it comes (a command not yet started is not started).

A test may ask it to send a signal to the deploy: with ``TRIP_SIGNAL=SIGTERM`` and
``TRIP_WHEN=<text>``, the first remote command holding the text makes it signal its
parent (the deploy) once, before running the command; with ``TRIP_AT=end``, after
the command ended and before the client exits. ``TRIP_REMOTE=stays`` makes that
command behave as OpenSSH does when its client is killed: the remote command is
not ended, it runs on what had reached it, and here it starts as late as it could,
once the next command to the same port has ended (``held_commands`` waits for it).
Until it is signalled or its stdin is closed, that client reads nothing.
"""
from __future__ import annotations

import os
import sys
import time
from pathlib import Path

SCRIPT = r'''#!{python}
import os, select, signal, socket, subprocess, sys, time
FOLDER = {folder!r}
args = sys.argv[1:]
opts, port, op, i = {{}}, None, None, 0
while i < len(args):
    a = args[i]
    if a in ("-o", "-p", "-i", "-O"):
        v = args[i + 1]
        if a == "-o":
            k, _, val = v.partition("=")
            opts[k] = val
        elif a == "-p":
            port = v
        elif a == "-O":
            op = v
        i += 2
    elif a in ("-f", "-N", "-T", "-q"):
        i += 1
    else:
        break
rest = args[i:]
target = rest[0] if rest else ""
cmd = rest[1:]
if cmd and cmd[0] == "--":
    cmd = cmd[1:]
path = opts.get("ControlPath")
if port == "1":
    sys.stderr.write("ssh: connect to host %s port 1: Connection refused\n" % target)
    sys.exit(255)


def talk(word):
    s = socket.socket(socket.AF_UNIX)
    s.settimeout(5)
    s.connect(path)
    s.sendall(word.encode())
    reply = s.recv(100).decode()
    s.close()
    return reply


if op is not None:
    try:
        pid = talk(op)
    except OSError as exc:
        sys.stderr.write("Control socket connect(%s): %s\n" % (path, exc))
        sys.exit(255)
    if op == "check":
        sys.stderr.write("Master running (pid=%s)\r\n" % pid)
    sys.exit(0)
if opts.get("ControlMaster") == "yes":
    if os.fork():
        t0 = time.monotonic()
        while not os.path.exists(path) and time.monotonic() - t0 < 5:
            time.sleep(0.01)
        sys.exit(0 if os.path.exists(path) else 255)
    os.setsid()
    if os.fork():
        os._exit(0)
    os.makedirs(os.path.join(FOLDER, "masters"), exist_ok=True)
    open(os.path.join(FOLDER, "masters", str(os.getpid())), "w").close()
    srv = socket.socket(socket.AF_UNIX)
    srv.bind(path)
    srv.listen(50)
    srv.settimeout(600)
    while True:
        try:
            c, _ = srv.accept()
        except OSError:
            break
        word = c.recv(100).decode()
        c.sendall(str(os.getpid()).encode())
        c.close()
        if word == "exit":
            break
    os.unlink(path)
    os._exit(0)
line = " ".join(cmd)
trip, when = os.environ.get("TRIP_SIGNAL"), os.environ.get("TRIP_WHEN")
tripped = False
if trip and when and when in line:
    try:
        os.close(os.open(os.path.join(FOLDER, "tripped"),
                         os.O_CREAT | os.O_EXCL | os.O_WRONLY))
        tripped = True
    except FileExistsError:
        pass
held = os.path.join(FOLDER, "held-%s" % port)
procs, stopped = [], []


def signal_parent():
    os.kill(os.getppid(), getattr(signal, trip))


def end(signum, frame):
    # the remote command's group goes with the client, whenever the signal comes:
    # before the command started (it is not started), while it starts, or after
    stopped.append(signum)
    if procs:
        try:
            os.killpg(procs[0].pid, signal.SIGTERM)
        except OSError:
            pass
        sys.exit(255)


def gone(signum, frame):
    # OpenSSH: the client goes, its remote command does not; it runs on with what
    # had reached it. Here it starts only once the next command to this port has
    # ended (the latest it could), and touches held-PORT.done when it has run.
    data = b""
    os.set_blocking(0, False)
    try:
        while True:
            chunk = os.read(0, 1 << 16)
            if not chunk:
                break
            data += chunk
    except BlockingIOError:
        pass
    with open(held + ".stdin", "wb") as f:
        f.write(data)
    open(held, "w").close()
    subprocess.Popen(
        ["sh", "-c", 'i=0; while [ ! -e "$1.go" ] && [ $i -lt 3000 ]; do sleep 0.01; '
         'i=$((i+1)); done; sh -c "$2" < "$1.stdin"; touch "$1.done"', "held", held, line],
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        start_new_session=True)
    os._exit(255)


for s in (signal.SIGTERM, signal.SIGHUP, signal.SIGINT):
    signal.signal(s, end)
if tripped and os.environ.get("TRIP_AT", "start") == "start":
    if os.environ.get("TRIP_REMOTE") == "stays":
        for s in (signal.SIGTERM, signal.SIGHUP, signal.SIGINT):
            signal.signal(s, gone)
        signal_parent()
        # nothing is read until the client is signalled (gone) or its stdin closed
        p = select.poll()
        p.register(0, 0)
        while not p.poll(1000):
            pass
        for s in (signal.SIGTERM, signal.SIGHUP, signal.SIGINT):
            signal.signal(s, end)
    else:
        signal_parent()
if not stopped:
    procs.append(subprocess.Popen(["sh", "-c", line], start_new_session=True))
if stopped:
    end(stopped[0], None)
    sys.exit(255)
rc = procs[0].wait()
if tripped and os.environ.get("TRIP_AT") == "end":
    signal_parent()          # the command is done; the client has not exited yet
if not tripped and os.path.exists(held) and not os.path.exists(held + ".go"):
    open(held + ".go", "w").close()
sys.exit(rc)
'''


class LocalSsh:
    def __init__(self, folder: Path):
        self.folder = Path(folder)
        self.bin = self.folder / "bin"
        self.bin.mkdir(parents=True, exist_ok=True)
        self.ssh = self.bin / "ssh"
        self.ssh.write_text(SCRIPT.format(python=sys.executable, folder=str(self.folder)))
        self.ssh.chmod(0o755)

    def env(self) -> dict:
        """PATH with the stand-in first (for monkeypatch.setenv)."""
        return {"PATH": f"{self.bin}{os.pathsep}{os.environ.get('PATH', '')}"}

    def masters(self) -> list[int]:
        d = self.folder / "masters"
        return sorted(int(p.name) for p in d.iterdir()) if d.is_dir() else []

    def live(self) -> list[int]:
        """The pids of stand-in ssh processes (masters and clients) still running."""
        out = []
        for p in Path("/proc").iterdir():
            if not p.name.isdigit():
                continue
            try:
                argv = (p / "cmdline").read_bytes().split(b"\0")
                state = (p / "stat").read_text().rsplit(")", 1)[1].split()[0]
            except OSError:
                continue
            if state != "Z" and str(self.ssh).encode() in argv[:2]:
                out.append(int(p.name))
        return out

    def reset_trip(self):
        (self.folder / "tripped").unlink(missing_ok=True)
        for p in self.folder.glob("held-*"):
            p.unlink()

    def held_commands(self, timeout_s: float = 30) -> int:
        """Wait until every command left running by a killed client (TRIP_REMOTE=stays)
        has run; how many there were."""
        held = [p for p in self.folder.glob("held-*") if "." not in p.name]
        t0 = time.monotonic()
        while not all(Path(f"{p}.done").exists() for p in held):
            assert time.monotonic() - t0 < timeout_s, "a held remote command never ran"
            time.sleep(0.02)
        return len(held)
