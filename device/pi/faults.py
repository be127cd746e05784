"""The fault bits: one table for the marker pipeline, the tracker, the runtime and
the wire protocol (u16, carried in SURFACE, IMU summary, HEARTBEAT and FAULT; the
byte tables are in docs/protocol.md).

Bits 0-5 and 7 are the marker pipeline's per-frame bits, bits 8-12 the runtime's,
bits 14-15 the encoder's. Bit 6 is the tracker's own bad-input flag (``Tracker.faults``);
it never goes on the wire. Bit 13 is reserved (0). Pure standard library,
so the protocol module stays importable without numpy.
"""
from __future__ import annotations

FAULT_NO_DOME = 1 << 0            # no dome found in the frame
FAULT_TOO_FEW_PINS = 1 << 1       # fewer pins than the profile's min_pin_fraction
FAULT_NO_REFERENCE = 1 << 2       # no reference frame chosen yet
FAULT_FRAME_SIZE_CHANGED = 1 << 3  # the frame size changed: geometry reset
FAULT_BAD_FRAME = 1 << 4          # the frame is not an image
FAULT_LOCALISER = 1 << 5          # the fixed-count localiser gave no usable pins
FAULT_BAD_INPUT = 1 << 6          # tracker only: pins not an (n, 2) array, bad rows dropped
FAULT_FRAME = 1 << 7              # the frame is implausible for this sensor: no contact
FAULT_CAMERA = 1 << 8             # no frame within camera.stall_periods frame periods
FAULT_IMU = 1 << 9                # the IMU read failed (stale / offline)
FAULT_MODEL = 1 << 10             # a model gave no usable output (uniform fallback)
FAULT_PINS_LOST = 1 << 11         # more than half the reference pins lost this frame
FAULT_LINK = 1 << 12              # bytes waiting and the port took none for stall_ms
FAULT_CLAMPED = 1 << 14           # a value was out of range and was clamped on encode
FAULT_NONFINITE = 1 << 15         # a value was NaN/inf/not a number; sent as 0

#: the bits a frame of the marker pipeline can raise
PIPELINE_FAULTS = 0xFF

FAULT_NAMES = {FAULT_NO_DOME: "no_dome", FAULT_TOO_FEW_PINS: "too_few_pins",
               FAULT_NO_REFERENCE: "reference_not_set",
               FAULT_FRAME_SIZE_CHANGED: "frame_size_changed", FAULT_BAD_FRAME: "bad_frame",
               FAULT_LOCALISER: "localiser", FAULT_FRAME: "frame", FAULT_CAMERA: "camera", FAULT_IMU: "imu",
               FAULT_MODEL: "model", FAULT_PINS_LOST: "pins_lost", FAULT_LINK: "link",
               FAULT_CLAMPED: "clamped", FAULT_NONFINITE: "nonfinite"}


def fault_names(bits: int) -> list[str]:
    """The names of the wire fault bits set in ``bits``, lowest bit first."""
    return [name for bit, name in FAULT_NAMES.items() if bits & bit]
