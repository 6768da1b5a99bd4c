"""Adaptive sampling at pixel scale: where a second pass's samples go, from a first pass's per-pixel
noise (Neyman allocation, `neyman_counts`, `second_pass`), and the two-pass render of one film window
built on `core.render.per_pixel.render_counts` (`render_adaptive`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from core.errors import RenderError
from core.image.film import sanitize
from core.render.per_pixel import WindowRender, render_counts

# The two-pass render. FIRST_SHARE of the samples go to a uniform first pass, whose per-pixel variance,
# blurred over BLUR_PX (a pixel's own estimate from a few dozen samples misses rare bright paths), sets
# where the rest go: each pixel's total in proportion to the square root of its relative variance
# (Neyman allocation, equal cost per sample assumed), never below the first pass. Both constants were
# chosen on the tune half of the suite (bench/suite.py), from a model of the allocation on measured noise
# maps (issue 15's notes; the wider blur since heavy-tailed noise, a glossy highlight's rare bright
# paths, shows in few of a pixel's first-pass samples); `quekaro bench adaptive` measures the result on
# the whole suite.
FIRST_SHARE = 0.5
BLUR_PX = 8.0
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
    (exact: `neyman_scale`), minus `first`, rounded stochastically (the expectation is kept) to
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
    extra = np.maximum(first, neyman_scale(base, cost, first, budget) * base) - first
    whole = np.floor(extra)
    return (whole + (rng.random(extra.shape) < extra - whole)).astype(np.int64)


def neyman_scale(base: np.ndarray, cost: np.ndarray, first: int, budget: float) -> float:
    """The lam with sum(max(first, lam base) cost) = budget (base >= 0 not all zero, budget above
    first x sum(cost)). The sum is convex and piecewise linear in lam; Newton's steps from lam = 0 land at
    or above the root and then fall to it, each fixing the set of pixels above `first` and solving the
    linear sum exactly, so they stop once that set stops changing (a handful of steps on noise maps)."""
    weighted = base * cost
    above = base > 0
    lam = 0.0
    for _ in range(base.size + 1):  # the set shrinks at each step after the first, so this always ends
        nxt = (budget - first * float(cost[~above].sum())) / float(weighted[above].sum())
        now = nxt * base > first
        if np.array_equal(now, above) or nxt >= lam > 0:
            return nxt
        above, lam = now, nxt
    return lam


def first_spp(spp: int) -> int:
    """The first pass's samples per pixel for a mean of `spp`."""
    return max(1, round(spp * FIRST_SHARE))


def render_adaptive(scene: Any, spp: int, seed: int, sensor: int = 0, integrator: Any = None,
                    first: int | None = None, blur_px: float = BLUR_PX) -> AdaptiveRender:
    """Render the film window with `spp` samples per pixel on average, `first` of them (default
    `first_spp(spp)`) in a uniform first pass and the rest placed where its noise is, every sample counted
    at the same cost. With `first` >= `spp` there is no second pass.

    The two passes are independent renders of the same pixels; each pixel's value is their average
    weighted by its sample count in each, so its expectation is Mitsuba's at any split.
    """
    first = first_spp(spp) if first is None else first
    if first < 1:
        raise RenderError(f"first pass of {first} samples per pixel (must be >= 1)")
    start = time.perf_counter()
    one, noise = first_pass(scene, first, seed, sensor, integrator, blur_px)
    extra, predicted = second_pass(noise, first, spp, np.random.default_rng(seed))
    middle = time.perf_counter()
    a, bad_a = sanitize(one.pixels)
    if not extra.any():  # the first pass spent the budget
        return AdaptiveRender(a, one.channels, np.full(extra.shape, first), (middle - start, 0.0), bad_a,
                              predicted, False)
    two = render_counts(scene, extra, (seed + 1) % 2**32, sensor, integrator, moments=False)
    end = time.perf_counter()
    b, bad_b = sanitize(two.pixels)
    pixels = combine_passes(a, b, first, extra)
    return AdaptiveRender(pixels, one.channels, first + extra, (middle - start, end - middle), max(bad_a, bad_b),
                          predicted, predicted < PAYS_BELOW)


