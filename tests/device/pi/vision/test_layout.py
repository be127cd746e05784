"""device/pi/vision/layout.py: the fixed pin layout of a profile, without the simulator."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from device.pi.vision.layout import LayoutError, layout_assignment, layout_for_profile
from device.profile import load_profile

REPO = Path(__file__).resolve().parents[4]


def test_layout_for_profile_is_the_profile_pins_in_order():
    for name, m in (("roboskin", 133), ("tactip331", 331)):
        lay = layout_for_profile(name)
        assert lay.shape == (m, 2) and lay.dtype == np.float64
        assert np.array_equal(lay, load_profile(name).pins_px)


def test_layout_for_profile_does_not_load_the_simulator():
    code = ("import sys; from device.pi.vision.layout import layout_for_profile; "
            "layout_for_profile('roboskin'); "
            "print(sorted(m for m in sys.modules if m.startswith('device.sim')))")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True,
                         env={"PYTHONPATH": str(REPO)}, check=True)
    assert out.stdout.strip() == "[]"


def test_a_vision_only_profile_is_a_layout_error(tmp_path):
    p = tmp_path / "cal.toml"
    p.write_text("[vision]\npitch_px=12.0\nn_pins=133\n")
    with pytest.raises(LayoutError, match="cal.toml"):
        layout_for_profile(str(p))


def test_layout_assignment_follows_a_shifted_reference():
    lay = layout_for_profile("roboskin")
    ref = lay[::-1] + [3.0, -2.0]
    idx = layout_assignment(ref, lay, 4.0)
    assert (idx == np.arange(len(lay))[::-1]).all()
