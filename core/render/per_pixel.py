"""The film's window rendered with its own sample count per pixel, as Mitsuba's own render loop would
(`render_counts`): the primitive of adaptive sampling (core.render.adaptive).

Mitsuba's `render` gives every pixel the same spp; `render_counts` draws `counts[p]` samples in pixel p
and returns the image, statistically Mitsuba's, with each pixel's sample moments (a `WindowRender`).
`render_core` draws a fixed spp in a unit of the window and none around it, for windows that overlap to
add up (a progressive job's passes at level off).
`check_renderable` refuses, with the reason, the scenes it cannot render as Mitsuba does.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from core import mitsuba_env
from core.errors import RenderError
from core.image.film import film_channels, film_weight
from core.image.metrics import RELMSE_EPSILON

# Mitsuba and Dr.Jit are imported where used (core.render.process explains why).

# Filters that never weigh a sample below zero: a spilling window's band (render_core) then holds its
# samples' sums exactly. With negative lobes (Lanczos, Mitchell, Catmull-Rom) a band pixel can weigh less
# than zero, where Mitsuba's film develops it to 0 and the sums it held are lost.
SPILL_FILTERS = ("GaussianFilter", "BoxFilter", "TentFilter")
SAMPLERS = ("IndependentSampler",)  # samplers whose samples do not depend on a fixed spp per pixel
# The wavefront is padded with masked lanes (no radiance, zero weight, left out of the moments) to a
# multiple of this: with Dr.Jit 1.5's LLVM backend the render kernel faulted (SIGSEGV in a worker thread)
# for some sample totals just below a multiple of 1024 (e.g. 2^19 - 7 on cbox at 128 px), and never with
# padded totals (tests/test_adaptive.py renders one such total in a child process).
LANE_MULTIPLE = 1024


@dataclass
class WindowRender:
    """The film's window after a render: `pixels` (H x W x C, every channel the film writes, `channels`
    its names), and per pixel the number of samples drawn in it, their RGB sum and sum of squares."""

    pixels: np.ndarray
    channels: tuple[str, ...]
    counts: np.ndarray
    sum: np.ndarray
    sum_sq: np.ndarray
    weight: np.ndarray | None = None  # with weights=True: the film's weight sum over each sample's share

    def relative_variance(self, epsilon: float = RELMSE_EPSILON) -> np.ndarray:
        """Per pixel, the per-sample variance (mean over RGB) over (mean^2 + epsilon), the mean also over
        RGB: about the relMSE one sample adds there. core.image.metrics.relmse weighs each channel by
        its own mean; weighted so, a saturated colour's dim channels make the predicted gain of an
        allocation noisier, enough to cross the threshold that decides whether to adapt
        (core.render.adaptive.PAYS_BELOW). Pixels with < 2 samples: 0."""
        n = np.maximum(self.counts, 1)[..., None].astype(np.float64)
        mean = self.sum / n
        var = np.maximum(self.sum_sq / n - mean * mean, 0.0) * n / np.maximum(n - 1, 1)
        rel = var.mean(axis=-1) / (mean.mean(axis=-1) ** 2 + epsilon)
        return np.where(self.counts >= 2, rel, 0.0)


def check_renderable(scene: Any, sensor: int = 0, integrator: Any = None) -> None:
    """Raise RenderError naming what makes per-pixel counts not Mitsuba's render for this scene: samplers
    other than `independent` (the others stratify over a pixel's fixed spp, which varying counts break),
    films that sample their border, and integrators that are not sampling integrators (a particle tracer
    splats anywhere)."""
    import mitsuba as mi

    mitsuba_env.require_vectorised("adaptive sampling (per-pixel sample counts in one wavefront)")
    if mi.is_polarized:  # the stokes integrator's wavefront crashed Dr.Jit's LLVM backend (SIGSEGV)
        raise RenderError(f"variant {mi.variant()}: per-pixel sample counts are not rendered in polarized "
                          "variants (with the stokes integrator their render crashed)")
    cam = scene.sensors()[sensor]
    kind = cam.sampler().class_name()
    if kind not in SAMPLERS:
        raise RenderError(f"sampler {kind}: per-pixel sample counts need the independent sampler (a "
                          "stratified sampler spreads a fixed spp over each pixel)")
    if cam.film().sample_border():
        raise RenderError("film with sample_border=true: per-pixel counts cover the window only")
    integ = integrator if integrator is not None else scene.integrator()
    if not isinstance(integ, mi.SamplingIntegrator):
        raise RenderError(f"integrator {integ.class_name()} is not a sampling integrator "
                          "(it does not draw its samples per pixel)")
    if isinstance(integ, getattr(mi, "CppADIntegrator", ())):  # prb, prbvolpath, direct_projective ...
        raise RenderError(f"integrator {integ.class_name()} is one of Mitsuba's Python differentiable "
                          "integrators, whose sample() takes a differentiation mode and state: per-pixel counts "
                          "drive the sampling integrators written in C++")


def render_counts(scene: Any, counts: np.ndarray, seed: int, sensor: int = 0, integrator: Any = None,
                  moments: bool = True, weights: bool = False) -> WindowRender:
    """Render the sensor's current film window (crop) with `counts[y, x]` samples in its pixel (y, x).

    `counts` has the window's shape (crop height x width); 0 leaves a pixel to its neighbours' filter
    footprints (or empty). `integrator` None is the scene's own; `moments` False skips the per-pixel sums;
    `weights` True reads back each pixel's filter weight sum in units of one sample (the film's weight over
    its pixel's share), which merges this render with others of the window (core.image.passes).

    This is Mitsuba's sampling loop (the steps of `SamplingIntegrator::render_sample`, as Mitsuba's Python
    integrators spell them in `mitsuba.ad.integrators.common`) with one change: each sample is splatted
    with the weight `mean / counts[p]`. The film's value is sum(w_filter s f) / sum(w_filter s), so every
    pixel's expectation is the one Mitsuba's filter gives at uniform density (tests/test_adaptive.py),
    only less noisy where counts are high. The moments (the samples' RGB sums and squares, by the pixel
    drawn in) choose a next pass's counts.
    """
    import drjit as dr
    import mitsuba as mi

    check_renderable(scene, sensor, integrator)
    cam = scene.sensors()[sensor]
    film = cam.film()
    integ = integrator if integrator is not None else scene.integrator()
    width, height = (int(v) for v in film.crop_size())
    counts = _checked_counts(counts, width, height)
    total = int(counts.sum())
    film.prepare(integ.aov_names())
    block = film.create_block()
    if total == 0:
        film.put_block(block)
        return _result(film, counts, weights=weights)
    uniform = int(counts.flat[0]) if (counts == counts.flat[0]).all() else 0
    lanes = padded(total)
    sampler = cam.sampler().clone()
    sampler.set_sample_count(max(1, round(total / counts.size)))
    sampler.set_samples_per_wavefront(1)
    sampler.seed(seed, lanes)
    live = dr.arange(mi.UInt32, lanes) < dr.opaque(mi.UInt32, total)
    if uniform:  # consecutive samples share a pixel: no index array
        pixel = dr.minimum(dr.arange(mi.UInt32, lanes) // dr.opaque(mi.UInt32, uniform),
                           dr.opaque(mi.UInt32, counts.size - 1))
        count_of = dr.opaque(mi.Float, uniform)
    else:
        index = np.repeat(np.arange(width * height, dtype=np.uint32), counts.ravel())
        pixel = mi.UInt32(np.pad(index, (0, lanes - total), mode="edge"))
        count_of = dr.gather(mi.Float, mi.Float(counts.ravel().astype(np.float32)), pixel)
    pos, pos_f, ray, ray_weight = _sample_rays(cam, film, sampler, pixel, width)
    if ray.has_differentials:
        ray.scale_differential(dr.rsqrt(count_of))
    spec, valid, aovs = integ.sample(scene, sampler, ray, cam.get_medium(), live)
    # The splat weight, mean count / this pixel's count; opaque, so that a new mean is not a new kernel.
    share = dr.rcp(count_of) * dr.opaque(mi.Float, total / counts.size)
    splat = mi.Vector2f(pos) if film.rfilter().is_box_filter() else pos_f
    rgb = _put(block, film, splat, ray_weight * spec, ray.wavelengths, share, dr.select(valid, 1.0, 0.0), aovs,
               live)
    sums = _moments(rgb, pixel, width * height, live) if moments else (None, None)
    film.put_block(block)
    return _result(film, counts, *sums, weights=weights)


def render_core(scene: Any, core: tuple[int, int, int, int], spp: int, seed: int, sensor: int = 0,
                integrator: Any = None) -> tuple[np.ndarray, tuple[str, ...]]:
    """Render `spp` samples in each pixel of `core` (x, y, w, h within the film's window) and none around
    it: the window's pixels around the core hold only the spill of the core's samples through the filter.
    Returns the window's developed pixels (H x W x C) and their channel names; the film keeps the raw
    weight sum per pixel (core.image.film.film_weight).

    Every sample is splatted with weight 1, as Mitsuba's render splats it, so the sums of windows that
    overlap (each pixel's value times its weight, added over the windows, over the weights added) are the
    image one render of all their cores gives (core.image.compose: a pixel by a core's border draws on the
    neighbour's samples as in an image rendered whole), with no sample drawn twice."""
    import drjit as dr
    import mitsuba as mi

    problem = spill_problem(scene, sensor, integrator)
    if problem:
        raise RenderError(problem)
    cam = scene.sensors()[sensor]
    film = cam.film()
    integ = integrator if integrator is not None else scene.integrator()
    width, height = (int(v) for v in film.crop_size())
    x, y, w, h = core
    if spp < 1 or w < 1 or h < 1 or x < 0 or y < 0 or x + w > width or y + h > height:
        raise RenderError(f"core {list(core)} at {spp} spp does not fit the film window {width}x{height}")
    total = w * h * spp
    if padded(total) >= 2**32:
        raise RenderError(f"{total} samples in one wavefront (at most 2^32 - {LANE_MULTIPLE}, padded)")
    film.prepare(integ.aov_names())
    block = film.create_block()
    lanes = padded(total)
    sampler = cam.sampler().clone()
    sampler.set_sample_count(spp)
    sampler.set_samples_per_wavefront(1)
    sampler.seed(seed, lanes)
    lane = dr.arange(mi.UInt32, lanes)
    live = lane < dr.opaque(mi.UInt32, total)
    k = dr.minimum(lane // dr.opaque(mi.UInt32, spp), dr.opaque(mi.UInt32, w * h - 1))  # the core's pixel
    row = k // dr.opaque(mi.UInt32, w)
    pixel = (row + dr.opaque(mi.UInt32, y)) * dr.opaque(mi.UInt32, width) + k - row * dr.opaque(mi.UInt32, w) \
        + dr.opaque(mi.UInt32, x)
    pos, pos_f, ray, ray_weight = _sample_rays(cam, film, sampler, pixel, width)
    if ray.has_differentials:
        ray.scale_differential(dr.rsqrt(dr.opaque(mi.Float, spp)))
    spec, valid, aovs = integ.sample(scene, sampler, ray, cam.get_medium(), live)
    splat = mi.Vector2f(pos) if film.rfilter().is_box_filter() else pos_f
    _put(block, film, splat, ray_weight * spec, ray.wavelengths, mi.Float(1.0), dr.select(valid, 1.0, 0.0), aovs,
         live)
    film.put_block(block)
    return film_channels(film)


def spill_problem(scene: Any, sensor: int = 0, integrator: Any = None) -> str | None:
    """Why `render_core` cannot render the scene so that its windows add up, or None: what
    `check_renderable` refuses, or a filter with negative lobes (SPILL_FILTERS)."""
    try:
        check_renderable(scene, sensor, integrator)
    except RenderError as exc:
        return str(exc)
    kind = scene.sensors()[sensor].film().rfilter().class_name()
    if kind not in SPILL_FILTERS:
        return f"filter {kind} weighs some samples below zero: a band pixel's sums would be lost"
    return None


def counts_problem(counts: np.ndarray, width: int, height: int, window: str = "the film window") -> str | None:
    """What makes `counts` unfit for a `window` of width x height, or None: its shape, or values that are
    not non-negative integers, or more samples than one wavefront holds."""
    if counts.shape != (height, width):
        return f"counts {counts.shape} do not match {window} {height}x{width}"
    if not np.issubdtype(counts.dtype, np.integer) or (counts < 0).any():
        return "counts must be non-negative integers"
    if padded(int(counts.sum())) >= 2**32:
        return f"{int(counts.sum())} samples in one wavefront (at most 2^32 - {LANE_MULTIPLE}, padded)"
    return None


def padded(total: int) -> int:
    """The wavefront's lanes for `total` samples: the next multiple of LANE_MULTIPLE."""
    return -(-total // LANE_MULTIPLE) * LANE_MULTIPLE


def _checked_counts(counts: np.ndarray, width: int, height: int) -> np.ndarray:
    counts = np.asarray(counts)
    problem = counts_problem(counts, width, height)
    if problem:
        raise RenderError(problem)
    return counts.astype(np.uint32)


def _sample_rays(cam: Any, film: Any, sampler: Any, pixel: Any, width: int) -> tuple[Any, ...]:
    """Primary rays of the samples (each in its pixel), in Mitsuba's order of sampler draws."""
    import drjit as dr
    import mitsuba as mi

    row = pixel // dr.opaque(mi.UInt32, width)
    pos = mi.Vector2i(mi.Int32(pixel - row * width), mi.Int32(row)) + mi.Vector2i(film.crop_offset())
    pos_f = mi.Vector2f(pos) + sampler.next_2d()
    scale = dr.rcp(mi.ScalarVector2f(film.crop_size()))
    offset = -mi.ScalarVector2f(film.crop_offset()) * scale
    aperture = sampler.next_2d() if cam.needs_aperture_sample() else mi.Point2f(0.5)
    time = mi.Float(cam.shutter_open())
    if cam.shutter_open_time() > 0:
        time += sampler.next_1d() * cam.shutter_open_time()
    wavelength = sampler.next_1d() if mi.is_spectral else mi.Float(0.0)
    ray, weight = cam.sample_ray_differential(time, wavelength, dr.fma(pos_f, scale, offset), aperture)
    return pos, pos_f, ray, weight


def _put(block: Any, film: Any, pos: Any, value: Any, wavelengths: Any, share: Any, alpha: Any,
         aovs: list[Any], live: Any) -> Any:
    """Splat the samples, each weighted by `share`; return their RGB (for the moments)."""
    import drjit as dr
    import mitsuba as mi

    if mi.is_polarized:
        value = mi.unpolarized_spectrum(value)
    if mi.is_spectral:
        rgb = mi.spectrum_to_srgb(value, wavelengths)
    elif mi.is_monochromatic:
        rgb = mi.Color3f(value.x)
    else:
        rgb = mi.Color3f(value)
    if dr.all(mi.has_flag(film.flags(), mi.FilmFlags.Special)):
        channels = film.prepare_sample(value * share, wavelengths, block.channel_count(), weight=share,
                                       alpha=alpha * share)
        base = block.channel_count() - len(aovs)
        channels = list(channels)[:base] + [a * share for a in aovs]
    else:
        head = [rgb.x * share, rgb.y * share, rgb.z * share]
        if mi.has_flag(film.flags(), mi.FilmFlags.Alpha):
            head.append(alpha * share)
        channels = head + [share] + [a * share for a in aovs]
    block.put(pos, channels, live)
    return rgb


def _moments(rgb: Any, pixel: Any, size: int, live: Any) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel, the sum and the sum of squares of its samples' RGB: (size x 3) each. (Atomic scatters
    in the render's own kernel: dr.block_sum over uniform counts measured ~2.5x slower here.)"""
    import drjit as dr
    import mitsuba as mi

    sums, squares = [], []
    for c in (rgb.x, rgb.y, rgb.z):
        acc, acc2 = dr.zeros(mi.Float, size), dr.zeros(mi.Float, size)
        dr.scatter_reduce(dr.ReduceOp.Add, acc, c, pixel, live)
        dr.scatter_reduce(dr.ReduceOp.Add, acc2, c * c, pixel, live)
        sums.append(acc)
        squares.append(acc2)
    dr.eval(*sums, *squares)
    return (np.stack([np.array(a, dtype=np.float64) for a in sums], axis=-1),
            np.stack([np.array(a, dtype=np.float64) for a in squares], axis=-1))


def _result(film: Any, counts: np.ndarray, sums: np.ndarray | None = None,
            squares: np.ndarray | None = None, weights: bool = False) -> WindowRender:
    pixels, names = film_channels(film)
    h, w = counts.shape
    zero = np.zeros((h * w, 3))
    sums = zero if sums is None else sums
    squares = zero if squares is None else squares
    weight = None
    if weights:  # a sample drawn in pixel p was splatted with weight mean / counts[p] (render_counts)
        share = np.where(counts > 0, counts.sum() / counts.size / np.maximum(counts, 1), 1.0)
        weight = film_weight(film, share)
    return WindowRender(pixels, names, counts, sums.reshape(h, w, 3), squares.reshape(h, w, 3), weight)
