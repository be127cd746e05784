"""Sensor profiles: the one parser of a sensor's TOML.

A profile (``device/profiles/NAME.toml``, or any ``.toml`` path) describes one
TacTip build. Two ship with tacfoot:

* ``roboskin``  - the seed paper's sensor: 133 pins on a radial layout, a dark
  dome in the middle of a 640x480 frame with a bright surround, LED-ring glare.
* ``tactip331`` - a 331-pin hexagonal dome, binarised 445x440 images.

Its sections:

* ``[profile]``, ``[layout]``, ``[glare]``: the geometry and look the simulator
  renders and the fixed pin layout models see (:func:`load_profile` ->
  :class:`SensorProfile`; see ``docs/simulator.md``). All lengths ending in
  ``_px`` are at the profile's native resolution; the simulator scales them when
  a scene asks for another frame size.
* ``[vision]``: the marker pipeline's parameters (:func:`load_pipeline_profile` ->
  :class:`PipelineProfile`). The Pi reads only this section, so the file that
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
match_gate_px = 4.7        # tracking distance gate, at most pitch_px (default 0.4 * pitch)
grid_n = 8                 # contact grid size
grid_gamma = 0.01          # temporal dampener per frame
grid_contact = 0.03        # grid cell level that counts as contact
contact_px = 1.0           # or: mean pin displacement that counts as contact (<= pitch_px)
min_pin_fraction = 0.5     # fewer pins than this share of n_pins is a fault
```
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from device.checks import finite_number, whole_number
from device.config import ConfigError, Fields, read_toml

PROFILE_DIR = Path(__file__).resolve().parent / "profiles"


@dataclass(frozen=True)
class GlareSpec:
    count: int = 0
    ring_radius_px: float = 0.0
    sigma_px: float = 10.0
    peak: float = 0.0
    phase_deg: float = 0.0
    centre_px: tuple[float, float] | None = None   # ring centre; default the dome centre
    centre_peak: float = 0.0       # a weaker blob near the middle of the dome
    centre_offset_px: tuple[float, float] = (0.0, 0.0)


@dataclass(frozen=True)
class SensorProfile:
    name: str
    width: int
    height: int
    dome_centre_px: tuple[float, float]
    dome_radius_px: float          # radius of the visible dome (dark disc / mask)
    px_per_mm: float
    dome_radius_mm: float          # curvature radius R used in a = sqrt(R d)
    pin_diameter_px: float
    style: str                     # "camera" (grey, glare) or "binary" (0/255 mask)
    dome_level: float
    pin_level: float
    surround_level: float
    vignette: float                # fractional darkening of the dome towards its rim
    pins_px: np.ndarray = field(repr=False)   # (M, 2) rest positions, native px
    glare: GlareSpec = GlareSpec()
    rim_radius_px: float = 0.0     # darkest ring of the dome wall (0: at dome_radius_px)
    # contact mechanics
    modulus_n_per_mm2: float = 0.35        # effective Hertz modulus E*
    skin_stiffness_n_per_mm: float = 3.0   # linearised normal stiffness of the skin
    tangential_stiffness_n_per_mm: float = 2.0
    normal_gain: float = 0.35      # pin spread (mm of pin travel per mm of indentation)
    shear_gain: float = 0.5        # pin travel per mm of patch shear

    @property
    def n_pins(self) -> int:
        return int(self.pins_px.shape[0])


def radial_layout(rings: list[int], radii: list[float], phases_deg: list[float],
                  centre: tuple[float, float]) -> np.ndarray:
    pts = []
    for n, r, ph in zip(rings, radii, phases_deg):
        if n == 1 and r == 0:
            pts.append((0.0, 0.0))
            continue
        ang = np.deg2rad(ph) + 2 * np.pi * np.arange(n) / n
        pts.extend(zip(r * np.cos(ang), r * np.sin(ang)))
    return np.asarray(pts, dtype=np.float64) + np.asarray(centre)


def hex_layout(n_rings: int, pitch: float, centre: tuple[float, float]) -> np.ndarray:
    """Centre pin plus ``n_rings`` hexagonal rings: 1 + 3 n (n + 1) pins."""
    pts = []
    for q in range(-n_rings, n_rings + 1):
        for r in range(max(-n_rings, -q - n_rings), min(n_rings, -q + n_rings) + 1):
            x = pitch * (q + r / 2.0)
            y = pitch * (r * math.sqrt(3) / 2.0)
            pts.append((x, y))
    pts = np.asarray(pts, dtype=np.float64)
    order = np.lexsort((np.arctan2(pts[:, 1], pts[:, 0]), np.round(np.hypot(*pts.T), 3)))
    return pts[order] + np.asarray(centre)


def builtin_toml(name_or_path: str | Path, folder: Path, field: str, kind: str,
                 error: type[ConfigError] = ConfigError) -> Path:
    """The path of a built-in TOML in ``folder`` named ``name_or_path``, or the
    ``.toml`` path itself. An unknown name raises ``error`` naming ``field``, the
    name and the built-in choices."""
    p = Path(name_or_path)
    if p.suffix == ".toml":
        return p
    p = folder / f"{name_or_path}.toml"
    if not p.exists():
        known = sorted(x.stem for x in folder.glob("*.toml"))
        raise error(f"{field}: unknown {kind} {str(name_or_path)!r}; built-in {kind}s "
                    f"are {known} or give a .toml path")
    return p


def builtin_profiles() -> list[str]:
    return sorted(p.stem for p in PROFILE_DIR.glob("*.toml"))


def load_profile(name_or_path: str | Path) -> SensorProfile:
    """Load a built-in profile's geometry by name, or a custom one from a TOML path."""
    p = builtin_toml(name_or_path, PROFILE_DIR, "sensor.profile", "profile")
    return parse_profile(read_toml(p), source=str(p))


