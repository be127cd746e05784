"""Tell systemd how the runtime is doing: the sd_notify protocol, pure stdlib.

systemd starts a ``Type=notify`` service with ``NOTIFY_SOCKET`` set to the path
of a unix datagram socket (a leading ``@`` means the Linux abstract namespace).
The service sends newline-separated ``KEY=VALUE`` lines there: ``READY=1`` once it
is up, ``WATCHDOG=1`` at least once per ``WatchdogSec``, ``STATUS=...`` free text.
With ``WatchdogSec=`` set, systemd also exports ``WATCHDOG_USEC`` (the interval in
microseconds) and ``WATCHDOG_PID`` (the pid that must send the pings).

Nothing here raises: without a socket (run by hand, in tests, on the host)
every call is a no-op that returns False, so the runtime calls it unconditionally.

    from device.pi.runtime import sdnotify
    sdnotify.notify("READY=1")
    dog = sdnotify.Watchdog()            # None interval -> tick() never pings
    while running:
        ...
        dog.tick(time.monotonic())
"""
from __future__ import annotations

import os
import socket

__all__ = ["notify", "watchdog_interval_s", "Watchdog"]

_FROM_ENV = object()      # Watchdog(): read the interval from the environment


def _address(raw: str) -> str | bytes | None:
    """The socket address for a NOTIFY_SOCKET value, or None if unusable."""
    if not raw:
        return None
    if raw[0] == "@":                       # abstract namespace: leading NUL byte
        return b"\0" + raw[1:].encode()
    if raw[0] == "/":
        return raw
    return None                             # vsock etc. are not supported here


def notify(state: str, env: dict | None = None) -> bool:
    """Send ``state`` (e.g. ``"READY=1"``) to systemd; True if it was sent.

    Returns False, without raising, when NOTIFY_SOCKET is unset or unusable or
    the send fails. ``env`` defaults to ``os.environ`` (tests pass their own).
    """
    env = os.environ if env is None else env
    try:
        addr = _address(env.get("NOTIFY_SOCKET", ""))
        if addr is None or not state:
            return False
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as s:
            s.sendto(state.encode("utf-8", "replace"), addr)
        return True
    except (OSError, ValueError, TypeError, AttributeError):
        return False


def watchdog_interval_s(env: dict | None = None) -> float | None:
    """The watchdog interval systemd expects pings within, in seconds.

    None when WATCHDOG_USEC is unset, not a positive integer, or WATCHDOG_PID
    names another process (the pings are then not ours to send).
    """
    env = os.environ if env is None else env
    try:
        usec = int(env.get("WATCHDOG_USEC", ""))
    except (TypeError, ValueError):
        return None
    if usec <= 0:
        return None
    pid = env.get("WATCHDOG_PID")
    if pid:
        try:
            if int(pid) != os.getpid():
                return None
        except ValueError:
            return None
    return usec / 1e6


class Watchdog:
    """Pings ``WATCHDOG=1`` at half the watchdog interval from a loop.

    ``interval_s`` defaults to ``watchdog_interval_s()``; with None, tick() never
    pings. ``tick(now_s)`` takes a monotonic time in seconds and returns True
    when it sent a ping this call. ``pings`` counts pings sent.
    """

    def __init__(self, interval_s=_FROM_ENV, env: dict | None = None):
        self.env = env
        if interval_s is _FROM_ENV:
            interval_s = watchdog_interval_s(env)
        if interval_s is not None and not (isinstance(interval_s, (int, float))
                                           and 0 < interval_s < float("inf")):
            raise ValueError(f"interval_s must be > 0 or None, got {interval_s!r}")
        self.interval_s = interval_s
        self.period_s = None if interval_s is None else interval_s / 2.0
        self._last_s: float | None = None
        self.pings = 0

    @property
    def enabled(self) -> bool:
        return self.period_s is not None

    def tick(self, now_s: float) -> bool:
        if self.period_s is None:
            return False
        if (self._last_s is not None and 0 <= now_s - self._last_s < self.period_s):
            return False                   # (a clock that went back pings at once)
        self._last_s = now_s
        if notify("WATCHDOG=1", self.env):
            self.pings += 1
            return True
        return False
