"""Planning a job: from a scene and the user's options to the effects to simulate and the work units.

This is the master's half of the pipeline before any unit renders: effect analysis, the complexity
pre-pass, and the partition into units with their features (C, S, Nd). The in-process pipeline
(`quekaro render`) and the farm's master both start from a `JobPlan`.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from core import integrators
from core.effects import Effects, analyse
from core.errors import QuekaroError
from core.integrators import CATALOGUE
from core.messages import LEVELS, VARIANT_PATTERN
from core.scene import SceneSpec, expand, film_info, sensor_elements
from core.units import Unit
from fuzzy.engine import DEFUZZIFIERS
from master.partition import equal_tiles

DEFAULT_SPP = 64  # when neither the user nor the scene's sampler says
# Integer options and their ranges (the message schema's limits, core.messages.JobInfo).
_INT_RANGES = {"spp": (1, 1 << 20), "depth": (1, 1024), "threads": (1, 4096), "units": (1, 4096),
               "sensor": (0, 1024)}


@dataclass(frozen=True)
class RenderOptions:
    """What the user asked for: optimisation level, predefined spp/depth, rules and overrides."""

    level: str = "off"
    spp: int | None = None
    depth: int | None = None
    threads: int | None = None
    rules: Path | None = None
    defuzzifier: str | None = None  # None: centroid in one process, each agent's own on a farm
    variant: str | None = None
    integrator: str | None = None
    units: int | None = None  # target number of work units; None: chosen from the image size
    sensor: int = 0  # which of the scene's sensors renders (Mitsuba's -s)

    def __post_init__(self) -> None:
        if self.level not in LEVELS:
            raise QuekaroError(f"--opt {self.level!r}: expected one of {', '.join(LEVELS)}")
        for name, (lo, hi) in _INT_RANGES.items():
            value = getattr(self, name)
            if value is None:
                continue
            if type(value) is not int:  # bool, float (1e400 is inf), str: refused, not coerced
                raise QuekaroError(f"option {name} (--{name} {value!r}): not an integer")
            if not lo <= value <= hi and not (name == "depth" and value == -1):
                raise QuekaroError(f"option {name} (--{name} {value}): outside {lo}..{hi}"
                                   + (" (or -1 for unbounded)" if name == "depth" else ""))
        if self.defuzzifier is not None and self.defuzzifier not in DEFUZZIFIERS:
            raise QuekaroError(f"option defuzzifier: {self.defuzzifier!r} is not one of {', '.join(DEFUZZIFIERS)}")
        if self.integrator is not None and self.integrator not in CATALOGUE:
            raise QuekaroError(f"option integrator: {self.integrator!r} is not one of Mitsuba's integrators")
        if self.variant is not None and not (isinstance(self.variant, str) and VARIANT_PATTERN.fullmatch(self.variant)):
            raise QuekaroError(f"option variant: {str(self.variant)[:40]!r} is not a Mitsuba variant name")

    def overrides(self) -> dict[str, Any]:
        """The effect decisions the user forced (they win over the analysis)."""
        forced = {"variant": self.variant, "integrator": self.integrator, "max_depth": self.depth}
        return {k: v for k, v in forced.items() if v is not None}

    def to_dict(self) -> dict[str, Any]:
        return {"level": self.level, "spp": self.spp, "depth": self.depth, "threads": self.threads,
                "rules": str(self.rules) if self.rules else None, "defuzzifier": self.defuzzifier,
                "variant": self.variant, "integrator": self.integrator, "units": self.units,
                "sensor": self.sensor}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> RenderOptions:
        """The options of a JSON object; unknown keys are refused, naming them (never silently dropped)."""
        if not isinstance(data, dict):
            raise QuekaroError(f"options must be a JSON object, got {type(data).__name__}")
        unknown = sorted(set(data) - {f.name for f in dataclasses.fields(cls)})
        if unknown:
            raise QuekaroError(f"option {unknown[0][:40]!r} is not known (known: "
                               f"{', '.join(f.name for f in dataclasses.fields(cls))})")
        rules = data.get("rules")
        if rules is not None and not isinstance(rules, str):
            raise QuekaroError(f"option rules: {rules!r} is not a path")
        return cls(level=data.get("level", "off"), spp=data.get("spp"), depth=data.get("depth"),
                   threads=data.get("threads"), rules=Path(rules) if rules else None,
                   defuzzifier=data.get("defuzzifier"), variant=data.get("variant"),
                   integrator=data.get("integrator"), units=data.get("units"), sensor=data.get("sensor", 0))


@dataclass
class JobPlan:
    """A planned job: image size, effects, the user's spp/depth, and the units to render."""

    spec: SceneSpec
    options: RenderOptions
    width: int
    height: int
    effects: Effects
    spp: int
    depth: int
    units: list[Unit]
    prepass_seconds: float = 0.0
    prepass_info: dict[str, Any] = field(default_factory=dict)

    def features(self) -> dict[str, list[float]]:
        """The fuzzy inputs of every unit, in unit order."""
        return {"C": [u.C for u in self.units], "S": [float(u.S) for u in self.units],
                "Nd": [u.Nd for u in self.units]}

    def ranges(self) -> dict[str, tuple[float, float]]:
        """The observed range of each dynamic input over the whole scene (the paper's dynamic sets)."""
        return {name: (min(values), max(values)) for name, values in self.features().items()}


