"""The whole job in one process (`quekaro render`): plan, choose each unit's parameters with the
fuzzy rules, render every unit in a child process, compose the tiles and write the outputs.

The farm runs exactly these steps, with the unit renders done by agents; `assemble` (tiles to image,
EXR, PNG and report) is shared with the master agent.
"""

from __future__ import annotations

import json
import logging
import os
import time
import uuid
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from core.model.hashing import sha256_file
from core.model.job import JobPlan, RenderOptions, SceneSpec
from core.model.seeds import plan_seed, unit_seed
from core.render.compose import TileSource, compose_planar
from core.render.imageio import write_exr, write_png_planar
from core.render.planner import Planner, RenderParams
from core.render.tiles import Tile
from core.render.worker import RenderRequest, RenderWorker
from planning.jobplan import plan_job

log = logging.getLogger(__name__)

UNIT_TIMEOUT_S = 3600.0


def plan_params(plan: JobPlan, planner: Planner) -> list[RenderParams]:
    """Each unit's depth, spp and band, from the rules at the job's optimisation level."""
    return planner.plan({k: list(v) for k, v in plan.features().items()}, plan.options.level,
                        user_depth=plan.depth, user_spp=plan.spp, ranges=plan.ranges())


def unit_job(plan: JobPlan, index: int, params: RenderParams, job_id: str, threads: int | None) -> RenderRequest:
    """The render order for one unit, with a seed unique to (job, unit, pass)."""
    unit = plan.units[index]
    return RenderRequest(
        scene=plan.spec, variant=plan.effects.variant, integrator=plan.effects.override,
        max_depth=params.depth, spp=params.spp, seed=unit_seed(job_id, unit.index, 0),
        width=plan.width, height=plan.height, unit=unit.rect, band=params.band, threads=threads,
        job_id=job_id, unit_index=unit.index, sensor=plan.options.sensor,
    )


def unit_record(plan: JobPlan, tile: Tile, params: dict[str, Any]) -> dict[str, Any]:
    """One unit's line in the report: where it is, what the rules saw and chose, what it cost."""
    unit = plan.units[int(tile.meta.get("unit_index", -1))]
    return {
        "index": unit.index, "rect": unit.rect.as_list(), "C": unit.C, "S": unit.S, "Nd": unit.Nd,
        "depth": params.get("depth"), "spp": params.get("spp"), "band": params.get("band"),
        "outputs": params.get("outputs", {}), "seconds": float(tile.meta.get("seconds", 0.0)),
        "nonfinite": int(tile.meta.get("nonfinite", 0)), "agent": params.get("agent"),
        "rules": params.get("rules"),
        **({"emulated": True} if params.get("emulated") else {}),  # slept by an emulated agent, not rendered
    }


def assemble(plan: JobPlan, tiles: Iterable[Tile | TileSource], params: dict[int, dict[str, Any]], out: Path,
             started: float, extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """Compose the tiles (in memory, or sources read from their files as needed) and write OUT.exr,
    OUT.png and OUT.json; return the report.

    `started` is the job's start on the `time.perf_counter` clock (for the total seconds)."""
    tiles = list(tiles)
    image, compose_report = compose_planar(tiles, plan.width, plan.height)
    channels = tiles[0].channels if tiles else ("R", "G", "B")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_exr(out, image, channels=channels, planar=True)
    write_png_planar(out.with_suffix(".png"), image)
    del image
    units = sorted((unit_record(plan, t, params[int(t.meta["unit_index"])]) for t in tiles),
                   key=lambda u: u["index"])
    report = {
        "scene": plan.spec.to_dict(), "options": plan.options.to_dict(),
        "image": {"width": plan.width, "height": plan.height, "exr": str(out),
                  "png": str(out.with_suffix(".png")), "channels": list(channels), "sensor": plan.options.sensor},
        "effects": plan.effects.to_dict(), "user": {"spp": plan.spp, "depth": plan.depth},
        "prepass": plan.prepass_info, "units": units, "compose": compose_report.to_dict(),
        "totals": {
            "units": len(units), "prepass_seconds": plan.prepass_seconds,
            "render_seconds": sum(u["seconds"] for u in units),
            "samples": sum(u["spp"] * u["rect"][2] * u["rect"][3] for u in units),
            "nonfinite": sum(u["nonfinite"] for u in units),
            "emulated_units": sum(bool(u.get("emulated")) for u in units),
        },
    }
    report.update(extra or {})
    report["totals"]["seconds"] = time.perf_counter() - started
    write_json_atomic(out.with_suffix(".json"), report)
    return report


def write_json_atomic(path: Path, data: dict[str, Any]) -> None:
    """Write JSON through a .part file: a full disk leaves the .part, never a torn file."""
    tmp = path.with_name(f".{path.name}.part")
    tmp.write_text(json.dumps(data, indent=2))
    os.replace(tmp, path)


@dataclass(frozen=True)
class Progress:
    """How far a job in one process is: units rendered, and samples (spp x pixels) rendered of all;
    `pixels` the image's, so that samples / pixels is the mean spp rendered so far."""

    units_done: int
    units_total: int
    samples_done: int
    samples_total: int
    pixels: int


def render_job(spec: SceneSpec, options: RenderOptions, out: Path, job_id: str | None = None,
               progress: Callable[[Progress], None] | None = None) -> dict:
    """Render the scene as units in one process; write OUT.exr/.png/.json and return the report.
    `progress` hears after the plan and after every unit."""
    start = time.perf_counter()
    job_id = job_id or uuid.uuid4().hex[:12]
    worker = RenderWorker()
    worker.launch()  # the child imports Mitsuba while this process plans; its first render waits for it
    try:
        seed = plan_seed(sha256_file(spec.path), spec.defines, options.to_dict())
        plan = plan_job(spec, options, seed=seed)
        planner = Planner(options.rules, options.defuzzifier)
        chosen = plan_params(plan, planner)
        samples = [p.spp * u.rect.area for u, p in zip(plan.units, chosen, strict=True)]
        report = progress or (lambda _p: None)
        report(Progress(0, len(plan.units), 0, sum(samples), plan.width * plan.height))
        tiles, params = [], {}
        for unit, p in zip(plan.units, chosen, strict=True):
            job = unit_job(plan, unit.index, p, job_id, options.threads)
            tiles.append(worker.render(job, timeout=UNIT_TIMEOUT_S))
            params[unit.index] = {**p.to_dict(), "rules": planner.rules_path.name}
            report(Progress(len(tiles), len(plan.units), sum(samples[:len(tiles)]), sum(samples),
                            plan.width * plan.height))
    finally:
        worker.stop()
    return assemble(plan, tiles, params, out, start, {"job_id": job_id})
