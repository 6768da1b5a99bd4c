"""Adaptive sampling at pixel scale: the film's window rendered with its own sample count per pixel, as
Mitsuba's own render loop would (`render_counts`), and the two-pass render built on it (`render_adaptive`).

Mitsuba's `render` gives every pixel the same spp. Adaptive sampling needs more samples where the noise
is, so this is Mitsuba's sampling loop (the steps of `SamplingIntegrator::render_sample`, as Mitsuba's own
Python integrators spell them in `mitsuba.ad.integrators.common`) with one change: pixel p draws
`counts[p]` samples, and each sample is splatted with the weight `mean / counts[p]`. A pixel's value is
the film's ratio sum(w_filter s f) / sum(w_filter s) over the samples near it; with s proportional to one
over its pixel's count, every pixel's expectation is the one Mitsuba's filter gives at uniform density,
so the image is statistically Mitsuba's (tests/test_adaptive.py), only less noisy where counts are high.

Beside the image it returns each pixel's sample moments (sums of the samples' RGB and squares, by the
pixel the sample was drawn in), from which the two-pass render estimates where the next pass's go.

Refused, with the reason: samplers other than `independent` (stratified, multijitter, low-discrepancy
samplers stratify over a pixel's fixed spp, which varying counts break), films that sample their border,
and integrators that are not sampling integrators (a particle tracer splats anywhere).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.ndimage import gaussian_filter

from core.errors import RenderError
from core.render.metrics import RELMSE_EPSILON
from core.render.worker import film_channels, sanitize

# Mitsuba and Dr.Jit are imported where used (core.render.worker explains why).

SAMPLERS = ("IndependentSampler",)  # samplers whose samples do not depend on a fixed spp per pixel


@dataclass
class WindowRender:
    """The film's window after a render: `pixels` (H x W x C, every channel the film writes, `channels`
    its names), and per pixel the number of samples drawn in it, their RGB sum and sum of squares."""

    pixels: np.ndarray
    channels: tuple[str, ...]
    counts: np.ndarray
    sum: np.ndarray
    sum_sq: np.ndarray

    def relative_variance(self, epsilon: float = RELMSE_EPSILON) -> np.ndarray:
        """Per pixel, the per-sample variance (mean over RGB) over (mean^2 + epsilon): the relMSE one
        sample adds there (core.render.metrics.relmse's weighting). Pixels with < 2 samples: 0."""
        n = np.maximum(self.counts, 1)[..., None].astype(np.float64)
        mean = self.sum / n
        var = np.maximum(self.sum_sq / n - mean * mean, 0.0) * n / np.maximum(n - 1, 1)
        rel = var.mean(axis=-1) / (mean.mean(axis=-1) ** 2 + epsilon)
        return np.where(self.counts >= 2, rel, 0.0)


def check_renderable(scene: Any, sensor: int = 0, integrator: Any = None) -> None:
    """Raise RenderError naming what makes per-pixel counts not Mitsuba's render for this scene."""
    import mitsuba as mi

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


def render_counts(scene: Any, counts: np.ndarray, seed: int, sensor: int = 0, integrator: Any = None,
                  moments: bool = True) -> WindowRender:
    """Render the sensor's current film window (crop) with `counts[y, x]` samples in its pixel (y, x).

    `counts` has the window's shape (crop height x width); 0 leaves a pixel to its neighbours' filter
    footprints (or empty). `integrator` None is the scene's own; `moments` False skips the per-pixel sums.
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
        return _result(film, counts)
    uniform = int(counts.flat[0]) if (counts == counts.flat[0]).all() else 0
    sampler = cam.sampler().clone()
    sampler.set_sample_count(max(1, round(total / counts.size)))
    sampler.set_samples_per_wavefront(1)
    sampler.seed(seed, total)
    if uniform:  # consecutive samples share a pixel: no index array
        pixel = dr.arange(mi.UInt32, total) // dr.opaque(mi.UInt32, uniform)
        count_of = mi.Float(uniform)
    else:
        pixel = mi.UInt32(np.repeat(np.arange(width * height, dtype=np.uint32), counts.ravel()))
        count_of = dr.gather(mi.Float, mi.Float(counts.ravel().astype(np.float32)), pixel)
    pos, pos_f, ray, ray_weight = _sample_rays(cam, film, sampler, pixel, width)
    if ray.has_differentials:
        ray.scale_differential(dr.rsqrt(count_of))
    spec, valid, aovs = integ.sample(scene, sampler, ray, cam.get_medium(), mi.Bool(True))
    share = dr.rcp(count_of) * (total / counts.size)  # the splat weight: mean count / this pixel's count
    splat = mi.Vector2f(pos) if film.rfilter().is_box_filter() else pos_f
    rgb = _put(block, film, splat, ray_weight * spec, ray.wavelengths, share, dr.select(valid, 1.0, 0.0), aovs)
    sums = _moments(rgb, pixel, width * height) if moments else (None, None)
    film.put_block(block)
    return _result(film, counts, *sums)


def _checked_counts(counts: np.ndarray, width: int, height: int) -> np.ndarray:
    counts = np.asarray(counts)
    if counts.shape != (height, width):
        raise RenderError(f"counts {counts.shape} do not match the film window {height}x{width}")
    if not np.issubdtype(counts.dtype, np.integer) or (counts < 0).any():
        raise RenderError("counts must be non-negative integers")
    if int(counts.sum()) >= 2**32:
        raise RenderError(f"{int(counts.sum())} samples in one wavefront (at most 2^32 - 1)")
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
         aovs: list[Any]) -> Any:
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
    block.put(pos, channels)
    return rgb


def _moments(rgb: Any, pixel: Any, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel, the sum and the sum of squares of its samples' RGB: (size x 3) each. (Atomic scatters
    in the render's own kernel: dr.block_sum over uniform counts measured ~2.5x slower here.)"""
    import drjit as dr
    import mitsuba as mi

    sums, squares = [], []
    for c in (rgb.x, rgb.y, rgb.z):
        acc, acc2 = dr.zeros(mi.Float, size), dr.zeros(mi.Float, size)
        dr.scatter_reduce(dr.ReduceOp.Add, acc, c, pixel)
        dr.scatter_reduce(dr.ReduceOp.Add, acc2, c * c, pixel)
        sums.append(acc)
        squares.append(acc2)
    dr.eval(*sums, *squares)
    return (np.stack([np.array(a, dtype=np.float64) for a in sums], axis=-1),
            np.stack([np.array(a, dtype=np.float64) for a in squares], axis=-1))


def _result(film: Any, counts: np.ndarray, sums: np.ndarray | None = None,
            squares: np.ndarray | None = None) -> WindowRender:
    pixels, names = film_channels(film)
    h, w = counts.shape
    zero = np.zeros((h * w, 3))
    sums = zero if sums is None else sums
    squares = zero if squares is None else squares
    return WindowRender(pixels, names, counts, sums.reshape(h, w, 3), squares.reshape(h, w, 3))


# The two-pass render. FIRST_SHARE of the samples go to a uniform first pass, whose per-pixel variance,
# blurred over BLUR_PX (a pixel's own estimate from a few dozen samples misses rare bright paths), sets
# where the rest go: each pixel's total in proportion to the square root of its relative variance
# (Neyman allocation, equal cost per sample assumed), never below the first pass. Both constants were
# chosen on the tune half of the suite (bench/suite.py), from a model of the allocation on measured noise
# maps (issue 15's note); `quekaro bench adaptive` measures the result on the whole suite.
FIRST_SHARE = 0.5
BLUR_PX = 4.0
# Moved samples land on pixels that may cost more per sample: on the tune half the reallocation cost up to
# ~5 % more time at the same spp. So the second pass stays uniform unless the first pass predicts a
# larger gain than that (relMSE at the same spp below PAYS_BELOW of uniform's).
PAYS_BELOW = 0.95


@dataclass
class AdaptiveRender:
    """The combined image of both passes and each pixel's total samples; `seconds` per pass."""

    pixels: np.ndarray
    channels: tuple[str, ...]
    counts: np.ndarray
    seconds: tuple[float, float]
    nonfinite: int
    predicted: float  # relMSE over uniform's at the same spp, expected from the first pass's noise
    adapted: bool  # False: the first pass predicted too little gain, and the second pass was uniform


def neyman_counts(relative_variance: np.ndarray, first: int, total: float, rng: np.random.Generator,
                  cost: np.ndarray | None = None) -> np.ndarray:
    """Second-pass counts: each pixel's total n = max(first, lam sqrt(variance / cost)), lam such that the
    totals cost what `total` samples at uniform density would, sum(n cost) = total x mean(cost)
    (bisection to 1e-9 relative), minus `first`, rounded stochastically (the expectation is kept) to
    integers. `cost`: each pixel's relative time per sample (None: equal). All zero when the first pass
    spent the budget."""
    variance = np.maximum(np.asarray(relative_variance, dtype=np.float64), 0.0)
    cost = np.ones(variance.shape) if cost is None else np.maximum(np.asarray(cost, dtype=np.float64), 1e-12)
    if cost.shape != variance.shape:
        raise RenderError(f"cost map {cost.shape} does not match the variance map {variance.shape}")
    budget = total * float(cost.mean())
    if budget <= first * float(cost.sum()):
        return np.zeros(variance.shape, dtype=np.int64)
    base = np.sqrt(variance / cost)
    if not base.any():  # no pixel is noisier than another: the rest uniformly
        base = np.ones(base.shape)
    lo, hi = 0.0, budget / float((base * cost)[base > 0].min())
    while hi - lo > 1e-9 * hi:
        lam = 0.5 * (lo + hi)
        lo, hi = (lo, lam) if (np.maximum(first, lam * base) * cost).sum() > budget else (lam, hi)
    extra = np.maximum(first, lo * base) - first
    whole = np.floor(extra)
    return (whole + (rng.random(extra.shape) < extra - whole)).astype(np.int64)


def render_adaptive(scene: Any, spp: int, seed: int, sensor: int = 0, integrator: Any = None,
                    cost: np.ndarray | None = None, first_share: float = FIRST_SHARE,
                    blur_px: float = BLUR_PX) -> AdaptiveRender:
    """Render the film window with `spp` samples per pixel on average, the second pass's placed where the
    noise is. `cost` (the window's shape) is each pixel's relative time per sample, e.g. the complexity
    pre-pass's ray counts (planning.complexity): with it the samples cost what `spp` uniform ones would;
    None counts every sample the same.

    The two passes are independent renders of the same pixels; each pixel's value is their average
    weighted by its sample count in each, so its expectation is Mitsuba's at any split.
    """
    if not 0 < first_share <= 1:
        raise RenderError(f"first_share {first_share} (must be in (0, 1])")
    cam = scene.sensors()[sensor]
    width, height = (int(v) for v in cam.film().crop_size())
    first = max(1, round(spp * first_share))
    start = time.perf_counter()
    one = render_counts(scene, np.full((height, width), first, dtype=np.int64), seed, sensor, integrator)
    noise = one.relative_variance()
    if blur_px > 0:
        noise = gaussian_filter(noise, blur_px, mode="nearest")
    extra, predicted = second_pass(noise, first, spp, np.random.default_rng(seed), cost)
    middle = time.perf_counter()
    two = render_counts(scene, extra, (seed + 1) % 2**32, sensor, integrator, moments=False)
    end = time.perf_counter()
    a, bad_a = sanitize(one.pixels)
    b, bad_b = sanitize(two.pixels)
    wa = np.float32(first) / (first + extra)[..., None].astype(np.float32)
    pixels = (wa * a + (1 - wa) * b).astype(np.float32)
    return AdaptiveRender(pixels, one.channels, first + extra, (middle - start, end - middle), max(bad_a, bad_b),
                          predicted, predicted < PAYS_BELOW)


def second_pass(noise: np.ndarray, first: int, spp: int, rng: np.random.Generator,
                cost: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """(second-pass counts, predicted relMSE ratio at the same spp): Neyman's where it is predicted to
    pay (below PAYS_BELOW), else spp - first everywhere."""
    extra = neyman_counts(noise, first, spp * noise.size, rng, cost)
    predicted = predicted_ratio(noise, first + extra, spp)
    if predicted < PAYS_BELOW:
        return extra, predicted
    return np.full(noise.shape, max(spp - first, 0), dtype=np.int64), predicted


def predicted_ratio(relative_variance: np.ndarray, totals: np.ndarray, spp: int) -> float:
    """Expected relMSE of an image with `totals` samples per pixel over one with `spp` everywhere, for
    this per-sample relative variance: sum(v / n) / sum(v / spp); 1 where there is no noise."""
    noise = float(np.sum(relative_variance)) / spp
    return float(np.sum(relative_variance / np.maximum(totals, 1))) / noise if noise > 0 else 1.0
