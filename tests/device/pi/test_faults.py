"""The one fault-bit table (device/pi/faults.py): single distinct bits in a u16, the
pipeline's in the low byte, names in bit order, and the MicroPython link consumer's
copies of the runtime bits at the same values."""
from __future__ import annotations

import re
from pathlib import Path

from device.pi import faults as F

ROOT = Path(__file__).resolve().parents[3]
PIPELINE = (F.FAULT_NO_DOME, F.FAULT_TOO_FEW_PINS, F.FAULT_NO_REFERENCE,
            F.FAULT_FRAME_SIZE_CHANGED, F.FAULT_BAD_FRAME, F.FAULT_LOCALISER, F.FAULT_FRAME)
RUNTIME = (F.FAULT_CAMERA, F.FAULT_IMU, F.FAULT_MODEL, F.FAULT_PINS_LOST, F.FAULT_LINK,
           F.FAULT_CLAMPED, F.FAULT_NONFINITE)


def test_every_bit_is_one_distinct_bit_of_a_u16():
    bits = PIPELINE + RUNTIME + (F.FAULT_BAD_INPUT,)
    assert all(b > 0 and b & (b - 1) == 0 and b <= 0x8000 for b in bits)
    assert len(set(bits)) == len(bits)


def test_pipeline_bits_fit_the_pipeline_mask_and_runtime_bits_do_not():
    assert all(b & F.PIPELINE_FAULTS for b in PIPELINE)
    assert not any(b & F.PIPELINE_FAULTS for b in RUNTIME)


def test_names_cover_the_wire_bits_and_not_the_tracker_bit():
    assert set(F.FAULT_NAMES) == set(PIPELINE + RUNTIME)
    assert len(set(F.FAULT_NAMES.values())) == len(F.FAULT_NAMES)
    assert F.fault_names(F.FAULT_BAD_INPUT) == []
    assert F.fault_names(F.FAULT_CAMERA | F.FAULT_NO_DOME | F.FAULT_LINK) == [
        "no_dome", "camera", "link"]
    assert F.fault_names(0) == []


def test_micropython_link_consumer_uses_the_same_values():
    src = (ROOT / "device" / "micropython" / "surface_link.py").read_text()
    found = {name: int(value, 0) for name, value in
             re.findall(r"^(FAULT_[A-Z_]+) = const\((0x[0-9A-Fa-f]+|\d+)\)", src, re.M)}
    assert found, "surface_link.py defines no FAULT_ constants"
    found.pop("FAULT_LEN", None)          # the FAULT payload's length, not a bit
    assert len(found) == 8
    assert found["FAULT_FRAME"] == 0x0080    # the implausible-frame bit: the gait must see it
    for name, value in found.items():
        assert getattr(F, name) == value, name
