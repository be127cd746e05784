"""Scene files: a sensor, a surface, a timeline of actions and a list of effects.

A scene is a TOML file; the format is documented in ``docs/simulator.md``.
:func:`load_scene` accepts a built-in scene name (``host scenes`` lists them)
or a path, and returns a validated, immutable :class:`Scene`.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from device.checks import FPS_MAX_HZ, FPS_MIN_HZ
from device.config import ConfigError, Fields, read_toml
from device.profile import SensorProfile, builtin_toml, load_profile

SCENE_DIR = Path(__file__).with_name("scenes")

SURFACE_LABELS = ("no-touch", "hard", "soft", "slippery")
TEXTURE_LABELS = ("none", "smooth", "lego", "concrete")
ACTIONS = ("lower", "drag", "hold", "lift")


@dataclass(frozen=True)
class Surface:
    name: str
    label: str = "hard"                 # hard | soft | slippery
    stiffness_n_per_mm: float = 200.0   # surface normal stiffness (series with the skin)
    mu: float = 0.9                     # static Coulomb coefficient
    mu_kinetic_ratio: float = 0.85      # mu_kinetic = ratio * mu
    stick_slip: bool = False            # re-check static friction after every slide
    texture: str = "smooth"             # smooth | lego | concrete
    stud_pitch_mm: float = 8.0          # Lego stud pitch
    texture_amplitude_mm: float = 0.0   # jitter amplitude while sliding
    pin_shake_mm: float = 0.0           # each patch pin's own random shake while sliding


# Preset surfaces a scene can name directly. Texture amplitudes are pin jitter at
# the contact patch; Lego studs shake the pins much more than concrete grit.
PRESETS: dict[str, Surface] = {
    "hard": Surface("hard", "hard", 200.0, 0.9, texture="smooth"),
    "soft": Surface("soft", "soft", 1.5, 1.0, texture="smooth"),
    "wet": Surface("wet", "slippery", 200.0, 0.08, texture="smooth"),
    "smooth": Surface("smooth", "hard", 200.0, 0.5, texture="smooth"),
    "lego": Surface("lego", "hard", 200.0, 0.6, texture="lego", texture_amplitude_mm=0.25),
    "concrete": Surface("concrete", "hard", 200.0, 0.8, texture="concrete",
                        texture_amplitude_mm=0.12),
    # fitted to the real roboskin clips (docs/simulator.md, "Sim-to-real"): the skin
    # grips a smooth surface and lets go in stick-slip jumps; on concrete it grips
    # less and the grit shakes the pins a little
    "roboskin-smooth": Surface("roboskin-smooth", "hard", 200.0, 1.1, mu_kinetic_ratio=0.6,
                               stick_slip=True, texture="smooth", pin_shake_mm=0.08),
    "roboskin-concrete": Surface("roboskin-concrete", "hard", 200.0, 0.45, texture="concrete",
                                 texture_amplitude_mm=0.02, pin_shake_mm=0.02),
}


@dataclass(frozen=True)
class Action:
    kind: str
    duration_s: float
    depth_mm: float = 0.0         # lower: target commanded depth into the surface
    height_mm: float = 2.0        # lift: height above the surface
    direction_deg: float = 0.0    # drag: direction of the sensor body's motion
    speed_mm_s: float = 0.0       # drag
    surface: str | None = None    # switch to this surface at the start of the action
    offset_mm: tuple[float, float] = (0.0, 0.0)  # lower: contact centre offset on the dome


@dataclass(frozen=True)
class Effect:
    name: str
    params: dict = field(default_factory=dict)


# name -> {param: (default, min, max)}
EFFECTS: dict[str, dict[str, tuple[float, float, float]]] = {
    "glare": {"peak": (-1.0, -1.0, 255.0), "count": (-1.0, -1.0, 64.0),
              "sigma_px": (-1.0, -1.0, 1000.0)},
    "camera_noise": {"sigma": (4.0, 0.0, 128.0)},
    "exposure_flicker": {"amplitude": (0.08, 0.0, 0.9)},
    "motion_blur": {"exposure_ms": (8.0, 0.0, 1000.0)},
    "lens_distortion": {"k1": (-0.12, -0.5, 0.5)},
    "pin_loss": {"fraction": (0.1, 0.0, 1.0)},
    "exposure": {"gain": (0.85, 0.05, 4.0)},
    "pitch": {"scale": (1.03, 0.5, 2.0)},
    "imu_noise": {"accel_g": (0.02, 0.0, 16.0), "gyro_dps": (0.5, 0.0, 2000.0)},
}


@dataclass(frozen=True)
class Scene:
    name: str
    profile: SensorProfile
    width: int
    height: int
    fps: float
    surfaces: dict
    surface: str                  # the surface in force at the start
    timeline: tuple
    effects: tuple = ()
    hover_mm: float = 2.0
    description: str = ""
    source: str = ""

    @property
    def effect_names(self) -> tuple[str, ...]:
        return tuple(e.name for e in self.effects)

    def effect(self, name: str) -> Effect | None:
        for e in self.effects:
            if e.name == name:
                return e
        return None

    def with_effects(self, *effects: Effect | str) -> "Scene":
        """A copy with these effects (names take default parameters)."""
        out = []
        for e in effects:
            out.append(e if isinstance(e, Effect) else parse_effect(e, "effects", self.source))
        return replace(self, effects=tuple(out))

    @property
    def duration_s(self) -> float:
        return sum(a.duration_s for a in self.timeline)


def builtin_scenes() -> list[str]:
    return sorted(p.stem for p in SCENE_DIR.glob("*.toml"))


def load_scene(name_or_path: str | Path) -> Scene:
    p = builtin_toml(name_or_path, SCENE_DIR, "scene", "scene")
    doc = read_toml(p)
    return parse_scene(doc, source=str(p), default_name=p.stem, base_dir=p.parent)


def _parse_surface(f: Fields, name: str) -> Surface:
    preset = f.string("preset", name if name in PRESETS else "hard", choices=tuple(PRESETS))
    base = PRESETS[preset]
    s = Surface(
        name=name,
        label=f.string("label", base.label, choices=SURFACE_LABELS[1:]),
        stiffness_n_per_mm=f.number("stiffness_n_per_mm", base.stiffness_n_per_mm, min=0,
                                    min_exclusive=True),
        mu=f.number("mu", base.mu, min=0),
        mu_kinetic_ratio=f.number("mu_kinetic_ratio", base.mu_kinetic_ratio, min=0, max=1),
        stick_slip=f.boolean("stick_slip", base.stick_slip),
        texture=f.string("texture", base.texture, choices=TEXTURE_LABELS[1:]),
        stud_pitch_mm=f.number("stud_pitch_mm", base.stud_pitch_mm, min=0, min_exclusive=True),
        texture_amplitude_mm=f.number("texture_amplitude_mm", base.texture_amplitude_mm, min=0),
        pin_shake_mm=f.number("pin_shake_mm", base.pin_shake_mm, min=0, max=100),
    )
    f.done()
    return s


def parse_effect(item: Any, where: str, source: str) -> Effect:
    if isinstance(item, str):
        item = {"name": item}
    f = Fields(item, where, source)
    name = f.string("name", choices=tuple(EFFECTS))
    params = {}
    for key, (default, lo, hi) in EFFECTS[name].items():
        params[key] = f.number(key, default, min=lo, max=hi)
    f.done()
    return Effect(name, params)


def parse_scene(doc: dict, source: str = "", default_name: str = "scene",
                base_dir: Path | None = None) -> Scene:
    top = Fields(doc, "", source)
    name = top.string("name", default_name)
    description = top.string("description", "")
    hover_mm = top.number("hover_mm", 2.0, min=0, max=1000)

    sen = top.sub("sensor", {})
    prof_name = sen.string("profile", "roboskin")
    if prof_name.endswith(".toml") and base_dir is not None and not Path(prof_name).is_absolute():
        prof_name = str(base_dir / prof_name)
    try:
        profile = load_profile(prof_name)
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None
    width = sen.integer("width", profile.width, min=16, max=4096)
    height = sen.integer("height", profile.height, min=16, max=4096)
    # the camera's bound (--fps): a scene is played as a camera source
    fps = sen.number("fps", 120.0, min=FPS_MIN_HZ, max=FPS_MAX_HZ)
    sen.done()

    surfaces = dict(PRESETS)
    surf_tab = top.sub("surface", {})
    surfaces["scene"] = _parse_surface(surf_tab, "scene")
    extra = top.sub("surfaces", {})
    for key in list(extra.table):
        surfaces[key] = _parse_surface(extra.sub(key), key)
    extra.done()

    raw_tl = top.raw("timeline", [])
    if not isinstance(raw_tl, list) or not raw_tl:
        top.fail("timeline", raw_tl, "must be a non-empty list of [[timeline]] actions")
    timeline = []
    for i, item in enumerate(raw_tl):
        f = Fields(item, f"timeline[{i}]", source)
        kind = f.string("action", choices=ACTIONS)
        surface = f.string("surface", "") or None
        if surface is not None and surface not in surfaces:
            f.fail(f"timeline[{i}].surface", surface,
                   f"must name a preset or a [surfaces] table: {sorted(surfaces)}")
        kw: dict = {"kind": kind, "surface": surface,
                    "duration_s": f.number("duration_s", min=0, max=3600, min_exclusive=True)}
        if kind == "lower":
            kw["depth_mm"] = f.number("depth_mm", min=0, max=100)
            kw["offset_mm"] = f.pair("offset_mm", (0.0, 0.0))
        elif kind == "lift":
            kw["height_mm"] = f.number("height_mm", 2.0, min=0, max=1000)
        elif kind == "drag":
            kw["direction_deg"] = f.number("direction_deg", 0.0, min=-360, max=360)
            kw["speed_mm_s"] = f.number("speed_mm_s", min=0, max=100000)
        f.done()
        timeline.append(Action(**kw))

    raw_fx = top.raw("effects", [])
    if not isinstance(raw_fx, list):
        top.fail("effects", raw_fx, "must be a list of effect names or tables")
    effects = []
    for i, item in enumerate(raw_fx):
        e = parse_effect(item, f"effects[{i}]", source)
        if e.name in {x.name for x in effects}:
            raise ConfigError(f"{source}: effects[{i}].name {e.name!r} is listed twice")
        effects.append(e)
    top.done()
    return Scene(name=name, profile=profile, width=width, height=height, fps=fps,
                 surfaces=surfaces, surface="scene", timeline=tuple(timeline),
                 effects=tuple(effects), hover_mm=hover_mm, description=description,
                 source=source)
