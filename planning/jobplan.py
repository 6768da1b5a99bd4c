"""Planning a job: from a scene and the user's options to the effects to simulate and the work units.

This is the master's half of the pipeline before any unit renders: effect analysis, the complexity
pre-pass, and the partition into units with their features (C, S, Nd); for an adaptive job, the render
units with their shares of the level's samples (planning.budgets). The in-process pipeline
(`quekaro render`) and the farm's master both start from a `JobPlan`.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from enum import StrEnum
from typing import Any

from lxml import etree

from core.errors import QuekaroError, RenderError, SceneError
from core.image.denoise import AOV_SPP, DENOISER_FILTER
from core.image.film import bitmap_names
from core.model import integrators
from core.model.job import RGB, Effects, ImageFile, JobPlan, RenderOptions, SceneSpec
from core.model.levels import OFF
from core.model.units import WorkUnit
from core.render.per_pixel import check_renderable, spill_problem
from core.render.process import build_integrator
from core.rules.outputs import LS_MAX
from core.rules.unit_params import Planner, RenderParams, adaptive_params
from core.scene.effects import analyse_loaded
from core.scene.scene import expand, film_info, sensor_elements, sensor_of
from planning import budgets, depthcut
from planning.complexity import ComplexityMap, film_size, prepass
from planning.partition import DEFAULT_SIZES, MERGE_TOLERANCE, equal_tiles, partition

# Sensors whose film crop renders exactly that part of the image (compared with plain Mitsuba per pixel in
# the compatibility suite). A batch sensor, for one, picks its camera from the position within the crop,
# so its tiles showed the wrong camera; any sensor not listed renders whole, as one unit.
TILED_SENSORS = ("perspective", "thinlens", "orthographic")


def scene_spp(spec: SceneSpec, sensor_index: int = 0, loaded: Any = None) -> int | None:
    """The sample count the scene's sensor's sampler asks for, read from the XML (None if not stated);
    where the XML cannot say which sensor that is, the `loaded` scene's (None without it)."""
    return _stated_spp(sensor_elements(expand(spec).root), spec, sensor_index, loaded)


def _stated_spp(sensors: list[etree._Element] | None, spec: SceneSpec, sensor_index: int,
                loaded: Any) -> int | None:
    """`scene_spp` from the scene's sensor elements (core.scene.scene.sensor_elements)."""
    if sensors is None:
        return int(loaded.sensors()[sensor_index].sampler().sample_count()) if loaded is not None else None
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
            if count < 1:  # Mitsuba loads 0, and its render then dies of a floating-point exception
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


# A unit's side (px) when the rules run: in one process, and for a farm's job (not an adaptive one, whose
# partition is the same wherever it runs). See default_unit_count.
RULE_SIDE = 56
FARM_RULE_SIDE = 90


def default_unit_count(width: int, height: int, level: str, min_units: int = 1, spp: int | None = None,
                       farm: bool = False) -> int:
    """Units of about 256 px a side at level off and RULE_SIDE (FARM_RULE_SIDE for a `farm` job) when the
    rules run, and at least `min_units` (a farm asks for a few per agent). Given the `spp` (a job's plan),
    level off is one unit, Mitsuba's own render call over the whole film, as the `mitsuba` command renders
    it: every further unit costs a render call and its bands (cbox 512x512 at 256 spp, 4 units ran 1.05x
    the command's whole process, one unit 1.02x; `--progressive` renders level off in passes with a live
    image). Without the spp (an adaptive job's render grid) level off tiles by size.
    When the rules run, the rules move samples
    between units, so the noisy corner of a scene must fall in units of its own (the partition weighs
    cost by relative noise, so the costly corner is split and the cheap wall stays in big units), while
    every unit pays a fixed cost per render call (~0.05 s here, ~20 spp of a 40 px unit), a 2 px band
    ((40+4)^2/40^2 = 1.21x the pixels at 40 px, 1.15x at 56) and a kernel compilation per new crop size.
    On caustic-corner at 160x160 (model from measured per-pixel noise and per-call cost) level S reached
    0.84x the uniform relMSE with 8 units, 0.91x with 7, 0.96x with 12 and 1.45x with 22 (40 px). A farm's
    unit also pays its award, its tile's upload and its bands in each agent's batch, so a farm's units are
    larger (docs/benchmarks/unit-size/README.md: level S at 34 units against 85, side by side)."""
    side = 256 if level == "off" else FARM_RULE_SIDE if farm else RULE_SIDE
    wanted = round(width * height / (side * side))
    if level == "off" and spp is not None:
        wanted = 1
    wanted = max(wanted, min_units)
    return max(1, min(256, wanted, width * height))


