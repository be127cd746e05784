"""``python -m host`` (host/__main__.py) runs the host command."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest


def test_python_dash_m_host_works():
    r = subprocess.run([sys.executable, "-m", "host", "scenes"], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0 and "walk" in r.stdout



# --- one catch for tacfoot's errors, and -v/-q (issues 31 and 32) ------------------

def _bench_runtime_raises(monkeypatch, exc):
    import host.cli.bench as bench

    def fake(**kw):
        raise exc
    monkeypatch.setattr(bench, "bench_runtime", fake)


def test_a_tacfoot_error_is_one_line_and_exit_2(monkeypatch, capsys):
    from device.pi.runtime.link import LinkError
    from host.cli import main
    _bench_runtime_raises(monkeypatch, LinkError("--serial /dev/ttyX: the port is gone"))
    assert main(["bench", "runtime", "--json"]) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert err == "host bench: error: --serial /dev/ttyX: the port is gone\n"


@pytest.mark.parametrize("bug", [KeyError("frames"), ValueError("math domain error")])
def test_a_plain_bug_is_not_reported_as_bad_input(monkeypatch, capsys, bug):
    """A KeyError or a bare ValueError from a defect shows as itself (a traceback),
    not as "error: ..." with exit 2."""
    from host.cli import main
    _bench_runtime_raises(monkeypatch, bug)
    with pytest.raises(type(bug)):
        main(["bench", "runtime", "--json"])
    assert "error:" not in capsys.readouterr().err


@pytest.mark.parametrize("flags, shown", [
    (["-q"], ["error"]), ([], ["info", "warning", "error"]),
    (["-v"], ["debug", "info", "warning", "error"]),
    (["bench", "runtime", "-q"], ["error"])])
def test_verbose_and_quiet_choose_the_messages_and_leave_stdout_alone(monkeypatch, capsys,
                                                                    flags, shown):
    import logging

    import host.cli.bench as bench
    from host.cli import main

    def fake(**kw):
        log = logging.getLogger("host.bench.runtime")
        for level in ("debug", "info", "warning", "error"):
            getattr(log, level)(level)
        return {"frames": 3}
    monkeypatch.setattr(bench, "bench_runtime", fake)
    monkeypatch.setattr(bench, "format_runtime", lambda res: "the text form")
    argv = flags + ["--json"] if flags[:1] == ["bench"] else flags + ["bench", "runtime",
                                                                      "--json"]
    assert main(argv) == 0
    out, err = capsys.readouterr()
    assert json.loads(out) == {"frames": 3}
    assert err.splitlines() == shown
