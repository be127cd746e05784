"""The systemd interface (device/pi/runtime/sdnotify.py): notify over a path or an
abstract socket, False (never an exception) without one, and the watchdog interval
and pings."""
from __future__ import annotations

import os
import socket
import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from device.pi.runtime import sdnotify


def _dgram_server(addr):
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.bind(addr)
    s.settimeout(2.0)
    return s


def test_notify_reaches_a_path_socket(tmp_path):
    path = str(tmp_path / "notify.sock")
    with _dgram_server(path) as srv:
        assert sdnotify.notify("READY=1", {"NOTIFY_SOCKET": path}) is True
        assert srv.recv(256) == b"READY=1"
        assert sdnotify.notify("STATUS=frames 12\nWATCHDOG=1", {"NOTIFY_SOCKET": path})
        assert srv.recv(256) == b"STATUS=frames 12\nWATCHDOG=1"


def test_notify_reaches_an_abstract_socket():
    name = f"tacfoot-test-{os.getpid()}-{time.monotonic_ns()}"
    with _dgram_server("\0" + name) as srv:
        assert sdnotify.notify("READY=1", {"NOTIFY_SOCKET": "@" + name}) is True
        assert srv.recv(256) == b"READY=1"


def test_notify_uses_os_environ(tmp_path, monkeypatch):
    path = str(tmp_path / "n.sock")
    with _dgram_server(path) as srv:
        monkeypatch.setenv("NOTIFY_SOCKET", path)
        assert sdnotify.notify("READY=1")
        assert srv.recv(64) == b"READY=1"
    monkeypatch.delenv("NOTIFY_SOCKET")
    assert sdnotify.notify("READY=1") is False


@pytest.mark.parametrize("value", ["", "relative/sock", "/nonexistent/dir/sock", "@",
                                   "vsock:2:1234"])
def test_notify_without_a_usable_socket_returns_false(value, tmp_path):
    assert sdnotify.notify("READY=1", {"NOTIFY_SOCKET": value}) is False
    assert sdnotify.notify("READY=1", {}) is False


def test_notify_to_a_socket_nobody_listens_on_returns_false(tmp_path):
    path = str(tmp_path / "gone.sock")
    _dgram_server(path).close()          # the file stays, nobody receives
    assert sdnotify.notify("READY=1", {"NOTIFY_SOCKET": path}) is False


@given(st.dictionaries(st.sampled_from(["NOTIFY_SOCKET", "WATCHDOG_USEC", "WATCHDOG_PID"]),
                       st.text(max_size=40)), st.text(max_size=40))
@settings(max_examples=150, deadline=None)
def test_sdnotify_never_raises(env, state):
    assert sdnotify.notify(state, env) in (True, False)
    iv = sdnotify.watchdog_interval_s(env)
    assert iv is None or (iv > 0 and iv < float("inf"))
    dog = sdnotify.Watchdog(env=env)
    assert dog.tick(0.0) in (True, False)


def test_watchdog_interval_from_environment():
    me = str(os.getpid())
    assert sdnotify.watchdog_interval_s({"WATCHDOG_USEC": "5000000"}) == 5.0
    assert sdnotify.watchdog_interval_s({"WATCHDOG_USEC": "2500000", "WATCHDOG_PID": me}) == 2.5
    # set for another process (e.g. inherited through a fork): not ours
    assert sdnotify.watchdog_interval_s({"WATCHDOG_USEC": "5000000",
                                         "WATCHDOG_PID": str(os.getpid() + 1)}) is None
    for bad in ({}, {"WATCHDOG_USEC": ""}, {"WATCHDOG_USEC": "0"}, {"WATCHDOG_USEC": "-5"},
                {"WATCHDOG_USEC": "abc"}, {"WATCHDOG_USEC": "1000", "WATCHDOG_PID": "x"}):
        assert sdnotify.watchdog_interval_s(bad) is None, bad


def test_watchdog_pings_at_half_the_interval(tmp_path):
    path = str(tmp_path / "wd.sock")
    env = {"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "2000000"}     # 2 s -> ping every 1 s
    with _dgram_server(path) as srv:
        dog = sdnotify.Watchdog(env=env)
        assert dog.enabled and dog.period_s == 1.0
        sent = [dog.tick(100.0 + i / 10) for i in range(41)]   # 4 s of a 10 Hz loop
        assert sum(sent) == 5 and dog.pings == 5           # at 100, 101, 102, 103, 104 s
        assert [i for i, s in enumerate(sent) if s] == [0, 10, 20, 30, 40]
        srv.settimeout(0.5)
        got = [srv.recv(64) for _ in range(5)]
        assert got == [b"WATCHDOG=1"] * 5
        # a clock that jumps back pings at once rather than going quiet
        assert dog.tick(50.0) is True


def test_watchdog_disabled_without_interval(tmp_path):
    dog = sdnotify.Watchdog(env={"NOTIFY_SOCKET": str(tmp_path / "x.sock")})
    assert not dog.enabled
    assert not any(dog.tick(float(t)) for t in range(100))
    assert sdnotify.Watchdog(interval_s=None).tick(0.0) is False
    for bad in (0, -1.0, float("nan"), float("inf"), "5"):
        with pytest.raises(ValueError, match="interval_s"):
            sdnotify.Watchdog(interval_s=bad)