def parse_profile(doc: dict, source: str = "") -> SensorProfile:
    top = Fields(doc, "", source)
    f = top.sub("profile")
    name = f.string("name")
    width = f.integer("width", min=8, max=8192)
    height = f.integer("height", min=8, max=8192)
    centre = f.pair("dome_centre_px")
    dome_r = f.number("dome_radius_px", min=1)
    px_per_mm = f.number("px_per_mm", min=0, min_exclusive=True)
    dome_r_mm = f.number("dome_radius_mm", min=0, min_exclusive=True)
    pin_d = f.number("pin_diameter_px", min=0.5)
    style = f.string("style", "camera", choices=("camera", "binary"))
    dome_level = f.number("dome_level", 70, min=0, max=255)
    pin_level = f.number("pin_level", 200, min=0, max=255)
    surround_level = f.number("surround_level", 235, min=0, max=255)
    vignette = f.number("vignette", 0.0, min=0, max=1)
    rim_r = f.number("rim_radius_px", 0.0, min=0)
    mech = dict(
        modulus_n_per_mm2=f.number("modulus_n_per_mm2", 0.35, min=0, min_exclusive=True),
        skin_stiffness_n_per_mm=f.number("skin_stiffness_n_per_mm", 3.0, min=0, min_exclusive=True),
        tangential_stiffness_n_per_mm=f.number("tangential_stiffness_n_per_mm", 2.0, min=0,
                                               min_exclusive=True),
        normal_gain=f.number("normal_gain", 0.35, min=0),
        shear_gain=f.number("shear_gain", 0.5, min=0),
    )
    f.done()

    pins = _layout_pins(top.sub("layout"), centre, dome_r, pin_d)

    top.raw("vision")      # the pipeline's section (parse_pipeline_profile)
    glare = GlareSpec()
    if top.has("glare"):
        g = top.sub("glare")
        glare = GlareSpec(count=g.integer("count", 0, min=0, max=64),
                          ring_radius_px=g.number("ring_radius_px", 0.0, min=0),
                          sigma_px=g.number("sigma_px", 10.0, min=0.5),
                          peak=g.number("peak", 60.0, min=0, max=255),
                          phase_deg=g.number("phase_deg", 0.0),
                          centre_px=g.pair("centre_px", centre),
                          centre_peak=g.number("centre_peak", 0.0, min=0, max=255),
                          centre_offset_px=g.pair("centre_offset_px", (0.0, 0.0)))
        g.done()
    top.done()
    if pins.shape[0] == 0:
        raise ConfigError(f"{source}: layout gives no pins inside the dome")
    return SensorProfile(name=name, width=width, height=height, dome_centre_px=centre,
                         dome_radius_px=dome_r, px_per_mm=px_per_mm, dome_radius_mm=dome_r_mm,
                         pin_diameter_px=pin_d, style=style, dome_level=dome_level,
                         pin_level=pin_level, surround_level=surround_level, vignette=vignette,
                         pins_px=pins, glare=glare, rim_radius_px=rim_r, **mech)


