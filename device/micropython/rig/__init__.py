"""The data-collection rig's RP2040 firmware (docs/rig.md)."""