def scene_spp(spec: SceneSpec, sensor_index: int = 0) -> int | None:
    """The sample count the scene's sensor's sampler asks for, read from the XML (None if not stated)."""
    sensors = sensor_elements(expand(spec).root)
    sensor = sensors[sensor_index] if sensor_index < len(sensors) else None
    sampler = sensor.find("sampler") if sensor is not None else None
    if sampler is None:
        return None
    for child in sampler:
        if child.tag == "integer" and child.get("name") == "sample_count":
            try:
                count = int(child.get("value", ""))
            except ValueError:
                return None
            if count < 1:  # Mitsuba reads 0 as "the sampler's default": say so instead of guessing
                raise QuekaroError(f"{spec.path}: sample_count {count} (e.g. from -D) is not a sample count; "
                                   "give 1 or more, or --spp")
            return count
    return None


def farm_min_units(live_agents: int) -> int:
    """Units a farm job needs at least for its live agents: 4 each on small farms, and from 8 agents on
    3 each plus 8 for the end game. Every unit pays a render call and its bands, so past the few each
    agent needs for balance more units cost more than they even out (simulated on caustic-corner
    512x512 with the real auction, 25 ms tile delivery: 32 agents reached 0.80 / 0.79 efficiency with
    4 per agent and 0.83 / 0.81 with 3 + 8, equal / mixed speeds; 8 agents get 32 either way)."""
    n = max(1, live_agents)
    return min(4 * n, 3 * n + 8)


def default_unit_count(width: int, height: int, level: str, min_units: int = 1) -> int:
    """Units of about 256 px a side at level off and 56 px when the rules run, and at least `min_units`
    (a farm asks for a few per agent). At level off nothing is gained by small units in one process:
    each render call costs ~0.05 s and bands add pixels (16 units of 128 px ran 1.16x one plain render of
    cbox 512x512, 256 spp). When the rules run, the rules move samples
    between units, so the noisy corner of a scene must fall in units of its own (the partition weighs
    cost by relative noise, so the costly corner is split and the cheap wall stays in big units), while
    every unit pays a fixed cost per render call (~0.05 s here, ~20 spp of a 40 px unit), a 2 px band
    ((40+4)^2/40^2 = 1.21x the pixels at 40 px, 1.15x at 56) and a kernel compilation per new crop size.
    On caustic-corner at 160x160 (model from measured per-pixel noise and per-call cost) level S reached
    0.84x the uniform relMSE with 8 units, 0.91x with 7, 0.96x with 12 and 1.45x with 22 (40 px)."""
    side = 256 if level == "off" else 56
    wanted = max(round(width * height / (side * side)), min_units)
    return max(1, min(256, wanted, width * height))


def plan_job(spec: SceneSpec, options: RenderOptions, seed: int = 0, min_units: int = 1) -> JobPlan:
    """Analyse the scene's effects, run the pre-pass (optimised levels only) and partition the image
    (into `options.units` units, else the default count and at least `min_units`)."""
    effects = analyse(spec, options.overrides())
    info = film_info(spec, options.sensor)
    width, height = info.width, info.height
    spp = options.spp or scene_spp(spec, options.sensor) or DEFAULT_SPP
    depth = effects.max_depth
    target = options.units or default_unit_count(width, height, options.level, min_units)
    if not effects.splittable:
        if options.level != "off":
            effects.reasons.append(f"level {options.level} not applied: the rules choose per unit, and this "
                                   "integrator renders as one unit at the user's spp and depth")
        return JobPlan(spec, dataclasses.replace(options, level="off"), width, height, effects, spp, depth,
                       _plain_units(width, height, 1))
    if options.level == "off":
        # The rules need no features at level off, so the pre-pass would be pure overhead.
        units = _plain_units(width, height, target)
        return JobPlan(spec, options, width, height, effects, spp, depth, units)
    return _planned_with_prepass(spec, options, effects, width, height, spp, depth, target, seed)


def _planned_with_prepass(spec: SceneSpec, options: RenderOptions, effects: Effects, width: int,
                          height: int, spp: int, depth: int, target: int, seed: int) -> JobPlan:
    from core import scene as scene_mod
    from master.complexity import prepass
    from master.partition import partition

    start = time.perf_counter()
    scene = scene_mod.load(spec, effects.variant, options.threads)
    own = integrators.scene_element(expand(spec).root)
    radiance = effects.override or integrators.radiance_xml(own, depth)
    cmap = prepass(scene, width, height, integrator=radiance, max_depth=depth,
                   threads=options.threads, full_spp=spp, seed=seed, sensor=options.sensor)
    units = partition(cmap, target_units=target)
    seconds = time.perf_counter() - start
    return JobPlan(spec, options, width, height, effects, spp, depth, units, seconds, dict(cmap.info))


def _plain_units(width: int, height: int, target: int) -> list[Unit]:
    rects = equal_tiles(width, height, target)
    units = []
    for i, rect in enumerate(rects):
        units.append(Unit(index=i, rect=rect, C=0.0, S=rect.area, Nd=0.0, cost=float(rect.area),
                          neighbours=()))
    return units
