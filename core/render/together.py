"""Several units of one job rendered in one wavefront (`render_batch_here`): every pixel at its unit's spp
through core.render.counts.render_counts over the whole image, and each unit's tile cut from that image.

Why: besides its samples, a Mitsuba render call costs milliseconds (tracing the kernel, seeding the
sampler, preparing and developing the film), and a unit's window renders its band's pixels again; a
rule-planned job of 85 units paid that 85 times. One call per batch pays it once, and a pixel near a
unit's border draws on its neighbours' samples as in an image rendered whole.

The tiles are statistically the per-unit ones: each pixel's expectation is Mitsuba's at its unit's depth
(render_counts weights each sample by one over its pixel's count, tests/test_adaptive.py), so the units'
bands blend as before. A batch holds units of one depth (the depth is part of the integrator, one per
call), up to BATCH_SAMPLES samples (the wavefront a level-off unit holds, planning.jobplan), and band
pixels that belong to a unit of another batch render at the spp of the unit whose window holds them.
Where render_counts cannot render the scene as Mitsuba does (a stratified sampler, a film that samples
its border, a particle tracer, a scalar variant), `together_problem_here` says why and the units render
one by one.
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np

from core.errors import RenderError
from core.model.geometry import Rect
from core.render.counts import check_renderable, render_counts
from core.render.film import sanitize
from core.render.scene import sensor_of
from core.render.tiles import Tile
from core.render.worker import RenderRequest, _local_cache, aim, unit_meta

BATCH_SAMPLES = 1 << 24
METHOD = "together"  # the tiles' window_method


def batches(jobs: Sequence[RenderRequest], cap: int = BATCH_SAMPLES) -> list[list[RenderRequest]]:
    """The units grouped into batches that each render in one call: one depth per batch, in the order
    given, each batch's windows at their spp (`cost`) adding up to at most `cap` samples; a unit whose
    window alone holds more is a batch of its own."""
    open_batches: dict[int | None, list[RenderRequest]] = {}
    held: dict[int | None, int] = {}
    done: list[list[RenderRequest]] = []
    for job in jobs:
        key = job.max_depth
        if key in open_batches and held[key] + cost(job) > cap:
            done.append(open_batches.pop(key))
        batch = open_batches.setdefault(key, [])
        held[key] = (held.get(key, 0) if batch else 0) + cost(job)
        batch.append(job)
    return done + list(open_batches.values())


def cost(job: RenderRequest) -> int:
    """The samples a unit's window takes at its spp: an upper bound of what it adds to a batch."""
    return job.window.area * job.spp


def batch_counts(batch: Sequence[RenderRequest]) -> np.ndarray:
    """Per pixel of the image (H x W), the samples the batch draws there: each unit's spp on its
    rectangle, then on the band pixels left at zero the spp of the (first) unit whose window holds them."""
    first = batch[0]
    counts = np.zeros((first.height, first.width), dtype=np.int64)
    for job in batch:
        counts[_slices(job.unit)] = job.spp
    for job in batch:
        window = counts[_slices(job.window)]
        window[window == 0] = job.spp
    return counts


def together_problem_here(job: RenderRequest) -> str | None:
    """Why the job's units cannot render together in this process (loading its scene if needed), or None."""
    if job.first is not None:
        return "a two-pass (adaptive) unit places its own samples"
    scene, _, _ = aim(job, job.window, _local_cache)
    try:
        check_renderable(scene, job.sensor, _local_cache.integrator(job.integrator, job.max_depth))
    except RenderError as exc:
        return str(exc)
    return None


def render_batch_here(batch: Sequence[RenderRequest]) -> list[Tile]:
    """The batch's tiles (one per unit, its window cut from one render of the image), in this process.
    Each tile's seconds are the call's, shared by the samples drawn on the units' rectangles."""
    first = batch[0]
    mixed = {(j.scene.key(), j.variant, j.integrator, j.max_depth, j.sensor, j.width, j.height) for j in batch}
    if len(mixed) > 1 or any(j.first is not None for j in batch):
        raise RenderError("a batch holds units of one job, depth and sensor, none of them two-pass")
    image = Rect(0, 0, first.width, first.height)
    scene, load_s, method = aim(first, image, _local_cache)
    sensor = sensor_of(scene, first.sensor, str(first.scene.path))
    integrator = _local_cache.integrator(first.integrator, first.max_depth)
    counts = batch_counts(batch)
    start = time.perf_counter()
    made = render_counts(scene, counts, first.seed, first.sensor, integrator, moments=False)
    seconds = time.perf_counter() - start
    bad = ~np.isfinite(made.pixels).all(axis=-1)
    pixels, _ = sanitize(made.pixels)
    own = [int(counts[_slices(j.unit)].sum()) for j in batch]
    tiles = []
    for job, samples in zip(batch, own, strict=True):
        window = _slices(job.window)
        meta = unit_meta(job, sensor, seconds * samples / max(sum(own), 1), load_s if job is first else 0.0,
                         int(bad[window].sum()), job.spp, f"{METHOD} ({method})")
        tiles.append(Tile(pixels[window], job.window, job.unit, meta, made.channels))
    return tiles


def _slices(rect: Rect) -> tuple[slice, slice]:
    return slice(rect.y, rect.y + rect.h), slice(rect.x, rect.x + rect.w)
