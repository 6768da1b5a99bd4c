"""Several units of one job rendered in one call (`render_batch_here`): every pixel at its unit's spp
through core.render.per_pixel.render_counts over the units' windows at once, each unit's tile cut from it.

A render call costs milliseconds besides its samples, and a unit's window renders its band again; one call
per batch pays that once. `batches` groups the units, `together_problem_here` says why a job's units must
render one by one instead, and `render_batch` runs a batch in a render process.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence

import numpy as np

from core.errors import RenderError
from core.image.film import sanitize
from core.image.passes import WEIGHT
from core.image.tiles import Tile
from core.model.geometry import Rect
from core.render.per_pixel import check_renderable, render_counts
from core.render.process import RenderProcess, RenderRequest, aim, local_cache, unit_meta
from core.scene.scene import sensor_of

BATCH_SAMPLES = 1 << 24  # the most a batch's render call holds (a few seconds of a simple scene here)
# A batch renders the whole image's film where the image has at most this many pixels, else the least
# rectangle holding its units' windows, itself at most this many: the film's memory and its development
# stay bounded whatever the image's size (a 2048 x 2048 film).
BATCH_PIXELS = 1 << 22
METHOD = "together"  # the tiles' window_method


def batches(jobs: Sequence[RenderRequest], cap: int = BATCH_SAMPLES,
            pixels: int = BATCH_PIXELS) -> list[list[RenderRequest]]:
    """The units grouped into batches that each render in one call: one depth per batch, in the order
    given, each batch's windows at their spp (`cost`) adding up to at most `cap` samples and their bounding
    rectangle at most `pixels`; a unit beyond either alone is a batch of its own. One depth, since the
    depth is part of the integrator, and a call has one; one pass of a unit (a call draws each pixel once:
    two passes of one unit in it would be one set of samples twice)."""
    open_batches: dict[int | None, list[RenderRequest]] = {}
    held: dict[int | None, tuple[int, Rect]] = {}  # per open batch: its samples and bounding rectangle
    done: list[list[RenderRequest]] = []
    for job in jobs:
        key = job.max_depth
        if key in open_batches:
            samples, box = held[key]
            grown = box.bounding(job.window)
            again = any(other.unit == job.unit for other in open_batches[key])
            if samples + cost(job) <= cap and grown.area <= pixels and not again:
                open_batches[key].append(job)
                held[key] = (samples + cost(job), grown)
                continue
            done.append(open_batches.pop(key))
        open_batches[key] = [job]
        held[key] = (cost(job), job.window)
    return done + list(open_batches.values())


def cost(job: RenderRequest) -> int:
    """The samples a unit's window takes at its spp: an upper bound of what it adds to a batch."""
    return job.window.area * job.spp


def bounds(batch: Sequence[RenderRequest], pixels: int = BATCH_PIXELS) -> Rect:
    """What the batch's call renders: the whole image where it has at most `pixels` pixels, else the least
    rectangle holding the batch's windows. Dr.Jit bakes the film's size into the kernel: batches of one
    depth on one film size share it, where each bounding rectangle compiled its own (scattered units on an
    agent: 0.37 s a batch of four against 0.21 s, cbox 512 px at 1 thread)."""
    first = batch[0]
    if first.width * first.height <= pixels:
        return Rect(0, 0, first.width, first.height)
    out = first.window
    for job in batch[1:]:
        out = out.bounding(job.window)
    return out


def batch_counts(batch: Sequence[RenderRequest]) -> np.ndarray:
    """Per pixel of the batch's `bounds`, the samples the batch draws there: each unit's spp on its
    rectangle, then on the band pixels left at zero the spp of the (first) unit whose window holds them."""
    area = bounds(batch)
    counts = np.zeros((area.h, area.w), dtype=np.int64)
    for job in batch:
        counts[_within(job.unit, area)] = job.spp
    for job in batch:
        window = counts[_within(job.window, area)]
        window[window == 0] = job.spp
    return counts


