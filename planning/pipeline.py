"""The whole job in one process (`quekaro render`): plan, choose each unit's parameters with the
fuzzy rules, render every unit in a child process, compose the tiles and write the outputs.

The farm runs exactly these steps, with the unit renders done by agents; `assemble` (tiles to image,
EXR, PNG and report) is shared with the master agent.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import threading
import time
import uuid
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from core.errors import QuekaroError, RenderError, SceneError
from core.files import staged_together, written_atomically
from core.image.compose import TileSource, compose_planar, image_channels
from core.image.denoise import AOV_SPP, AOVS, DENOISER_CHANNELS, QUALITY, denoise_planar
from core.image.film import display_rgb, film_output
from core.image.imageio import write_image, write_png_planar
from core.image.passes import UnitPasses, merge_pass
from core.image.tiles import Tile
from core.interrupt import first_ctrl_c_stops
from core.model.geometry import Rect
from core.model.hashing import sha256_file
from core.model.job import RAW_SUFFIX, ImageFile, JobPlan, RenderOptions, SceneSpec
from core.model.levels import OFF
from core.model.seeds import plan_seed, unit_seed
from core.model.units import WorkUnit
from core.render.batch import batch_name, batches, render_batch, together_problem_here
from core.render.process import ADAPTIVE_META, RenderProcess, RenderRequest, adopt_scene
from core.rules.unit_params import Planner, RenderParams
from planning.jobplan import plan_job_loaded, plan_params
from planning.progressive import (
    BUDGET,
    ONE_PROCESS_PASSES,
    TIME,
    Finish,
    Goal,
    PassDone,
    PassOrder,
    Progressive,
    RenderRound,
    Stop,
)

log = logging.getLogger(__name__)

UNIT_TIMEOUT_S = 3600.0
STOPPING = ("quekaro: stopping: the image keeps the passes merged so far, once every unit has one (Ctrl-C again "
            "quits without it)")
# What a progressive unit's report line adds (ProgressiveRun._record).
PASS_RECORD = ("passes", "relmse_estimate", "relative_error_estimate", "verdict")


def unit_job(plan: JobPlan, unit: WorkUnit, params: RenderParams, job_id: str, threads: int | None) -> RenderRequest:
    """The render order for one unit (in two passes in an adaptive job), with a seed unique to (job, unit)."""
    return RenderRequest(
        scene=plan.spec, variant=plan.effects.variant, integrator=plan.effects.override,
        max_depth=params.depth, spp=params.spp, seed=unit_seed(job_id, unit.index, 0),
        width=plan.width, height=plan.height, unit=unit.rect, band=params.band, threads=threads,
        job_id=job_id, unit_index=unit.index, sensor=plan.options.sensor, first=plan.first_spp,
    )


def aov_job(plan: JobPlan, job_id: str, threads: int | None) -> RenderRequest:
    """The render order of a denoised job's AOV pass: the denoiser's albedo and normal, whole image."""
    return RenderRequest(
        scene=plan.spec, variant=plan.effects.variant, integrator=None, max_depth=None, spp=AOV_SPP,
        seed=unit_seed(job_id, len(plan.units), 0), width=plan.width, height=plan.height,
        unit=Rect(0, 0, plan.width, plan.height), threads=threads, job_id=job_id, sensor=plan.options.sensor, aovs=AOVS,
    )


def denoiser_planes(tile: Tile) -> np.ndarray:
    """The AOV pass's tile as the denoiser reads it: its `DENOISER_CHANNELS` planes, (6, H, W)."""
    index = {name: i for i, name in enumerate(tile.channels)}
    pixels = tile.pixels
    return np.stack([pixels[..., index[name]] for name in DENOISER_CHANNELS])


AOV_PASS_FILE = "aov-pass.npy"  # a farm job's AOV pass, in its folder on the master


def save_aov_pass(path: Path, planes: np.ndarray) -> None:
    """Keep a job's AOV pass (`denoiser_planes`) as a .npy file, written whole or not at all."""
    def write(tmp: Path) -> None:
        with open(tmp, "wb") as handle:
            np.save(handle, np.asarray(planes, dtype=np.float32), allow_pickle=False)

    written_atomically(path, write, "the denoiser's AOV pass")


