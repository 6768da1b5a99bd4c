"""An agent's speed: a tiny reference render timed in its own render process (`measure_speed`), and the
estimates it implies (`estimate_seconds`). Speed is in mega-rays per second, the same rays as the master's
unit cost (`WorkUnit.cost`: rays at 1 spp), so a unit's estimate is cost x spp / (speed x 1e6) seconds.
"""

from __future__ import annotations

from dataclasses import dataclass

from core.data import DEMO_SCENE
from core.errors import QuekaroError
from core.mitsuba_env import DEFAULT_VARIANT
from core.model.geometry import Rect
from core.model.job import SceneSpec
from core.render.process import RenderProcess, RenderRequest

REFERENCE_SCENE = DEMO_SCENE
REF_RES = 32
REF_SPP = 128
REF_DEPTH = 6
# Mean rays per sample of the reference render, counted by planning.complexity.prepass (path, depth 6,
# 32x32): 6.67. Measured, not derived: it changes only if scenes/cbox.xml or the tracer changes.
REF_RAYS_PER_SAMPLE = 6.67
RAYS_PER_SPEED_UNIT = 1e6
MIN_SPEED = 1e-6  # core.model.messages.Register's lower bound


@dataclass(frozen=True)
class SpeedSample:
    """The measured speed (mega-rays/s), the best timed render's seconds, the pixel samples per second, and
    `compile_s`: what the first render of a new kernel (window size, depth) cost on top (the warm-up's extra)."""

    speed: float
    seconds: float
    samples_per_s: float
    variant: str
    compile_s: float = 0.0


def reference_job(threads: int | None, spp: int = REF_SPP) -> RenderRequest:
    """The reference render as a unit job: the whole 32x32 image of the repository's Cornell box
    (scenes/cbox.xml, only built-in shapes), path tracer at depth REF_DEPTH, `spp` samples."""
    if not REFERENCE_SCENE.is_file():
        raise QuekaroError(f"reference scene for the speed benchmark not found: {REFERENCE_SCENE}")
    spec = SceneSpec(REFERENCE_SCENE, {"res": str(REF_RES), "spp": str(spp), "max_depth": str(REF_DEPTH)})
    return RenderRequest(spec, DEFAULT_VARIANT, "path", REF_DEPTH, spp, 7, REF_RES, REF_RES,
                   Rect(0, 0, REF_RES, REF_RES), threads=threads, job_id="speed-benchmark")


def measure_speed(worker: RenderProcess, threads: int | None, repeats: int = 2,
                  timeout: float = 120.0) -> SpeedSample:
    """Time the reference render in `worker` (blocking), with the agent's thread count: one untimed warm-up
    that compiles the kernel (~0.6 s), then the best of `repeats` (~1.5 s in all)."""
    job = reference_job(threads)
    cold = worker.render(job, timeout)  # compiles the kernel; its time is not the agent's speed
    tiles = [worker.render(job, timeout) for _ in range(max(1, repeats))]
    seconds = max(min(float(t.meta["seconds"]) for t in tiles), 1e-6)
    samples = REF_RES * REF_RES * REF_SPP
    speed = samples * REF_RAYS_PER_SAMPLE / seconds / RAYS_PER_SPEED_UNIT
    compile_s = max(float(cold.meta["seconds"]) - seconds, 0.0)
    return SpeedSample(max(speed, MIN_SPEED), seconds, samples / seconds, str(tiles[0].meta.get("variant")),
                       compile_s)


def estimate_seconds(cost: float, spp: int, speed: float) -> float:
    """Seconds to render a unit of master cost `cost` at `spp` on an agent of `speed`; `spp` is what the
    agent's own rules chose. The cost is the rays one sample of each pixel traces (camera ray, bounces,
    shadow rays). At level off the master sets it to the pixel count, one "ray" a sample: those estimates
    come out short by the scene's rays per sample, which the agent's per-job correction
    (agents.state.Calibration) absorbs after one unit."""
    return float(cost) * max(int(spp), 1) / (max(speed, MIN_SPEED) * RAYS_PER_SPEED_UNIT)
