"""The pipeline's view of a sensor profile: the ``[vision]`` section.

A sensor profile TOML (``device/profiles/NAME.toml``) holds the simulator's
geometry (``[profile]``, ``[layout]``, ``[glare]``) and the marker pipeline's
parameters (``[vision]``). The Pi reads only ``[vision]``, so the file that
``host calibrate`` writes from a real clip (which has only ``[vision]``) is a
valid pipeline profile on its own.

```toml
[vision]
block = 11                 # adaptive-threshold neighbourhood, px (odd)
offset = 14.0              # grey levels above the local mean that count as pin
blur_sigma_px = 1.0        # pre-blur against MPEG block noise (0: off)
min_area_px = 10           # smaller blobs are noise
max_area_px = 100          # larger blobs are glare (the paper: remove large blobs)
roi_shrink = 0.75          # pins are searched within roi_shrink * dome radius
pitch_px = 11.7            # pin spacing at rest
n_pins = 133               # the fixed pin count the localiser returns
dome_px = [325.8, 218.8, 145.0]   # optional: fix the region instead of finding it
match_gate_px = 4.7        # tracking distance gate (default 0.4 * pitch)
grid_n = 8                 # contact grid size
grid_gamma = 0.01          # temporal dampener per frame
grid_contact = 0.03        # grid cell level that counts as contact
contact_px = 1.0           # or: mean pin displacement that counts as contact
min_pin_fraction = 0.5     # fewer pins than this share of n_pins is a fault
```
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from device.config import ConfigError, Fields, read_toml
from device.pi.vision.extract import VisionParams

PROFILE_DIR = Path(__file__).resolve().parent / "profiles"


class ProfileError(ConfigError):
    """A bad pipeline profile; the message names the file and the field."""


@dataclass(frozen=True)
class PipelineProfile:
    name: str
    vision: VisionParams
    pitch_px: float
    n_pins: int
    dome_px: tuple[float, float, float] | None
    match_gate_px: float
    grid_n: int
    grid_gamma: float
    grid_contact: float
    contact_px: float
    min_pin_fraction: float
    source: str = ""


def load_pipeline_profile(name_or_path: str | Path) -> PipelineProfile:
    p = Path(name_or_path)
    if p.suffix != ".toml":
        p = PROFILE_DIR / f"{name_or_path}.toml"
        if not p.exists():
            known = sorted(x.stem for x in PROFILE_DIR.glob("*.toml"))
            raise ProfileError(f"profile: unknown profile {str(name_or_path)!r}; built-in "
                               f"profiles are {known} or give a .toml path")
    return parse_pipeline_profile(read_toml(p), source=str(p))



def parse_pipeline_profile(doc: dict, source: str = "") -> PipelineProfile:
    try:
        name = doc.get("profile", {}).get("name", Path(source).stem or "custom")
        f = Fields(doc.get("vision"), "vision", source)
        if "vision" not in doc:
            f.fail("vision", None, "section is required")
        block = f.integer("block", 11, min=3, max=255)
        if block % 2 != 1:
            f.fail("vision.block", block, "must be odd")
        min_area = f.integer("min_area_px", 10, min=1)
        max_area = f.integer("max_area_px", 100, min=1)
        if max_area < min_area:
            f.fail("vision.max_area_px", max_area, f"must be >= min_area_px ({min_area})")
        vision = VisionParams(block=block, offset=f.number("offset", 14.0, min=-255, max=255),
                              blur_sigma_px=f.number("blur_sigma_px", 1.0, min=0, max=50),
                              min_area_px=min_area, max_area_px=max_area,
                              roi_shrink=f.number("roi_shrink", 0.75, min=0, max=1.5,
                                                  min_exclusive=True))
        pitch = f.number("pitch_px", min=0.5, max=1000)
        dome = None
        if f.has("dome_px"):
            d = f.number_list("dome_px")
            if len(d) != 3 or d[2] <= 0:
                f.fail("vision.dome_px", d, "must be [cx, cy, r] with r > 0")
            dome = (d[0], d[1], d[2])
        prof = PipelineProfile(
            name=str(name), vision=vision, pitch_px=pitch,
            n_pins=f.integer("n_pins", min=1, max=10000), dome_px=dome,
            match_gate_px=f.number("match_gate_px", 0.4 * pitch, min=0, min_exclusive=True),
            grid_n=f.integer("grid_n", 8, min=1, max=256),
            grid_gamma=f.number("grid_gamma", 0.01, min=0, max=1),
            grid_contact=f.number("grid_contact", 0.03, min=0, max=1),
            contact_px=f.number("contact_px", 1.0, min=0),
            min_pin_fraction=f.number("min_pin_fraction", 0.5, min=0, max=1),
            source=source)
        f.done()
        return prof
    except ConfigError as exc:
        raise ProfileError(str(exc)) from None
