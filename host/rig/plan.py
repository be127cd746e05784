"""Trial files for the data-collection rig (docs/rig.md): a plan of plates, action
variants and repetitions, checked completely before anything moves.

Each trial is one repetition of one action variant on one base plate (a press at
one depth, a drag in one direction at one load and speed).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from device.config import ConfigError, Fields, read_toml
from device.sim.scene import PRESETS, SURFACE_LABELS, TEXTURE_LABELS

ACTIONS = ("press", "drag")
DIRECTIONS = {"left": -1, "right": 1, "centre": 0}


@dataclass(frozen=True)
class RigLimits:
    travel_mm: float = 40.0        # z travel below the home switch (the firmware's)
    surface_mm: float = 20.0       # plate surface below the home switch
    approach_mm: float = 2.0       # each trial starts this far above the surface
    max_load_n: float = 20.0       # load cell range
    x_travel_mm: float = 30.0      # DC axis travel either side of centre
    max_speed_mm_s: float = 50.0   # DC axis speed at full duty / stepper speed cap


@dataclass(frozen=True)
class Plate:
    name: str
    surface: str
    texture: str
    sim: str


@dataclass(frozen=True)
class Variant:
    key: str
    action: str
    depth_mm: float = 0.0
    load_n: float = 0.0
    direction: str = ""
    distance_mm: float = 0.0
    speed_mm_s: float = 0.0
    press_speed_mm_s: float = 5.0
    hold_s: float = 0.0


@dataclass(frozen=True)
class Trial:
    id: str
    plate: Plate
    variant: Variant
    rep: int


@dataclass
class Plan:
    name: str
    description: str
    source: str
    repetitions: int
    limits: RigLimits
    plates: list
    variants: list
    trials: list = field(default_factory=list)


def load_plan(path: str | Path) -> Plan:
    """Read and validate a trial file; every error names the entry and value."""
    p = Path(path)
    doc = read_toml(p)
    return parse_plan(doc, source=str(p), default_name=p.stem)


def parse_plan(doc: dict, source: str = "", default_name: str = "trials") -> Plan:
    top = Fields(doc, "", source)
    name = top.string("name", default_name)
    description = top.string("description", "")
    reps = top.integer("repetitions", 1, min=1, max=100000)
    r = top.sub("rig", {})
    lim = RigLimits(
        travel_mm=r.number("travel_mm", 40.0, min=0, min_exclusive=True, max=1000),
        surface_mm=r.number("surface_mm", 20.0, min=0, max=1000),
        approach_mm=r.number("approach_mm", 2.0, min=0, max=100),
        max_load_n=r.number("max_load_n", 20.0, min=0, min_exclusive=True, max=10000),
        x_travel_mm=r.number("x_travel_mm", 30.0, min=0, max=1000),
        max_speed_mm_s=r.number("max_speed_mm_s", 50.0, min=0, min_exclusive=True, max=1000),
    )
    r.done()
    if lim.surface_mm >= lim.travel_mm:
        top.fail("rig.surface_mm", lim.surface_mm,
                 f"must be inside the travel (rig.travel_mm = {lim.travel_mm:g})")
    if lim.surface_mm - lim.approach_mm < 0:
        top.fail("rig.approach_mm", lim.approach_mm,
                 f"must be <= rig.surface_mm ({lim.surface_mm:g}): above the home switch")

    raw_plates = top.raw("plates")
    if not isinstance(raw_plates, list) or not raw_plates:
        top.fail("plates", raw_plates, "must be a non-empty list of [[plates]] tables")
    plates = []
    for i, item in enumerate(raw_plates):
        f = Fields(item, f"plates[{i}]", source)
        pname = f.string("name")
        surface = f.string("surface", choices=SURFACE_LABELS[1:])
        texture = f.string("texture", "smooth", choices=TEXTURE_LABELS[1:])
        default_sim = pname if pname in PRESETS else {"hard": "hard", "soft": "soft",
                                                      "slippery": "wet"}[surface]
        sim = f.string("sim", default_sim, choices=tuple(PRESETS))
        f.done()
        if pname in {p.name for p in plates}:
            f.fail(f"plates[{i}].name", pname, "is listed twice")
        plates.append(Plate(pname, surface, texture, sim))

    raw_actions = top.raw("actions")
    if not isinstance(raw_actions, list) or not raw_actions:
        top.fail("actions", raw_actions, "must be a non-empty list of [[actions]] tables")
    variants: list[Variant] = []
    max_depth = lim.travel_mm - lim.surface_mm
    for i, item in enumerate(raw_actions):
        where = f"actions[{i}]"
        f = Fields(item, where, source)
        kind = f.string("action", choices=ACTIONS)
        hold = f.number("hold_s", 0.2, min=0, max=600)
        press_v = f.number("press_speed_mm_s", 5.0, min=0, min_exclusive=True,
                           max=lim.max_speed_mm_s)
        if kind == "press":
            depths = f.number_list("depths_mm", min=0)
            for k, d in enumerate(depths):
                if d <= 0:
                    f.fail(f"{where}.depths_mm[{k}]", d, "must be > 0")
                if d > max_depth:
                    f.fail(f"{where}.depths_mm[{k}]", d,
                           f"is beyond the rig's travel: the surface is at {lim.surface_mm:g} "
                           f"of {lim.travel_mm:g} mm, so at most {max_depth:g} mm")
                variants.append(Variant(f"press-{d:g}mm", "press", depth_mm=d, hold_s=hold,
                                        press_speed_mm_s=press_v))
        else:
            dirs = f.raw("directions", ["left", "right", "centre"])
            if not isinstance(dirs, list) or not dirs:
                f.fail(f"{where}.directions", dirs, "must be a non-empty list")
            for k, dname in enumerate(dirs):
                if dname not in DIRECTIONS:
                    f.fail(f"{where}.directions[{k}]", dname,
                           f"must be one of {sorted(DIRECTIONS)}")
            loads = f.number_list("loads_n", min=0)
            for k, ld in enumerate(loads):
                if not 0 < ld <= lim.max_load_n:
                    f.fail(f"{where}.loads_n[{k}]", ld,
                           f"must be > 0 and <= the load cell's range ({lim.max_load_n:g} N)")
            dist = f.number("distance_mm", 10.0, min=0, min_exclusive=True)
            if dist > lim.x_travel_mm:
                f.fail(f"{where}.distance_mm", dist,
                       f"is beyond the x axis travel ({lim.x_travel_mm:g} mm)")
            speeds = f.number_list("speeds_mm_s", [10.0], min=0)
            for k, v in enumerate(speeds):
                if not 0 < v <= lim.max_speed_mm_s:
                    f.fail(f"{where}.speeds_mm_s[{k}]", v,
                           f"must be > 0 and <= {lim.max_speed_mm_s:g} mm/s")
            for dname in dirs:
                for ld in loads:
                    for v in (speeds if DIRECTIONS[dname] else speeds[:1]):
                        key = (f"drag-{dname}-{ld:g}N" if not DIRECTIONS[dname]
                               else f"drag-{dname}-{ld:g}N-{v:g}mm_s")
                        variants.append(Variant(key, "drag", load_n=ld, direction=dname,
                                                distance_mm=dist, speed_mm_s=v, hold_s=hold,
                                                press_speed_mm_s=press_v))
        f.done()
    top.done()
    seen = set()
    for v in variants:
        if v.key in seen:
            raise ConfigError(f"{source}: action variant {v.key!r} is listed twice")
        seen.add(v.key)
    plan = Plan(name, description, source, reps, lim, plates, variants)
    plan.trials = [Trial(f"{name}/{pl.name}/{v.key}/r{rep:03d}", pl, v, rep)
                   for pl in plates for rep in range(reps) for v in variants]
    return plan


def plan_summary(plan: Plan) -> dict:
    return {"name": plan.name, "source": plan.source, "description": plan.description,
            "trials": len(plan.trials), "repetitions": plan.repetitions,
            "plates": [p.name for p in plan.plates], "variants": [v.key for v in plan.variants],
            "estimated_s": round(sum(estimate_s(t, plan.limits) for t in plan.trials), 1)}


def estimate_s(trial: Trial, lim: RigLimits) -> float:
    v = trial.variant
    t = 2 * (lim.approach_mm + 3.0) / v.press_speed_mm_s + v.hold_s + 0.3
    if v.action == "drag" and v.direction != "centre":
        t += v.distance_mm / v.speed_mm_s
    return t