class Floors(StrEnum):
    """When a rule level's plan measures its units' depth floors (planning.depthcut)."""

    RULES = "rules"  # where the plan's rules cut some unit's depth (the rules that render it: one process)
    ALWAYS = "always"  # at every rule level: rules the plan cannot see choose (a farm's agents with others)
    HELD = "held"  # as RULES, and where they cut none every unit's floor is the user's depth: a farm whose
    # agents plan as the master does, where an agent with other rules may still join and must not cut


def plan_job(spec: SceneSpec, options: RenderOptions, seed: int = 0, min_units: int = 1,
             floors: Floors = Floors.RULES, farm: bool = False) -> JobPlan:
    """Analyse the scene's effects, run the pre-pass (optimised levels only) on the scene as the analysis
    loaded it, and partition the image (into `options.units` units, else the default count and at least
    `min_units`). `floors`: when the units' depth floors are measured (Floors); `farm`: a farm's job, whose
    units are larger where the rules run (default_unit_count)."""
    return plan_job_loaded(spec, options, seed, min_units, floors, farm)[0]


def plan_job_loaded(spec: SceneSpec, options: RenderOptions, seed: int = 0, min_units: int = 1,
                    floors: Floors = Floors.RULES, farm: bool = False) -> tuple[JobPlan, Any]:
    """`plan_job`, and the scene as the analysis loaded it in the plan's variant (the pre-pass leaves it
    as loaded), for a process that renders the units next."""
    floors = Floors(floors)  # a stale boolean (the former floors_always) is refused, not read as RULES
    own_filter = film_info(spec, options.sensor).filter_type if options.denoise else ""
    if options.denoise:
        spec = dataclasses.replace(spec, rfilter=DENOISER_FILTER)
    effects, loaded = analyse_loaded(spec, options.overrides())
    _check_renders(spec, options, loaded)
    if options.denoise:
        _check_denoisable(spec, effects, loaded, options.sensor)
        effects.reasons.extend(denoise_reasons(own_filter))
    plan = pin_passes(_plan(spec, options, seed, min_units, effects, loaded, floors, farm))
    if options.units and len(plan.units) != options.units and plan.effects.splittable:
        plan.effects.reasons.append(
            f"--units {options.units} is a target: {len(plan.units)} made (units are at least {DEFAULT_SIZES[0]} "
            f"px, and neighbours whose complexity differs by under {MERGE_TOLERANCE:.0%} merge)")
    return plan, loaded


def denoise_reasons(own_filter: str) -> list[str]:
    """What a denoised job changes, and why (its effects' reasons)."""
    return [f"denoise: box reconstruction filter in place of the scene's {own_filter}: the denoiser expects each "
            "pixel's own noise, and a wider filter spreads every sample over its neighbours, where it gains little "
            "(quekaro bench denoise measures both: docs/benchmarks/denoise)",
            f"denoise: albedo and shading normal rendered for the denoiser in one pass of {AOV_SPP} spp over the "
            "image (Mitsuba's aov integrator); the raw image, with them, is kept as OUT.raw.exr"]


def _check_denoisable(spec: SceneSpec, effects: Effects, loaded: Any, sensor: int) -> None:
    """Refuse --denoise where the denoiser cannot take the image: a film whose colour is not R, G, B (XYZ,
    luminance, spectral films) or a polarized render (its Stokes vectors)."""
    film = sensor_of(loaded, sensor).film()
    names = _film_names(loaded, sensor, [])[:3]
    if names != RGB or "polarized" in effects.variant:
        what = f"variant {effects.variant} (Stokes vectors)" if "polarized" in effects.variant else \
            f"film {film.class_name()} writes {list(names)}"
        raise QuekaroError(f"{spec.path}: --denoise: the denoiser takes R, G, B colour; {what}")