def first_pass(scene: Any, first: int, seed: int, sensor: int = 0, integrator: Any = None,
               blur_px: float = BLUR_PX) -> tuple[WindowRender, np.ndarray]:
    """The uniform first pass over the film window, `first` samples per pixel, and the noise map the second
    pass's samples follow: its per-pixel relative variance blurred over `blur_px`, each pixel's own
    neighbourhood left out (`blurred`)."""
    film = scene.sensors()[sensor].film()
    width, height = (int(v) for v in film.crop_size())
    one = render_counts(scene, np.full((height, width), first, dtype=np.int64), seed, sensor, integrator)
    return one, blurred(one.relative_variance(), blur_px, exclusion_px(film.rfilter().radius()))


def combine_passes(a: np.ndarray, b: np.ndarray, first: int, extra: np.ndarray, axis: int = -1) -> np.ndarray:
    """Two independent renders of the same pixels, averaged per pixel by their sample counts (`first`
    everywhere in `a`, `extra` (H x W) in `b`); `axis` is the images' channel axis. float32."""
    if first < 1:
        raise RenderError(f"first pass of {first} samples (must be >= 1)")
    weight = np.expand_dims(np.float32(first) / (first + extra).astype(np.float32), axis)
    return (weight * a + (1 - weight) * b).astype(np.float32)


def blurred(noise: np.ndarray, blur_px: float = BLUR_PX, exclude_px: int = 0) -> np.ndarray:
    """The per-pixel noise map blurred over `blur_px` (a gaussian's sigma; 0: as it is), leaving out the
    square of pixels within `exclude_px` of each pixel (renormalised).

    Why leave a square out: a pixel's first-pass value comes from the samples within the reconstruction
    filter's reach; if its second-pass count depended on those same samples' noise, the per-pixel
    weighting of the two passes would correlate with the first pass's value and bias the mean (measured:
    a spectral test scene's pixels off by 2 standard errors). Without them the count is independent of it."""
    if blur_px <= 0:
        return noise
    noise = np.asarray(noise, dtype=np.float64)
    reach = int(4 * blur_px + 0.5)  # truncated at 4 sigma, as scipy.ndimage.gaussian_filter does
    x = np.arange(-reach, reach + 1, dtype=np.float64)
    kernel = np.exp(-0.5 * (x / blur_px) ** 2)
    kernel /= kernel.sum()
    full = separable(noise, kernel)
    if exclude_px <= 0:
        return full
    centre = np.where(np.abs(x) <= exclude_px, kernel, 0.0)
    inner = separable(noise, centre)
    return np.maximum(full - inner, 0.0) / (1.0 - centre.sum() ** 2)


def separable(image: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """`image` (2-D) correlated with `weights` (odd length, centred) along both axes, its edge pixels
    repeated beyond the border: scipy.ndimage.correlate1d's mode "nearest" on each axis, to float64
    rounding (tests/test_adaptive.py compares them). Written here because importing scipy.ndimage costs
    ~0.24 s, paid by every adaptive job's planner and again by its render process before the first unit."""
    weights = np.asarray(weights, dtype=np.float64)
    reach = len(weights) // 2
    out = np.asarray(image, dtype=np.float64)
    for axis in (1, 0):
        padded = np.pad(out, [(reach, reach) if a == axis else (0, 0) for a in (0, 1)], mode="edge")
        out = sliding_window_view(padded, len(weights), axis=axis) @ weights  # the taps as one product
    return out


def exclusion_px(filter_radius: float) -> int:
    """Pixels around a pixel whose samples can reach it through a filter of this radius (a sample lies
    anywhere in its pixel, up to half a pixel beyond the pixel's centre)."""
    return int(np.ceil(filter_radius + 0.5))


def second_pass(noise: np.ndarray, first: int, spp: int, rng: np.random.Generator) -> tuple[np.ndarray, float]:
    """(second-pass counts, predicted relMSE ratio at the same spp): Neyman's where it is predicted to
    pay (below PAYS_BELOW), else spp - first everywhere."""
    extra = neyman_counts(noise, first, spp * noise.size, rng)
    predicted = predicted_ratio(noise, first + extra, spp)
    if predicted < PAYS_BELOW:
        return extra, predicted
    return np.full(noise.shape, max(spp - first, 0), dtype=np.int64), predicted


def predicted_ratio(relative_variance: np.ndarray, totals: np.ndarray, spp: int) -> float:
    """Expected relMSE of an image with `totals` samples per pixel over one with `spp` everywhere, for
    this per-sample relative variance: sum(v / n) / sum(v / spp); 1 where there is no noise."""
    noise = float(np.sum(relative_variance)) / spp
    return float(np.sum(relative_variance / np.maximum(totals, 1))) / noise if noise > 0 else 1.0
