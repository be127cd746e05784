"""The leg's MCAP log and live view, written by a child process (the runtime's
default, ``[mcap] writer = "process"``; docs/viewing.md).

Encoding the messages (JSON templates, the JPEG, the pin annotations), compressing
the chunks and serving viewers is about 0.3-0.7 ms of Python a frame. In a thread of
the runtime's process it holds the GIL the loop needs, and cost the loop a third of
its throughput (docs/BENCHMARKS.md). :class:`McapProcess` keeps only the front on
the loop's side: per frame it computes the log times and copies what the messages
need (as :class:`~device.pi.runtime.mcaplog.McapLog` does), and queues it; a sender
thread hands the queue to the child in batches, one pickled list every
:data:`~device.pi.runtime.mcaplog.WRITER_POLL_S`. The child
(``python -m device.pi.runtime.mcapproc``, started with the runtime's interpreter)
is an :class:`McapLog` that writes in its own thread, with the live view
(``--foxglove``) in it too; it runs on another core, at a lower priority
(:data:`WRITER_NICE`): the leg's loop comes first.

What the thread writer promised holds here:

- the queue holds :data:`~device.pi.runtime.mcaplog.QUEUE_ITEMS` frames and packets;
  when the child falls that far behind, the oldest is dropped and counted
  (``mcap_dropped``, ``mcap_messages_lost``);
- the log never raises into the loop: the child's failed writes are counted in its
  status, which it sends back every :data:`STATUS_EVERY_S`; a child that died is
  counted too (what was queued and sent after its last status is lost) and warned
  about once;
- a crash of the runtime does not cost the file: the child ignores SIGINT and
  SIGTERM (a Ctrl-C or systemd reaches the whole group), and when its parent is
  gone (the pipe ends) it writes what it has and ends the file with its summary;
- :meth:`McapProcess.close` waits at most ``CLOSE_WAIT_S`` (or until ``close_by``)
  for the child's last status, then stops it; what it had not written is lost.

A bad ``--mcap`` path or a ``--foxglove`` port that cannot be served is refused
at start-up in one line, as before: the child reports its first file and port, or
the error, before the loop starts (:data:`START_WAIT_S`).
"""
from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import threading
import time
from multiprocessing.connection import Connection
from pathlib import Path

from device.errors import TacfootError
from device.pi.runtime import mcapmsg as M
from device.pi.runtime.mcapfiles import McapLogError
from device.pi.runtime.mcaplog import CLOSE_WAIT_S, WRITER_POLL_S, McapLog

__all__ = ["McapProcess", "START_WAIT_S", "STATUS_EVERY_S", "WRITER_NICE", "serve"]

_log = logging.getLogger(__name__)

#: the child's first file and live view must be ready within this, s
START_WAIT_S = 30.0
#: the child sends its counts this often, s
STATUS_EVERY_S = 0.25
#: the child's nice value: the log yields the CPU to the leg's loop, never the reverse
#: (when it falls behind, the oldest frames are dropped and counted)
WRITER_NICE = 10
#: the messages the child takes (McapLog's writing methods); nothing else is called
_CALLS = ("_frame", "_packet", "_record", "_write_doc", "_image")


def _package_root() -> str:
    return str(Path(__file__).resolve().parents[3])