def _layout_pins(lay: Fields, centre: tuple[float, float], dome_r: float | None,
                 pin_d: float | None) -> np.ndarray:
    """The rest pin positions (M, 2) px of a ``[layout]`` section: ``radial`` rings,
    a ``hex`` grid cut to the dome, or measured ``points`` (``pins_px = [[x, y], ...]``,
    as ``host calibrate`` writes them)."""
    kind = lay.string("kind", choices=("radial", "hex", "points"))
    if kind == "points":
        raw = lay.raw("pins_px")
        try:
            pins = np.asarray(raw, np.float64)
        except (TypeError, ValueError):
            pins = np.zeros((0, 3))
        if pins.ndim != 2 or pins.shape[1:] != (2,) or len(pins) == 0 \
                or not np.isfinite(pins).all():
            lay.fail("layout.pins_px", raw if isinstance(raw, (int, float, str)) else
                     f"<{type(raw).__name__}>", "must be a non-empty list of finite [x, y] pairs")
        lay.done()
        return pins
    lay_centre = lay.pair("centre_px", centre)
    if kind == "radial":
        rings = lay.number_list("rings", integer=True, min=1)
        radii = lay.number_list("ring_radii_px", min=0)
        phases = lay.number_list("ring_phase_deg", [0.0] * len(rings))
        if not (len(rings) == len(radii) == len(phases)):
            lay.fail("layout.ring_radii_px", radii, f"must have one entry per ring ({len(rings)})")
        pins = radial_layout(rings, radii, phases, lay_centre)
    else:
        n_rings = lay.integer("hex_rings", min=0, max=60)
        pitch = lay.number("pitch_px", min=0, min_exclusive=True)
        count = lay.integer("count", 0, min=0)
        pins = hex_layout(n_rings, pitch, lay_centre)
        # a hexagon's corners can stick out of a round dome: keep what fits, and
        # with ``count`` the pins nearest the centre (a hex grid cut to a disc)
        if dome_r is not None:
            keep = np.hypot(*(pins - centre).T) <= dome_r - (pin_d or 0.0) / 2
            pins = pins[keep]
        if count:
            if count > len(pins):
                lay.fail("layout.count", count, f"must be <= the {len(pins)} pins that fit")
            pins = pins[np.argsort(np.hypot(*(pins - lay_centre).T), kind="stable")[:count]]
    lay.done()
    return pins


def has_sim_geometry(name_or_path: str | Path) -> bool:
    """Whether a profile carries the simulator's ``[profile]`` geometry (image size,
    dome, optics), as the built-in ones do; a calibrated profile does not."""
    p = builtin_toml(name_or_path, PROFILE_DIR, "sensor.profile", "profile")
    doc = read_toml(p)
    return isinstance(doc.get("profile"), dict) and "width" in doc["profile"]


def load_layout(name_or_path: str | Path) -> np.ndarray:
    """The fixed pin layout (M, 2) px of a built-in profile or a profile TOML: its
    ``[layout]`` section, which a calibrated profile (``[vision]`` + ``[layout]
    kind = "points"``) has without the simulator's ``[profile]`` geometry."""
    p = builtin_toml(name_or_path, PROFILE_DIR, "sensor.profile", "profile")
    if has_sim_geometry(p):
        return load_profile(p).pins_px
    doc = read_toml(p)
    top = Fields(doc, "", str(p))
    if not top.has("layout"):
        top.fail("layout", None, "section is required: the rest pin layout (host calibrate "
                                 "writes it from no-contact frames)")
    centre = (0.0, 0.0)
    if isinstance(doc.get("vision"), dict) and isinstance(doc["vision"].get("dome_px"), list) \
            and len(doc["vision"]["dome_px"]) == 3:
        centre = tuple(float(v) for v in doc["vision"]["dome_px"][:2])
    pins = _layout_pins(top.sub("layout"), centre, None, None)
    if len(pins) == 0:
        raise ConfigError(f"{p}: layout gives no pins")
    return pins


