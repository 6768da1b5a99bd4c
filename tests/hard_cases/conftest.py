"""Shared set-up of the hard-case catalogue: where its data lives, and two ways to render a case scene.

A scene case is rendered along one of two routes, and every scene test runs on both:
  - "units": the job's parts called in the pipeline's order (pre-pass and partition at optimised levels,
    equal tiles at `off`; the planner; every unit in one shared `RenderProcess` child, one by one as an
    agent renders them; `compose`). Cheap, since one child process serves the whole catalogue.
  - "pipeline": `planning.pipeline.render_job` with `RenderOptions`, exactly as `quekaro render` runs it
    (at a rule level its units in batches where the scene allows, core.render.batch).
    Skipped, with the import error as the reason, while `planning.pipeline` cannot be imported.
Both return a `Run`: the composed image, the non-finite pixels counted, the units' parameters and windows.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from core.image.compose import compose
from core.model.geometry import filter_reach
from core.model.job import SceneSpec
from core.model.seeds import unit_seed
from core.render.process import RenderProcess, RenderRequest
from core.rules.unit_params import Planner
from core.scene.scene import film_info

HERE = Path(__file__).resolve().parent
SCENES = HERE / "scenes"
RULES = HERE / "rules"
MESSAGES = HERE / "messages"
VARIANT = "llvm_ad_rgb"
THREADS = 1


def pipeline_import_error() -> str | None:
    """None when planning.pipeline imports, else why not (the skip reason of the pipeline route)."""
    try:
        import planning.pipeline  # noqa: F401
    except ImportError as exc:
        return f"planning.pipeline cannot be imported yet: {exc}"
    return None


@dataclass
class Run:
    """What one rendered case gives the tests to check."""

    image: np.ndarray
    nonfinite: int  # pixels the unit renders found non-finite (and zeroed)
    units: list[dict[str, Any]]  # per unit: rect, window, depth, spp, band, C, Nd
    compose: dict[str, Any]
    report: dict[str, Any] = field(default_factory=dict)  # the pipeline's JSON report (pipeline route)


@pytest.fixture(scope="session")
def worker() -> Iterator[RenderProcess]:
    """One render child for the whole catalogue (Mitsuba imported once)."""
    with RenderProcess() as w:
        yield w


def _plan_units(spec: SceneSpec, level: str, spp: int, depth: int, target: int) -> list[Any]:
    from core.model.units import WorkUnit
    from planning.partition import equal_tiles

    info = film_info(spec)
    if level == "off":
        rects = equal_tiles(info.width, info.height, target)
        return [WorkUnit(index=i, rect=r, C=0.0, S=r.area, Nd=0.0, cost=float(r.area)) for i, r in enumerate(rects)]
    from core.scene import scene as scene_mod
    from planning.complexity import prepass
    from planning.partition import partition

    scene = scene_mod.load(spec, VARIANT, THREADS)
    cmap = prepass(scene, info.width, info.height, integrator="path", max_depth=depth, threads=THREADS,
                   full_spp=spp, seed=1)
    return partition(cmap, target_units=target)


def render_units(worker: RenderProcess, spec: SceneSpec, level: str, spp: int, depth: int, units: int,
                 rules: Path | None = None) -> Run:
    """The "units" route: the pipeline's steps, every unit rendered in the shared worker."""
    info = film_info(spec)
    plan = _plan_units(spec, level, spp, depth, units)
    features = {"C": [u.C for u in plan], "S": [float(u.S) for u in plan], "Nd": [u.Nd for u in plan]}
    ranges = {k: (min(v), max(v)) for k, v in features.items()}
    reach = filter_reach(info.filter_radius)
    chosen = Planner(rules).plan(features, level, user_depth=depth, user_spp=spp, ranges=ranges, min_band=reach)
    tiles, records = [], []
    for unit, p in zip(plan, chosen, strict=True):
        job = RenderRequest(spec, VARIANT, "path", p.depth, p.spp, unit_seed("hard", unit.index, 0), info.width,
                      info.height, unit.rect, p.band, THREADS, "hard", unit.index)
        tile = worker.render(job, timeout=120)
        tiles.append(tile)
        records.append({"rect": unit.rect.as_list(), "window": tile.rect.as_list(), "depth": p.depth,
                        "spp": p.spp, "band": p.band, "C": unit.C, "Nd": unit.Nd,
                        "nonfinite": int(tile.meta["nonfinite"])})
    image, report = compose(tiles, info.width, info.height, reach=reach)
    return Run(image, sum(r["nonfinite"] for r in records), records, report.to_dict())


def render_pipeline(spec: SceneSpec, level: str, spp: int, depth: int, units: int, rules: Path | None,
                    out: Path) -> Run:
    """The "pipeline" route: `render_job` as `quekaro render` calls it; reads back what it wrote."""
    from core.image.imageio import read_image
    from core.model.job import RenderOptions
    from planning.pipeline import render_job

    options = RenderOptions(level=level, spp=spp, depth=depth, threads=THREADS, rules=rules, units=units)
    report = render_job(spec, options, out)
    written = json.loads(out.with_suffix(".json").read_text())
    assert written["totals"]["nonfinite"] == report["totals"]["nonfinite"]
    records = [{**u, "window": None} for u in report["units"]]
    return Run(read_image(out), int(report["totals"]["nonfinite"]), records, report["compose"], report)


Renderer = Callable[..., Run]


@pytest.fixture(params=["units", "pipeline"])
def render(request: pytest.FixtureRequest, tmp_path: Path) -> Renderer:
    """render(scene_name, level, spp=4, depth=4, units=4, rules=None, **defines) -> Run, on either route."""
    route = request.param
    if route == "pipeline" and (reason := pipeline_import_error()):
        pytest.skip(reason)

    def run(scene: str, level: str, spp: int = 4, depth: int = 4, units: int = 4, rules: Path | None = None,
            **defines: Any) -> Run:
        spec = SceneSpec(SCENES / scene, {"spp": spp, "depth": depth, **defines})
        if route == "units":
            return render_units(request.getfixturevalue("worker"), spec, level, spp, depth, units, rules)
        return render_pipeline(spec, level, spp, depth, units, rules, tmp_path / "out.exr")

    return run