def _check_renders(spec: SceneSpec, options: RenderOptions, loaded: Any) -> None:
    """Refuse a scene Mitsuba loads but cannot render: no such sensor, or no integrator (Mitsuba 3.9: "No
    integrator specified") where the user gives none."""
    sensor_of(loaded, options.sensor, str(spec.path))
    if loaded.integrator() is None and not options.integrator:
        raise SceneError(f"{spec.path}: the scene names no integrator, and Mitsuba renders none without one: add "
                         "one (e.g. <integrator type=\"path\"/>) or give --integrator")


def _plan(spec: SceneSpec, options: RenderOptions, seed: int, min_units: int, effects: Effects,
          loaded: Any, floors: Floors = Floors.RULES, farm: bool = False) -> JobPlan:
    """The plan for the analysed scene (`loaded`, its effects `effects`)."""
    info = film_info(spec, options.sensor)
    width, height = info.width, info.height
    sensors = sensor_elements(expand(spec).root)
    spp = (options.spp or _stated_spp(sensors, spec, options.sensor, loaded)
           or _sampler_default(loaded, options.sensor, effects))
    added = _added_channels(loaded, options.integrator)
    _check_image_file(spec, info.image_file, added, options.integrator)
    plan = JobPlan(spec, options, width, height, effects, spp, effects.max_depth, [],
                   filter_radius=info.filter_radius, colour=info.colour, image_file=info.image_file,
                   channels=_tile_channels(loaded, options.sensor, info.colour, added))
    # An adaptive job's --units are its render units (render_units); its rules see the level's own partition,
    # the same wherever it runs: a farm's minimum count (min_units) is its render units' (_adaptive), else
    # the level's budget fell with the farm's size (the rules weigh each unit's size).
    chosen = None if options.adaptive else options.units
    goal = "noise" if options.noise is not None else "time" if options.time is not None else None
    # A noise or time goal places samples by each unit's noise: at level off too, units by size, not one.
    target = chosen or default_unit_count(width, height, options.level, 1 if options.adaptive else min_units,
                                          None if goal else spp, farm and not options.adaptive)
    if not effects.splittable:
        return _one_unit(plan, "this integrator renders as one unit")
    if goal and not chosen and not farm and options.level == OFF and target > 1:
        effects.reasons.append(f"units: {target} of about 256 px, not one: the {goal} goal gives each unit the "
                               "samples its own measured noise asks (one unit would hold the image to its mean)")
    sensor_type, sampler = _sensor_kind(sensors, loaded, options.sensor)
    if sensor_type not in TILED_SENSORS:
        effects.reasons.append(f"one unit, the whole film: sensor {sensor_type}, whose crop windows are not "
                               f"the parts of its image (tiles: {', '.join(TILED_SENSORS)})")
        return _one_unit(plan, f"sensor {sensor_type} renders as one unit")
    if options.level != OFF and sampler not in ("independent", None):
        effects.reasons.append(f"sampler {sampler}: Mitsuba rounds each unit's spp to counts of its own (a "
                               "square, a power of four), so a unit may render more samples than its rules "
                               "chose; the report gives those it rendered")
    if options.in_passes and sampler not in ("independent", None):
        effects.reasons.append(f"sampler {sampler}: each pass stratifies its own samples, not the unit's all "
                               "together: the merged passes are unbiased, but noisier than one render of "
                               "their summed spp would be (the independent sampler loses nothing)")
    if options.level == "off":
        # The rules need no features at level off, so the pre-pass would be pure overhead.
        units = _plain_units(width, height, target)
        return dataclasses.replace(plan, units=units, spill=_spills(options, effects, loaded, len(units), farm))
    if options.adaptive:
        _check_adaptive(spec, loaded, options.sensor)
    radiance = _radiance_at(plan)
    plan, cmap = _with_prepass(plan, target, seed, loaded, radiance(plan.depth))
    if options.adaptive:
        return _adaptive(plan, cmap, min_units)
    return _with_depth_floors(plan, cmap, seed, loaded, radiance, floors)


