"""``python -m host`` (host/__main__.py) runs the host command."""
from __future__ import annotations

import subprocess
import sys


def test_python_dash_m_host_works():
    r = subprocess.run([sys.executable, "-m", "host", "scenes"], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0 and "walk" in r.stdout