def together_problem_here(job: RenderRequest) -> str | None:
    """Why the job's units cannot render together in this process (loading its scene if needed), or None:
    where render_counts cannot render the scene as Mitsuba does (a stratified sampler, a film that samples
    its border, a particle tracer, a scalar variant) or the unit is two-pass."""
    if job.first is not None:
        return "a two-pass (adaptive) unit places its own samples"
    cache = local_cache()
    scene, _ = cache.scene_for(job.scene, job.variant, job.threads)
    try:
        check_renderable(scene, job.sensor, cache.integrator(job.integrator, job.max_depth))
    except RenderError as exc:
        return str(exc)
    return None


def render_batch_here(batch: Sequence[RenderRequest]) -> list[Tile]:
    """The batch's tiles (one per unit, its window cut from one render of the batch's `bounds`), in this
    process. The call's seconds are shared among the tiles by the samples drawn on their units' rectangles;
    every tile's header gives the batch's seed, the first unit's.

    The tiles are statistically the per-unit ones: each pixel's expectation is Mitsuba's at its unit's
    depth (render_counts weights each sample by one over its pixel's count: tests/test_adaptive.py), so
    the bands blend as before, and a pixel near a border draws on its neighbours' samples as in an image
    rendered whole. The call's fixed cost (tracing the kernel, seeding the sampler, preparing and
    developing the film) is paid once: a rule-planned job of 85 units paid it 85 times. Windows share
    their common pixels: one that comes out non-finite is zeroed, and counted, in every tile holding it."""
    first = batch[0]
    mixed = {(j.scene.key(), j.variant, j.integrator, j.max_depth, j.sensor, j.width, j.height) for j in batch}
    if len(mixed) > 1 or any(j.first is not None for j in batch) or len({j.pass_index is None for j in batch}) > 1:
        raise RenderError("a batch holds units of one job, depth and sensor, none of them two-pass, all "
                          "passes or none")
    cache, area = local_cache(), bounds(batch)
    scene, load_s, method = aim(first, area, cache)
    sensor = sensor_of(scene, first.sensor, str(first.scene.path))
    integrator = cache.integrator(first.integrator, first.max_depth)
    counts = batch_counts(batch)
    start = time.perf_counter()
    in_passes = first.pass_index is not None
    made = render_counts(scene, counts, first.seed, first.sensor, integrator, moments=False, weights=in_passes)
    seconds = time.perf_counter() - start
    own = [int(counts[_within(j.unit, area)].sum()) for j in batch]
    tiles = []
    channels = (*made.channels, WEIGHT) if in_passes else made.channels
    for job, samples in zip(batch, own, strict=True):
        pixels, nonfinite = sanitize(made.pixels[_within(job.window, area)])
        if in_passes:
            pixels = np.concatenate([pixels, made.weight[_within(job.window, area)][..., None]], axis=-1)
        meta = unit_meta(job, sensor, seconds * samples / max(sum(own), 1), load_s if job is first else 0.0,
                         nonfinite, job.spp, f"{METHOD} ({method})") | {"seed": first.seed}
        tiles.append(Tile(pixels, job.window, job.unit, meta, channels))
    return tiles


def render_batch(worker: RenderProcess, batch: Sequence[RenderRequest], timeout: float | None,
                 abort: threading.Event | None = None) -> list[Tile]:
    """The batch's tiles, rendered by `render_batch_here` in `worker`'s render process."""
    return worker.call(render_batch_here, batch, doing=batch_name(batch), timeout=timeout, abort=abort)


def batch_name(batch: Sequence[RenderRequest]) -> str:
    return f"units {[j.unit_index for j in batch]}"


def _within(rect: Rect, area: Rect) -> tuple[slice, slice]:
    """Numpy index of `rect` in an array of `area`'s pixels."""
    return Rect(rect.x - area.x, rect.y - area.y, rect.w, rect.h).slices()