def _spills(options: RenderOptions, effects: Effects, loaded: Any, units: int, farm: bool) -> bool:
    """Whether a level-off job's passes draw their samples on their units alone (JobPlan.spill): a farm's
    job in passes, over several units, with the scene's own integrator, not denoised (its AOV pass blends),
    where render_core renders the scene so (core.render.per_pixel.spill_problem); the reason goes in the
    effects. In one process a round's passes render in one call that samples each pixel once already
    (core.render.batch), and one call a pass measured slower there."""
    if not farm or not options.in_passes or units < 2 or options.integrator or options.denoise \
            or spill_problem(loaded, options.sensor):
        return False
    effects.reasons.append("bands: each unit's samples are drawn on its own pixels and its band takes their "
                           "filter's spill, so no pixel is sampled twice (the tiles add up to one render's image)")
    return True


def _sampler_default(loaded: Any, sensor: int, effects: Effects) -> int:
    """The spp plain Mitsuba renders where the scene states no sample_count: its sampler's default (4 for
    the independent sampler), said in the effects."""
    sampler = loaded.sensors()[sensor].sampler()
    count = int(sampler.sample_count())
    effects.reasons.append(f"spp {count}: the scene's sampler states no sample_count, and {count} is its default "
                           f"({sampler.class_name()}), as plain Mitsuba renders it; --spp sets another")
    return count


def _sensor_kind(sensors: list[etree._Element] | None, loaded: Any, index: int) -> tuple[str, str | None]:
    """The plugin types of sensor `index` (of the scene's sensor elements) and of its sampler (None:
    Mitsuba's default, independent), as written; where the XML cannot say which sensor that is, from the
    loaded scene."""
    if sensors is None:
        sensor = loaded.sensors()[index]
        # Mitsuba's class names are its plugin names with a suffix (ThinLensCamera, IrradianceMeter, BatchSensor)
        kind = sensor.class_name().removesuffix("Camera").removesuffix("Sensor").lower()
        return kind, sensor.sampler().class_name().removesuffix("Sampler").lower()
    element = sensors[index] if index < len(sensors) else None
    if element is None:  # none declared: Mitsuba's default perspective camera
        return "perspective", None
    sampler = element.find("sampler")
    return element.get("type", "perspective"), sampler.get("type") if sampler is not None else None


def _one_unit(plan: JobPlan, why: str) -> JobPlan:
    """The plan as one unit at level off, the user's spp and depth; a rule level is dropped, saying `why`."""
    options = plan.options
    if options.level != OFF:
        plan.effects.reasons.append(f"level {options.level} not applied: the rules choose per unit, and {why} "
                                    "at the user's spp and depth")
    return dataclasses.replace(plan, options=dataclasses.replace(options, level=OFF, adaptive=False),
                               units=_plain_units(plan.width, plan.height, 1))


def _with_prepass(plan: JobPlan, target: int, seed: int, scene: Any,
                  radiance: str) -> tuple[JobPlan, ComplexityMap]:
    """The plan with units from the pre-pass on `scene` (as the analysis loaded it) with the `radiance`
    integrator (XML), partitioned."""
    start = time.perf_counter()
    options, depth = plan.options, plan.depth
    try:
        cmap = prepass(scene, plan.width, plan.height, integrator=radiance, max_depth=depth,
                       threads=options.threads, full_spp=plan.spp, seed=seed, sensor=options.sensor)
    except RuntimeError as exc:  # Mitsuba's own refusal of what the pre-pass asks of this scene
        raise QuekaroError(f"{plan.spec.path}: level {options.level}'s pre-pass (the features its rules read) "
                           f"failed in Mitsuba: {str(exc).strip()[-300:]}; level off renders without it") from exc
    units = partition(cmap, target_units=target)
    return dataclasses.replace(plan, units=units, prepass_seconds=time.perf_counter() - start,
                               prepass_info={**cmap.info, "seed": seed}), cmap