# ---------------------------------------------------------------- [vision]

@dataclass(frozen=True)
class VisionParams:
    """Parameters of the marker front end.

    block: side of the adaptive-threshold neighbourhood, px (odd, >= 3).
    offset: a pixel is "pin" when it is more than ``offset`` gray levels above
        the mean of its ``block`` x ``block`` neighbourhood.
    blur_sigma_px: Gaussian pre-blur before thresholding (0 disables). A light
        blur removes MPEG block noise that otherwise breaks pins into pieces.
    min_area_px: blobs smaller than this are noise, not pins.
    max_area_px: blobs larger than this are glare (LED reflections), not pins.
    roi_shrink: the pin search disc is ``roi_shrink`` times the dome radius;
        below 1 it keeps the bright specular glints on the dome rim out.
    contrast_ref: the dome's local contrast at calibration, gray levels (the 95th
        percentile of the blurred gray minus its ``block`` box mean over the dome
        disc, :func:`device.pi.vision.extract.local_contrast`). Given, the pipeline
        scales ``offset`` by the contrast it measures when it sets its reference,
        ``offset * clamp(contrast / contrast_ref, 0.5, 1)`` (1 for a ratio of 0.95 or
        more), so a darker exposure keeps its faint pins; None (absent) leaves the
        offset fixed.
    """

    block: int = 11
    offset: float = 14.0
    blur_sigma_px: float = 1.0
    min_area_px: int = 10
    max_area_px: int = 100
    roi_shrink: float = 0.75
    contrast_ref: float | None = None

    def __post_init__(self) -> None:
        whole_number("block", self.block, lo=3)
        if self.block % 2 != 1:
            raise ValueError(f"block must be odd, got block={self.block!r}")
        finite_number("offset", self.offset, lo=-255.0, hi=255.0)
        finite_number("blur_sigma_px", self.blur_sigma_px, lo=0.0, hi=50.0)
        whole_number("min_area_px", self.min_area_px, lo=1)
        whole_number("max_area_px", self.max_area_px, lo=1)
        if self.max_area_px < self.min_area_px:
            raise ValueError(
                f"max_area_px must be >= min_area_px, got max_area_px={self.max_area_px!r} "
                f"with min_area_px={self.min_area_px!r}"
            )
        finite_number("roi_shrink", self.roi_shrink, lo=0.0, hi=1.5, lo_open=True)
        if self.contrast_ref is not None:
            finite_number("contrast_ref", self.contrast_ref, lo=0.0, hi=255.0, lo_open=True)


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
    """Load a profile's ``[vision]`` section by built-in name or TOML path."""
    p = builtin_toml(name_or_path, PROFILE_DIR, "profile", "profile", ProfileError)
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
                                                  min_exclusive=True),
                              contrast_ref=(f.number("contrast_ref", min=0, max=255,
                                                     min_exclusive=True)
                                            if f.has("contrast_ref") else None))
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
            match_gate_px=f.number("match_gate_px", 0.4 * pitch, min=0, min_exclusive=True,
                                   max=pitch),
            grid_n=f.integer("grid_n", 8, min=1, max=256),
            grid_gamma=f.number("grid_gamma", 0.01, min=0, max=1),
            grid_contact=f.number("grid_contact", 0.03, min=0, max=1),
            contact_px=f.number("contact_px", 1.0, min=0, max=pitch),
            min_pin_fraction=f.number("min_pin_fraction", 0.5, min=0, max=1),
            source=source)
        f.done()
        return prof
    except ConfigError as exc:
        raise ProfileError(str(exc)) from None