def load_aov_pass(path: Path) -> np.ndarray | None:
    """The AOV pass `save_aov_pass` kept, or None where there is none (not yet rendered)."""
    try:
        return np.load(path, allow_pickle=False)
    except FileNotFoundError:
        return None


def render_aov_pass(worker: RenderProcess, plan: JobPlan, job_id: str) -> np.ndarray:
    """A denoised job's AOV pass (`aov_job`), rendered by `worker`, as the denoiser reads it."""
    return denoiser_planes(worker.render(aov_job(plan, job_id, plan.options.threads), UNIT_TIMEOUT_S))


def kept_aov_pass(worker: RenderProcess, plan: JobPlan, job_id: str, path: Path) -> np.ndarray:
    """The AOV pass kept at `path`, rendered and kept there first where it is not (a farm job's)."""
    planes = load_aov_pass(path)
    if planes is None:
        planes = render_aov_pass(worker, plan, job_id)
        save_aov_pass(path, planes)
    return planes


def unit_record(unit: WorkUnit, tile: Tile | TileSource, params: dict[str, Any]) -> dict[str, Any]:
    """One unit's line in the report: where it is, what the rules saw and chose, what it cost."""
    return {
        "index": unit.index, "rect": unit.rect.as_list(), "C": unit.C, "S": unit.S, "Nd": unit.Nd,
        "depth": params.get("depth"), "spp": params.get("spp"), "band": params.get("band"),
        "outputs": params.get("outputs", {}), "seconds": float(tile.meta.get("seconds", 0.0)),
        "nonfinite": int(tile.meta.get("nonfinite", 0)), "agent": params.get("agent"),
        "rules": params.get("rules"), "method": tile.meta.get("window_method"),
        **({"threads": tile.meta["threads"]} if "threads" in tile.meta else {}),  # Dr.Jit's, as it rendered
        **({"depth_floor": unit.depth_floor} if unit.depth_floor is not None else {}),
        **{k: tile.meta[k] for k in ADAPTIVE_META if k in tile.meta},  # a two-pass render's own account
        **({"emulated": True} if params.get("emulated") else {}),  # slept by an emulated agent, not rendered
        **{k: params[k] for k in PASS_RECORD if k in params},  # a progressive unit's passes and noise
    }


def assemble(plan: JobPlan, tiles: Iterable[Tile | TileSource], params: dict[int, dict[str, Any]], out: Path,
             started: float, extra: dict[str, Any] | None = None, aov_pass: np.ndarray | None = None,
             partial: bool = False) -> dict[str, Any]:
    """Compose the tiles (in memory, or sources read from their files as needed) and write OUT.exr,
    OUT.png and OUT.json; return the report. `aov_pass`: a denoised job's (`denoiser_planes`); `partial`:
    the tiles of a job that did not finish, pixels that none covers black.

    `started` is the job's start on the `time.perf_counter` clock (for the total seconds)."""
    job = composed(plan, plan.units, tiles, params, partial)
    job.denoiser = aov_pass
    return write_outputs(plan, job, out, started, extra)


@dataclass
class Composed:
    """A job's image before it is written: planar (channels, H, W), the channel names, what composing did
    and each unit's line in the report."""

    image: np.ndarray
    channels: tuple[str, ...]
    compose: dict[str, Any]
    units: list[dict[str, Any]]
    denoiser: np.ndarray | None = None  # a denoised job's AOV pass, planar in DENOISER_CHANNELS order


def composed(plan: JobPlan, units: Sequence[WorkUnit], tiles: Iterable[Tile | TileSource],
             params: dict[int, dict[str, Any]], partial: bool = False) -> Composed:
    """The tiles of the plan's `units` blended into one image, with the units' report lines (`partial`: some
    units have none, their pixels black)."""
    tiles = list(tiles)
    image, compose_report = compose_planar(tiles, plan.width, plan.height, partial, reach=plan.reach)
    channels = image_channels(tiles[0].channels) if tiles else ("R", "G", "B")
    records = (unit_record(units[int(t.meta["unit_index"])], t, params[int(t.meta["unit_index"])]) for t in tiles)
    return Composed(image, channels, compose_report.to_dict(), sorted(records, key=lambda u: u["index"]))