def _with_depth_floors(plan: JobPlan, cmap: ComplexityMap, seed: int, scene: Any,
                       radiance_at: Callable[[int], str], floors: Floors = Floors.RULES) -> JobPlan:
    """The plan with each unit's depth floor (planning.depthcut, measured with `radiance_at`) where its
    rules cut some unit's depth at this level, or at every level (Floors.ALWAYS). Where they cut none the
    passes would be pure overhead: the plan is unchanged, or (Floors.HELD) holds every unit at its depth.
    Where the rules are known, each floor is measured only down to its unit's chosen depth, and a unit
    whose cut cannot repay its passes keeps the depth it was last allowed (the user's where none was
    measured): no floor is lower than the true one, so an agent with other rules may still hold to it."""
    if plan.depth < 2:
        return plan
    # Floors.ALWAYS: the agents' rules may choose any depth, and at most LS_MAX times the user's spp
    needed, samples = None, [math.ceil(plan.spp * LS_MAX)] * len(plan.units)
    if floors != Floors.ALWAYS:
        chosen = plan_params(plan, Planner(plan.options.rules, plan.options.defuzzifier))
        if all(p.depth >= plan.depth for p in chosen):
            return _held(plan) if floors == Floors.HELD else plan
        needed, samples = [p.depth for p in chosen], [p.spp for p in chosen]
    if expand(plan.spec).root.find(".//medium") is not None:
        plan.effects.reasons.append(f"depth: no unit is cut below max_depth {plan.depth}: in a participating "
                                    "medium the pre-pass's few samples miss the rare long paths whose light a "
                                    "cut would lose, so the loss cannot be bounded")
        return _held(plan)
    if cmap.depth_rays is None:  # a map not from the pre-pass: nothing prices the passes, nothing is cut
        return _held(plan)
    low = tuple(max(1, v // 2) for v in cmap.info["low_size"])  # a unit's mean needs no finer grid
    rects, size = [u.rect for u in plan.units], (plan.width, plan.height)
    cost = depthcut.RayCost.from_rays(cmap.depth_rays, rects, size, samples)
    found = depthcut.measure(scene, radiance_at, plan.depth, rects, low, size, seed=seed,
                             sensor=plan.options.sensor, needed=needed, cost=cost)
    units = [dataclasses.replace(u, depth_floor=f) for u, f in zip(plan.units, found.floors, strict=True)]
    return dataclasses.replace(plan, units=units, prepass_seconds=plan.prepass_seconds + found.seconds,
                               prepass_info={**plan.prepass_info, **found.to_info()})


def _held(plan: JobPlan) -> JobPlan:
    """Every unit's floor at the user's depth: no unit is cut."""
    return dataclasses.replace(plan, units=[dataclasses.replace(u, depth_floor=plan.depth) for u in plan.units])


def _radiance_at(plan: JobPlan) -> Callable[[int], str]:
    """The radiance integrator the pre-pass measures with (the user's override, else the scene's own),
    as standalone XML at any depth."""
    override = plan.effects.override
    elem = (etree.Element("integrator", type=override) if override
            else integrators.scene_element(expand(plan.spec).root))
    return lambda depth: integrators.radiance_xml(elem, depth)


def _check_image_file(spec: SceneSpec, image_file: ImageFile, extra: list[str], override: str | None) -> None:
    """Refuse, before any work, a film whose file (PFM, RGBE: colour only) cannot hold the channels the
    integrator that renders adds (`extra`: AOVs, moments): plain Mitsuba renders such a scene and then
    fails to write it."""
    if image_file.format != "openexr" and extra:
        whose = f"--integrator {override}" if override else "integrator"
        raise QuekaroError(f"{spec.path}: the film's file_format {image_file.format} holds colour only, and the "
                           f"{whose} adds channels {extra[:6]}; plain Mitsuba fails to write this image "
                           "too: give the film file_format openexr")


def _added_channels(loaded: Any, override: str | None) -> list[str]:
    """The channels that the integrator that renders adds to the film: the user's override, built here
    as each unit builds it so that one Mitsuba cannot build is refused before any work, else the scene's."""
    if override:
        try:
            renders = build_integrator(override, None, None)
        except RenderError as exc:
            raise QuekaroError(f"--integrator {override}: {exc}") from exc
    else:
        renders = loaded.integrator()
    return list(renders.aov_names()) if renders is not None else []


def _tile_channels(loaded: Any, sensor: int, colour: tuple[str, ...], added: list[str]) -> tuple[str, ...]:
    """The channels each tile carries, as core.image.film.film_channels names a rendered film's: colour as
    R, G, B, then what Mitsuba's film holds past its colour once prepared for the integrator's `added`
    channels (its alpha, which PFM and RGBE films drop, then those)."""
    return (*RGB, *_film_names(loaded, sensor, added)[len(colour):])


def _film_names(loaded: Any, sensor: int, added: list[str]) -> tuple[str, ...]:
    """The channels of the sensor's film prepared for `added`, read from the film itself at 1 x 1 pixel, so
    that nothing of the image's size is allocated."""
    film = sensor_of(loaded, sensor).film()
    with film_size(loaded, 1, 1, sensor):
        film.prepare(added)
        return tuple(bitmap_names(film.bitmap()))


def _check_adaptive(spec: SceneSpec, loaded: Any, sensor: int) -> None:
    """Refuse an adaptive job before its pre-pass where per-pixel counts cannot render the scene as
    Mitsuba does (core.render.per_pixel.check_renderable: its sampler, film, integrator), naming the file."""
    try:
        check_renderable(loaded, sensor)
    except RenderError as exc:
        raise QuekaroError(f"{spec.path}: --adaptive: {exc}") from exc


def _adaptive(plan: JobPlan, cmap: ComplexityMap, min_units: int) -> JobPlan:
    """An adaptive job's plan: the level's samples (the rules on the level's partition) shared among the
    render units by the pre-pass's noise (planning.budgets). Its samples are placed per pixel inside each
    unit, so units only need to be few (every render call costs ~0.05 s and its bands)."""
    mean = budgets.level_spp(plan.units, plan_params(plan, Planner(plan.options.rules, plan.options.defuzzifier)))
    count = plan.options.units or default_unit_count(plan.width, plan.height, OFF, min_units)
    grid = _plain_units(plan.width, plan.height, count)
    split = budgets.shares(cmap.relative_noise(), [u.rect for u in grid], mean)
    units = [dataclasses.replace(u, spp=spp, cost=float(cmap.cost[u.rect.y:u.rect.y1, u.rect.x:u.rect.x1].sum()))
             for u, spp in zip(grid, split.spp, strict=True)]  # cost as the partition's: rays at 1 spp
    return dataclasses.replace(plan, units=units, first_spp=split.first,
                               shares={**split.to_dict(), "rule_units": len(plan.units)})


def pin_passes(plan: JobPlan) -> JobPlan:
    """A progressive job at a rule level: each unit holds the depth and samples its rules chose, once, so that
    all its passes, on whichever agent, estimate one image. Other plans are returned as they are."""
    if not plan.options.in_passes or plan.options.level == OFF:
        return plan
    chosen = plan_params(plan, Planner(plan.options.rules, plan.options.defuzzifier))
    units = [dataclasses.replace(u, depth=p.depth, spp=p.spp) for u, p in zip(plan.units, chosen, strict=True)]
    return dataclasses.replace(plan, units=units)


def plan_params(plan: JobPlan, planner: Planner) -> list[RenderParams]:
    """Each unit's depth, spp and band: the plan's own shares in an adaptive job, else the rules' at the
    job's optimisation level."""
    if plan.first_spp is not None:
        return adaptive_params(plan.units, plan.depth, plan.reach)
    return planner.plan({k: list(v) for k, v in plan.features().items()}, plan.options.level,
                        user_depth=plan.depth, user_spp=plan.spp, ranges=plan.ranges(), min_band=plan.reach,
                        depth_floor=[u.depth_floor for u in plan.units])


def _plain_units(width: int, height: int, target: int) -> list[WorkUnit]:
    rects = equal_tiles(width, height, target)
    units = []
    for i, rect in enumerate(rects):
        units.append(WorkUnit(index=i, rect=rect, C=0.0, S=rect.area, Nd=0.0, cost=float(rect.area),
                          neighbours=()))
    return units