class McapProcess(McapLog):
    """:class:`McapLog`'s interface; the log is written by a child process (module
    doc). ``foxglove`` is ``(host, port)`` for a live view, or None; ``max_clients``
    its viewer limit."""

    def __init__(self, path, cfg, *, max_mb: float = 256.0, clock=None, foxglove=None,
                 max_clients: int | None = None, keep_existing: bool = False,
                 prog: str = "device.pi run", metadata: dict | None = None,
                 records: str | None = None):
        if path is None and foxglove is None:
            raise McapLogError("McapLog needs a file (--mcap), a live view (--foxglove) "
                               "or both; got neither")
        self._setup(cfg, clock, prog, keep_existing, metadata, None)
        self.live = None
        self.path = None if path is None else Path(path)
        self._file_on = path is not None
        self._child: dict = {}           # the child's last status
        self._sent = 0                   # messages handed to the child
        self._dead = False
        self._final = False
        self.sender_cpu_s = 0.0
        self.host = self.port = None
        self._spawn(dict(path=None if path is None else str(path), cfg=cfg,
                         max_mb=float(max_mb), foxglove=foxglove, max_clients=max_clients,
                         keep_existing=keep_existing, prog=prog, metadata=self.metadata,
                         log_level=logging.getLogger("device").getEffectiveLevel()))
        self._start(records, background=True)

    # -- the child ------------------------------------------------------------------
    def _spawn(self, spec: dict) -> None:
        from_parent, to_child = os.pipe()        # (read end, write end)
        from_child, to_parent = os.pipe()
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(
            [_package_root()] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
        try:
            self._proc = subprocess.Popen(     # with this interpreter's flags (-I ...)
                [sys.executable, *subprocess._args_from_interpreter_flags(), "-m",
                 "device.pi.runtime.mcapproc", str(from_parent), str(to_parent)],
                pass_fds=(from_parent, to_parent), env=env, stdin=subprocess.DEVNULL)
        except OSError as exc:
            for fd in (to_child, from_parent, from_child, to_parent):
                os.close(fd)
            raise McapLogError(f"cannot start the MCAP writer process ({exc})") from None
        os.close(from_parent)
        os.close(to_parent)
        self._out, self._in = Connection(to_child, readable=False), Connection(from_child,
                                                                              writable=False)
        try:
            self._out.send(spec)
            reply = self._in.recv() if self._in.poll(START_WAIT_S) else ("error", None)
        except (OSError, EOFError):
            reply = ("error", None)
        if reply[0] != "ready":
            self._stop_child(0.0)
            self._in.close()
            why = reply[1] or f"the MCAP writer process did not start within {START_WAIT_S:g} s"
            raise McapLogError(why)
        self._take(reply[1])
        self.host, self.port = self._child.get("foxglove_host"), self._child.get("foxglove_port")

    def _take(self, st: dict) -> None:
        self._child = st
        self.files = list(st.get("mcap_files", []))

    def _read(self) -> None:
        """The child's statuses that have come (the newest wins); a closed pipe is a
        child that died."""
        try:
            while self._in.poll():
                kind, st = self._in.recv()
                self._take(st)
                self._final = self._final or kind == "final"
        except (OSError, EOFError):
            self._died()

    def _died(self) -> None:
        if self._dead:
            return
        self._dead = True
        if self._final:
            return
        if not self.warned:
            self.warned = True
            _log.warning("%s: warning: the MCAP writer process ended (exit %s); running "
                         "on, counting the lost messages", self.prog, self._proc.poll())

    def _anyone(self) -> bool:
        return self._file_on or bool(self._child.get("foxglove_any"))

    def _do(self, fn, args: tuple, n_msgs: int) -> None:
        if self._dead:                   # no writer: the messages are lost, counted
            self._dropped_msgs += n_msgs
        else:
            self._put((fn,) + args, n_msgs)

    # -- the sender thread ------------------------------------------------------------
    def _drain(self) -> None:
        """Hand what is queued to the child, a batch per pass, until closed."""
        q, wake = self._q, self._wake
        c0 = time.thread_time()
        while True:
            self.sender_cpu_s = time.thread_time() - c0
            closing = self._closing      # read first: all queued before close() is taken
            batch, n = [], 0
            while True:
                try:
                    fn, *args, k = q.popleft()
                except IndexError:
                    break
                if fn.__name__ == "_frame" and args[3] is not None:
                    args[3] = self._encoded(args[3])
                batch.append((fn.__name__, tuple(args)))
                n += k
            self._read()
            if batch and not self._dead:
                try:
                    self._out.send(batch)
                    self._sent += n
                except (OSError, ValueError, TypeError):    # the child gone, or close()
                    self._died()
            if self._dead:
                self._dropped_msgs += n if batch else 0
            if not batch:
                if closing or self._dead:
                    return
                wake.wait(WRITER_POLL_S)
            self._done += 1

    def _encoded(self, img: tuple) -> tuple:
        """An image frame's camera frame as its (JPEG, scale), made here: OpenCV lets
        the GIL go while it resizes and encodes, and 20 kB cross the pipe, not the
        frame; one it cannot encode goes as it is (the child counts the failure)."""
        try:
            return (M.jpeg(img[0], self.cfg.image_width, self.cfg.jpeg_quality),) + img[1:]
        except Exception:
            return img

    def close(self) -> None:
        """Send what is queued, have the child end its file and stop its live view,
        and wait for its last count, within ``CLOSE_WAIT_S`` or ``close_by``: the end
        is the pipe's end (which never blocks); a child not done by then is stopped."""
        if self._records is not None:
            self._records[0].removeHandler(self._records[1])
            self._records = None
        if self._thread is None:
            return
        now = time.monotonic()
        end = now + CLOSE_WAIT_S
        if self.close_by is not None:
            end = min(end, max(self.close_by, now + 0.05))
        self._closing = True
        self._wake.set()
        self._thread.join(max(0.0, end - time.monotonic()))
        if self._thread.is_alive():              # stuck sending to a stuck child:
            self._dead = True                    # its send fails once the child is gone
            self._proc.kill()
            self._thread.join(0.5)
        self._out.close()                        # the end: the child finishes its file
        while not self._final and not self._dead and time.monotonic() < end:
            if self._in.poll(min(0.05, max(0.0, end - time.monotonic()))):
                self._read()
        if not self._final:                      # too late: stopped, its rest lost
            self._dead = True
        self._stop_child(max(0.0, end - time.monotonic()))
        if not self._thread.is_alive():
            self._read()                         # a last count sent while it ended
            self._in.close()
        if self._q:                              # never sent
            self._dropped_msgs += sum(x[-1] for x in self._q)
            self._q.clear()
        self._thread = None

    def _stop_child(self, wait_s: float) -> None:
        try:
            self._out.close()
        except Exception:
            pass
        try:
            self._proc.wait(wait_s)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()

    def _counts(self) -> tuple[int, int]:
        """(written, lost). A child that died without its last count lost what it had
        been sent since its last count, and the chunk it had not yet written."""
        c = self._child
        written = c.get("mcap_messages_written", 0)
        lost = c.get("mcap_messages_lost", 0) + self._dropped_msgs
        if self._dead and not self._final:
            lost += max(0, self._sent - written - c.get("mcap_messages_lost", 0))
            unflushed = min(written, c.get("mcap_unflushed", 0))
            written, lost = written - unflushed, lost + unflushed
        return written, lost

    @property
    def messages_lost(self) -> int:
        return self._counts()[1]

    def status(self) -> dict:
        c = self._child
        written, lost = self._counts()
        st = {"mcap_messages_written": written,
              "mcap_messages_lost": lost, "mcap_dropped": self.dropped,
              "mcap_files": list(self.files),
              "mcap_file": self.files[-1] if self.files else None,
              "mcap_loop_cpu_s": round(self.loop_cpu_s, 4),
              "mcap_time_clamped": c.get("mcap_time_clamped", 0),
              "mcap_writer": "process",
              "mcap_sender_cpu_s": round(self.sender_cpu_s, 4),
              "mcap_writer_cpu_s": c.get("mcap_writer_cpu_s", 0.0)}
        st.update({k: v for k, v in c.items() if k.startswith("foxglove_")
                   and k not in ("foxglove_any", "foxglove_host")})
        return st


# -- the child's side ------------------------------------------------------------------
_CPU0 = [0.0]       # the child's CPU when its log was open (its start-up is not the log's)


def _child_status(log: McapLog) -> dict:
    st = log.status()
    st["mcap_writer_cpu_s"] = round(time.process_time() - _CPU0[0], 4)
    st["mcap_unflushed"] = log._file_msgs - log._file_kept    # in the chunk being filled
    if log.live is not None:
        st["foxglove_any"] = log.live.any()
        st["foxglove_host"] = log.live.host
    return st


def _open(spec: dict) -> McapLog:
    from device.pi.runtime.liveview import LiveView
    live = None
    if spec["foxglove"] is not None:
        live = LiveView(*spec["foxglove"], max_clients=spec["max_clients"])
    try:
        return McapLog(spec["path"], spec["cfg"], max_mb=spec["max_mb"], clock=time.monotonic,
                       live=live, keep_existing=spec["keep_existing"], prog=spec["prog"],
                       metadata=spec["metadata"])
    except BaseException:
        if live is not None:
            live.close()
        raise


def serve(inp: Connection, out: Connection) -> int:
    """The child: open the log, write each batch the parent sends, send the counts
    every :data:`STATUS_EVERY_S`; at the end (``None``, or the pipe closed by a
    parent that is gone) end the file and send the last count."""
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)      # the parent decides when the log ends
    try:                # not the loop's real-time policy (the unit's option), lower nice
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except (OSError, AttributeError):
        pass
    try:
        os.nice(WRITER_NICE)
    except OSError:
        pass
    try:
        spec = inp.recv()
        logging.getLogger("device").setLevel(spec["log_level"])
        log = _open(spec)
    except TacfootError as exc:
        out.send(("error", str(exc)))
        return 2
    except (EOFError, OSError):
        return 2
    _CPU0[0] = time.process_time()
    out.send(("ready", _child_status(log)))
    last = time.monotonic()
    while True:
        try:
            batch = inp.recv() if inp.poll(STATUS_EVERY_S) else ()
        except (EOFError, OSError):
            batch = None
        if batch is None:
            break
        for name, args in batch:
            if name in _CALLS:
                try:
                    getattr(log, name)(*args)
                except Exception as exc:     # never ends the log
                    log._fail(exc)
        now = time.monotonic()
        if now - last >= STATUS_EVERY_S:
            last = now
            try:
                out.send(("status", _child_status(log)))
            except OSError:
                pass
    log.close()
    try:
        out.send(("final", _child_status(log)))
    except OSError:
        pass
    return 0


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    inp = Connection(int(argv[0]), writable=False)
    out = Connection(int(argv[1]), readable=False)
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    return serve(inp, out)


if __name__ == "__main__":
    sys.exit(main())