def write_outputs(plan: JobPlan, job: Composed, out: Path, started: float,
                  extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """Write the image as the film asks (OUT.exr, or OUT.pfm / OUT.rgbe: every channel), OUT.png and the
    report OUT.json (and a denoised job's raw image, OUT.raw.exr); return the report. All or none: they are
    written under temporary names and renamed together, so a failure (a full disk) leaves an earlier
    render's files as they were."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    raw, job, denoised = job, *_denoised(plan, job, out)
    image, channels = film_output(job.image, job.channels, plan.colour)
    image_path = out.with_suffix(plan.image_file.suffix)
    paths = [image_path, out.with_suffix(".png"), *([out.with_suffix(RAW_SUFFIX)] if denoised else []),
             out.with_suffix(".json")]  # the report last: it says the set is complete
    with staged_together(paths) as (staged, png, *raw_staged, text):
        with ThreadPoolExecutor(1) as pool:  # both encoders release the GIL: 0.05 s together, not 0.09 at 512 px
            preview = pool.submit(write_png_planar, png, display_rgb(job.image, plan.colour))
            try:
                _, lossy = write_image(staged, image, channels, plan.image_file)
                if raw_staged:  # every channel rendered, the denoiser's AOVs after them, at full precision
                    write_image(raw_staged[0], np.concatenate([raw.image, raw.denoiser]),
                                (*raw.channels, *DENOISER_CHANNELS), ImageFile(component="float32"))
            finally:
                preview.exception()  # waits for the PNG before its file may be removed
            preview.result()  # its failure, if any
        report = _report(plan, job, out, image_path, lossy, channels, started, {**(extra or {}), **denoised})
        write_json_atomic(text, report)
    return report




def _denoised(plan: JobPlan, job: Composed, out: Path) -> tuple[Composed, dict[str, Any]]:
    """The image a job writes (denoised, for a job that asks) and the report's account of the denoising."""
    if not plan.options.denoise:
        return job, {}
    if job.denoiser is None:
        raise RenderError("a denoised job's image came without its AOV pass")
    start = time.perf_counter()
    image = denoise_planar(job.image, job.channels, job.denoiser)
    account = {"raw": str(out.with_suffix(RAW_SUFFIX)), "filter": plan.spec.rfilter, "aovs": list(DENOISER_CHANNELS),
               "aov_spp": AOV_SPP, "quality": QUALITY, "seconds": time.perf_counter() - start}
    return Composed(image, job.channels, job.compose, job.units), {"denoise": account}


def _report(plan: JobPlan, job: Composed, out: Path, written: Path, lossy: Any, channels: tuple[str, ...],
            started: float, extra: dict[str, Any] | None) -> dict[str, Any]:
    """The job's report (OUT.json) as `write_outputs` writes it."""
    units = job.units
    report = {
        "scene": plan.spec.to_dict(), "options": plan.options.to_dict(),
        "image": {"width": plan.width, "height": plan.height, "file": str(written),
                  **plan.image_file.to_dict(), "png": str(out.with_suffix(".png")), "channels": list(channels),
                  "sensor": plan.options.sensor, **({"lossy": lossy} if lossy else {})},
        "effects": plan.effects.to_dict(), "user": {"spp": plan.spp, "depth": plan.depth},
        "prepass": plan.prepass_info, "units": units, "compose": job.compose,
        **({"adaptive": dict(plan.shares)} if plan.first_spp is not None else {}),
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
    return report


def write_json_atomic(path: Path, data: dict[str, Any]) -> None:
    """Write JSON through a .part file: a full disk leaves neither a torn file nor the .part."""
    written_atomically(path, lambda tmp: tmp.write_text(json.dumps(data, indent=2)), "JSON")


@dataclass(frozen=True)
class Progress:
    """How far a job in one process is: units rendered, and samples (spp x pixels) rendered of all (None:
    not known yet, a noise goal's); `pixels` the image's, so that samples / pixels is the mean spp rendered
    so far."""

    units_done: int
    units_total: int
    samples_done: int
    samples_total: int | None
    pixels: int
    seconds_left: float | None = None  # a time goal's, as it is told: the ETA that rates cannot give yet


def render_job(spec: SceneSpec, options: RenderOptions, out: Path, job_id: str | None = None,
               progress: Callable[[Progress], None] | None = None) -> dict:
    """Render the scene as units in one process (each in two passes with `options.adaptive`); write
    OUT.exr/.png/.json and return the report. `progress` hears after the plan and after every unit, or
    every batch of units rendered together (core.render.batch)."""
    start = time.perf_counter()
    worker = RenderProcess()
    worker.launch()  # the child imports Mitsuba while this process hashes the scene
    try:
        seed = plan_seed(scene_digest(spec.path), spec.defines, options.to_dict())
        # Planned in the render process: Mitsuba is imported, the variant selected and the scene loaded
        # once, and this process, which composes and writes, never pays for Mitsuba's import or shutdown.
        plan = worker.call(plan_for_units_here, spec, options, seed, doing="planning", timeout=UNIT_TIMEOUT_S)
        return render_plan(plan, out, worker, start, job_id, progress)
    except KeyboardInterrupt:
        worker.kill()  # a render in flight would not read the request to exit that `stop` sends first
        raise
    finally:
        worker.stop()


def plan_for_units_here(spec: SceneSpec, options: RenderOptions, seed: int) -> JobPlan:
    """`plan_job` in the process that renders the units next (the render process): its units render the
    scene the analysis loaded, not a second load of it."""
    plan, loaded = plan_job_loaded(spec, options, seed)
    adopt_scene(plan.spec, plan.effects.variant, loaded)
    return plan


def scene_digest(path: Path) -> str:
    """The scene file's sha256, or a SceneError naming the file when it cannot be read."""
    try:
        return sha256_file(path)
    except FileNotFoundError as exc:
        raise SceneError(f"{path}: scene file not found") from exc
    except OSError as exc:  # a folder, no permission, an I/O error
        raise SceneError(f"{path}: cannot read the scene file ({exc.strerror or exc})") from exc


def render_plan(plan: JobPlan, out: Path, worker: RenderProcess, started: float, job_id: str | None = None,
                progress: Callable[[Progress], None] | None = None) -> dict:
    """The rest of `render_job` for a plan already made: the rules' (or the shares') parameters, every
    unit rendered by `worker`, composed and written. `started`: the job's start (time.perf_counter)."""
    job_id = job_id or uuid.uuid4().hex[:12]
    planner = Planner(plan.options.rules, plan.options.defuzzifier)
    chosen = plan_params(plan, planner)
    kind = ProgressiveRun if plan.options.in_passes else UnitRun
    run = kind(plan, chosen, job_id, plan.options.threads, worker, planner.rules_path.name, progress)
    job = run.render()
    if plan.options.denoise:
        start = time.perf_counter()
        job.denoiser = render_aov_pass(worker, plan, job_id)
        run.calls["aov_pass_seconds"] = time.perf_counter() - start
    worker.release()  # the render process ends (at once, without its teardown) while this one writes
    return write_outputs(plan, job, out, started, {"job_id": job_id, "render_calls": run.calls})


@dataclass
class UnitRun:
    """The units of one planned job rendered in order by one render process, with progress."""

    plan: JobPlan
    chosen: list[RenderParams]
    job_id: str
    threads: int | None
    worker: RenderProcess
    rules: str
    progress: Callable[[Progress], None] | None = None
    samples_done: int = 0
    # How the units rendered: {"calls": render calls, "together": bool, "why_not": reason or None}.
    calls: dict[str, Any] = field(default_factory=dict)

    def render(self) -> Composed:
        """Every unit at the spp its plan or the rules chose for it: at a rule level in batches of one
        render call each where the scene allows (core.render.batch), else unit by unit."""
        jobs = [unit_job(self.plan, u, p, self.job_id, self.threads) for u, p in zip(self.plan.units, self.chosen,
                                                                                     strict=True)]
        total = sum(j.spp * j.unit.area for j in jobs)
        self._tell(0, total)
        tiles, params = [], {}
        together = self._together(jobs)
        groups = batches(jobs) if together else [[j] for j in jobs]
        self.calls["calls"] = len(groups)
        for batch in groups:
            for tile in self._render(batch, together):
                tiles.append(tile)
                index = int(tile.meta["unit_index"])
                # The spp Mitsuba rendered: a stratified sampler rounds the rules' count (worker.rendered_spp).
                params[index] = {**self.chosen[index].to_dict(), "spp": int(tile.meta["spp"]), "rules": self.rules}
                self.samples_done += jobs[index].spp * jobs[index].unit.area
            self._tell(len(tiles), total)
        return composed(self.plan, self.plan.units, tiles, params)

    def _together(self, jobs: list[RenderRequest]) -> bool:
        """Whether the units render in batches: not at level off, whose units are plain Mitsuba's render
        call, nor in a two-pass (adaptive) job or a scene render_counts cannot render as Mitsuba does
        (the reason goes in the report)."""
        if self.plan.options.level == OFF and not self.plan.options.in_passes:
            problem = "level off renders each unit with Mitsuba's own render call"
        elif self.plan.first_spp is not None:
            problem = "an adaptive job's units each place their own samples in two passes"
        elif len(jobs) < 2:
            problem = "one unit"
        else:
            problem = self.worker.call(together_problem_here, jobs[0], doing="checking the scene",
                                       timeout=UNIT_TIMEOUT_S)
        if problem:
            log.info("units render one by one: %s", problem)
        self.calls.update(together=not problem, why_not=problem)
        return not problem

    def _render(self, batch: list[RenderRequest], together: bool, abort: threading.Event | None = None
                ) -> list[Tile]:
        """A batch's tiles; a batch of one unit is Mitsuba's render call. What a batch's render raises
        beyond the project's own errors (a Dr.Jit failure) is a RenderError naming its units, as a unit's
        is. `abort` set (and the worker interrupted) ends it in a RenderError."""
        if not together or len(batch) == 1:
            return [self.worker.render(batch[0], timeout=UNIT_TIMEOUT_S, abort=abort)]
        try:
            return render_batch(self.worker, batch, UNIT_TIMEOUT_S, abort)
        except QuekaroError:
            raise
        except Exception as exc:
            raise RenderError(f"{batch_name(batch)}: {type(exc).__name__}: {exc}") from exc

    def _tell(self, done: int, samples_total: int | None, seconds_left: float | None = None) -> None:
        if self.progress is not None:
            self.progress(Progress(done, len(self.plan.units), self.samples_done, samples_total,
                                   self.plan.width * self.plan.height, seconds_left))


@dataclass
class ProgressiveRun(UnitRun):
    """The units rendered in passes to the job's noise, time or budget goal (planning.progressive decides, this
    renders): each round's passes batched where the scene allows, merged per unit (core.image.passes).
    The rules (at a rule level) set each unit's depth and band; the samples go where the noise is."""

    def render(self) -> Composed:
        goal = Goal.of(self.plan.options, self.plan.spp)
        budgets = [p.spp for p in self.chosen] if goal.kind == BUDGET else None  # the rules' (or the user's) spp
        machine = Progressive(goal, [u.rect.area for u in self.plan.units], budgets, ONE_PROCESS_PASSES)
        merged: dict[int, UnitPasses] = {}
        start, rounds, passes = time.perf_counter(), 0, 0
        instructions = machine.start()
        together = self._together([self._pass_job(PassOrder(u.index, 0, 1)) for u in self.plan.units])
        self.calls["calls"] = 0
        self._bar(goal, budgets, 0.0, instructions[-1])  # rendering, no longer planning
        with first_ctrl_c_stops(self.worker.interrupt, STOPPING) as stop:
            while isinstance(instructions[-1], RenderRound):
                orders = instructions[-1].orders
                log.info("round %d: %d passes (%d spp) ordered", rounds + 1, len(orders), sum(o.spp for o in orders))
                instructions = []
                try:
                    for tile in self._render_round(orders, together, stop):
                        instructions += machine.handle(self._merge(merged, tile, time.perf_counter() - start))
                        passes += 1
                except RenderError:
                    if not stop.is_set():
                        raise
                    instructions = self._stopped(machine, time.perf_counter() - start)
                rounds += 1
                self.samples_done = sum(m.spp * self.plan.units[u].rect.area for u, m in merged.items())
                self._bar(goal, budgets, time.perf_counter() - start, instructions[-1])
        finish = instructions[-1]
        self.calls["progressive"] = {**goal.to_dict(), "reason": finish.reason, "rounds": rounds, "passes": passes,
                                     "seconds": time.perf_counter() - start, "interrupted": stop.is_set()}
        tiles = [merged[u.index].tile({"unit_index": u.index, "seconds": merged[u.index].seconds,
                                       "window_method": "passes"}) for u in self.plan.units]
        params = {u: self._record(u, merged[u], finish.units[u]) for u in merged}
        return composed(self.plan, self.plan.units, tiles, params)

    def _bar(self, goal: Goal, budgets: list[int] | None, elapsed: float, decided: RenderRound | Finish) -> None:
        """The bar after a round (`decided`: what comes next): the units no longer rendering, and the samples
        the goal comes to: a budget job's, a time job's at this rate for its seconds, a noise job's unknown
        (None) until it ends."""
        units = self.plan.units
        settled = len(units) - len({o.unit for o in decided.orders}) if isinstance(decided, RenderRound) else len(units)
        total: int | None = None
        if settled == len(units):
            total = self.samples_done
        elif goal.kind == BUDGET and budgets is not None:
            total = sum(b * u.rect.area for b, u in zip(budgets, units, strict=True))
        elif goal.kind == TIME and elapsed > 0 and self.samples_done:
            total = max(self.samples_done, round(self.samples_done * goal.seconds / elapsed))
        left = max(0.0, goal.seconds - elapsed) if goal.kind == TIME and settled < len(units) else None
        self._tell(settled, total, left)

    @staticmethod
    def _stopped(machine: Progressive, elapsed: float) -> list[Finish]:
        """Ctrl-C ended the round: the job ends on its passes so far, or, a unit without one, nothing is kept."""
        finish = machine.handle(Stop(elapsed))
        if not finish:
            log.warning("stopped before every unit had a pass: no image written")
            raise KeyboardInterrupt
        return finish

    @staticmethod
    def _merge(merged: dict[int, UnitPasses], tile: Tile, elapsed: float) -> PassDone:
        """Merge a pass's tile into its unit's passes; what the machine hears of it."""
        unit = int(tile.meta["unit_index"])
        done = merge_pass(merged, unit, tile)
        return PassDone(unit, int(tile.meta["pass"]), done.spp, done.seconds, done.relmse(), elapsed)

    def _pass_job(self, order: PassOrder) -> RenderRequest:
        unit = self.plan.units[order.unit]
        base = unit_job(self.plan, unit, self.chosen[order.unit], self.job_id, self.threads)
        # The least band, as a farm's agents render a pass (core.rules.unit_params.adaptive_params).
        return dataclasses.replace(base, spp=order.spp, seed=unit_seed(self.job_id, unit.index, order.pass_index),
                                   band=self.plan.reach, first=None, pass_index=order.pass_index)

    def _render_round(self, orders: Sequence[PassOrder], together: bool, stop: threading.Event) -> Iterator[Tile]:
        """The round's passes, batch by batch, in batches where the scene allows (a batch holds one pass of a
        unit); `stop` set ends the batch in flight (a RenderError)."""
        jobs = [self._pass_job(order) for order in orders]
        groups = batches(jobs) if together else [[j] for j in jobs]
        for batch in groups:
            self.calls["calls"] += 1
            yield from self._render(batch, together, stop)

    def _record(self, unit: int, passes: UnitPasses, verdict: str) -> dict[str, Any]:
        return {**self.chosen[unit].to_dict(), "band": self.plan.reach, "rules": self.rules, **passes.account(),
                "verdict": verdict}
