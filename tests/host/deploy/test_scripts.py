"""host/deploy/scripts.py: the systemd unit carries the runtime command line exactly;
``systemd-analyze verify`` accepts it when that tool is here."""
from __future__ import annotations

import os
import shlex
import shutil
import subprocess
import sys

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from host.deploy.options import DeployOptions
from host.deploy.scripts import render_unit, runtime_argv


def _opts(**kw) -> DeployOptions:
    base = dict(target="pi@leg1", camera="sim://walk", imu="sim://walk", serial="loop://")
    base.update(kw)
    return DeployOptions(**base)


def test_unit_has_the_required_settings():
    unit = render_unit(_opts(env=["OMP_NUM_THREADS=1", "TAG=a b"], watchdog_s=7))
    lines = unit.splitlines()
    for want in ("Type=notify", "NotifyAccess=main", "Restart=on-failure", "WatchdogSec=7",
                 "User=pi", "Environment=OMP_NUM_THREADS=1", 'Environment="TAG=a b"'):
        assert want in lines, want
    assert "@" not in "".join(l for l in lines if not l.startswith("#")), "unfilled field"
    (exec_line,) = [l for l in lines if l.startswith("ExecStart=")]
    assert exec_line.startswith("ExecStart=/opt/tacfoot/current/venv/bin/python -I -m device.pi run ")
    assert "--status /opt/tacfoot/run/status.json" in exec_line
    assert "--camera sim://walk" in exec_line
    # root runs without User=; $ and % are escaped for systemd
    unit = render_unit(_opts(target="root@leg1", camera="file:///d/50%$x.avi"))
    assert not any(l.startswith("User=") for l in unit.splitlines())
    assert "file:///d/50%%$$x.avi" in unit


def _exec_start_argv(unit: str) -> list[str]:
    """ExecStart= split the way systemd does for the quoting render_unit uses."""
    (line,) = [l for l in unit.splitlines() if l.startswith("ExecStart=")]
    return [w.replace("%%", "%").replace("$$", "$") for w in shlex.split(line[10:])]


@given(st.text(st.characters(max_codepoint=0x2FF, blacklist_categories=("Cc", "Cs")),
               min_size=1, max_size=30).filter(str.strip),   # a blank one is refused
       st.lists(st.text(st.characters(min_codepoint=32, max_codepoint=126), min_size=1,
                        max_size=12), max_size=3))
@settings(max_examples=200, deadline=None)
def test_unit_command_line_round_trips(camera, extra):
    o = _opts(camera=camera, runtime_args=extra)
    o.check()
    assert _exec_start_argv(render_unit(o)) == runtime_argv(o)


def test_unit_passes_systemd_analyze_verify(tmp_path):
    tool = shutil.which("systemd-analyze")
    if tool is None:
        pytest.skip("systemd-analyze not installed")
    prefix = tmp_path / "opt"
    (prefix / "current" / "venv" / "bin").mkdir(parents=True)
    os.symlink(sys.executable, prefix / "current" / "venv" / "bin" / "python")
    unit = tmp_path / "tacfoot.service"
    unit.write_text(render_unit(_opts(target="root@leg1", prefix=str(prefix),
                                         env=["OMP_NUM_THREADS=1"])))
    r = subprocess.run([tool, "verify", str(unit)], capture_output=True, text=True, timeout=60)
    out = r.stdout + r.stderr
    if r.returncode != 0 and "tacfoot.service" not in out:
        pytest.skip(f"systemd-analyze verify cannot run here: {out.strip()[-200:]}")
    assert r.returncode == 0 and "tacfoot.service:" not in out, out
    # and it does catch a broken unit, so the check above means something
    unit.write_text(unit.read_text().replace("Type=notify", "Type=notifyy"))
    r = subprocess.run([tool, "verify", str(unit)], capture_output=True, text=True, timeout=60)
    assert "tacfoot.service:" in r.stdout + r.stderr and "notifyy" in r.stdout + r.stderr
