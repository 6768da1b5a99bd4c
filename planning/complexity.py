"""The complexity pre-pass: a cheap estimate of per-pixel render cost and noise, before any unit exists.

`prepass(scene, ...) -> ComplexityMap`: `cost`, the rays traced per sample (`_ray_count_pass`), and `noise`,
the per-sample variance (`_moment_pass`), each from a reduced-resolution render that takes a share of the
full render's samples (`choose_downscale`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from core import mitsuba_env
from core.errors import QuekaroError
from core.image.film import film_channels
from core.model.job import SceneSpec
from core.scene import scene as scene_mod

# Mitsuba and Dr.Jit are imported where used: `import mitsuba` costs ~0.35 s and 85 MB, must follow the
# variant choice (core.mitsuba_env), and processes that never render must not pay for it.

MAX_TRACE_DEPTH = 16  # cap for max_depth=-1 (unbounded) in the ray-count tracer
RR_DEPTH = 5  # Mitsuba's path integrator default
RELATIVE_EPSILON = 0.01  # as core.image.metrics.relmse: keeps black pixels from dividing by zero


class ComplexityError(QuekaroError):
    """A complexity map that is malformed (wrong shape, negative or non-finite values)."""


@dataclass
class ComplexityMap:
    """Per-pixel estimates at full image resolution (H, W).

    `cost`: relative time per sample (rays per sample); `noise`: per-sample variance (mean over RGB);
    `seconds`: what the pre-pass took; `info`: how it was made (downscale, spp, sample counts);
    `mean`: the per-pixel mean radiance (mean over RGB), optional (None: brightness unknown, and
    `relative_noise` falls back to the absolute noise). `depth_rays`: the ray-count pass's own
    low-resolution grid, (depths, h, w): mean rays per sample of paths cut at depth d (layer d - 1),
    optional (None: not counted).
    """

    cost: np.ndarray
    noise: np.ndarray
    seconds: float = 0.0
    info: dict[str, Any] = field(default_factory=dict)
    mean: np.ndarray | None = None
    depth_rays: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.cost = np.asarray(self.cost, dtype=np.float64)
        self.noise = np.asarray(self.noise, dtype=np.float64)
        if self.cost.ndim != 2 or self.cost.shape != self.noise.shape or self.cost.size == 0:
            raise ComplexityError(
                f"cost {self.cost.shape} and noise {self.noise.shape} must be equal, non-empty 2-D shapes")
        if self.mean is not None:
            self.mean = np.asarray(self.mean, dtype=np.float64)
            if self.mean.shape != self.cost.shape:
                raise ComplexityError(f"mean {self.mean.shape} must have the shape of cost {self.cost.shape}")
        if self.depth_rays is not None:
            self.depth_rays = np.asarray(self.depth_rays, dtype=np.float64)
            if self.depth_rays.ndim != 3 or 0 in self.depth_rays.shape:
                raise ComplexityError(f"depth_rays {self.depth_rays.shape} must be a non-empty (depths, h, w) array")
        for name in ("cost", "noise", "mean", "depth_rays"):
            arr = getattr(self, name)
            if arr is None:
                continue
            if not np.all(np.isfinite(arr)) or np.any(arr < 0):
                raise ComplexityError(f"complexity map field {name!r} has negative or non-finite values")

    @property
    def height(self) -> int:
        return int(self.cost.shape[0])

    @property
    def width(self) -> int:
        return int(self.cost.shape[1])

    def complexity(self) -> np.ndarray:
        """Per-pixel complexity: the per-sample standard deviation (the expected error at 1 spp)."""
        return np.sqrt(self.noise)

    def relative_noise(self, epsilon: float = RELATIVE_EPSILON) -> np.ndarray:
        """Per-pixel per-sample relative variance, noise / (mean^2 + epsilon): a pixel's relative MSE at 1
        spp (core.image.metrics.relmse's epsilon). Without a mean, the absolute noise."""
        if self.mean is None:
            return self.noise
        return self.noise / (self.mean * self.mean + epsilon)


# How the pre-pass's samples (budget / 4 of the render's) are spent: the noise (moment) pass takes
# NOISE_SHARE of them at PREPASS_SPP per low-resolution pixel, the ray-count pass the rest at COST_SPP.
# Ray counts are smooth and need few samples; the noise map gains from resolution. On the default
# budget this is 4 spp at half the resolution for the noise (1,024 samples in a 32 px unit) where both
# passes took 16 spp at a fifth (655), for the same total and 0.8x the pre-pass time (0.21 against
# 0.26 s, caustic-corner 320x320, warm, medians of 6 alternating runs). Through the rules (`quekaro bench
# allocation`, 5 pre-pass seeds, the same time map and rule file; relMSE over uniform spp at equal
# render time) VS 0.64 -> 0.61, S 0.64 -> 0.62, N 0.75 -> 0.67, B 0.65 -> 0.63, VB 0.75 -> 0.71; the
# gain is mostly in the seeds that went wrong (N's worst 0.96 -> 0.72). Per 32 px cell, C ranks the
# cells' true relative noise about as well either way (rank correlation 0.78 against 0.80): a low-
# resolution pixel that straddles an edge counts the edge as noise (median C over the true mean std:
# 1.64 at a fifth of the resolution, 1.47 at half), and a 4-sample variance is biased low on heavy
# tails (the glass rim's cell: true mean std 1.0, C 0.3-0.8 over 5 seeds; at a fifth 1.2-2.1).
# Estimating the rim's cells well took 16x these samples (16 spp at full resolution: rms 2.07 for 2.02).
PREPASS_SPP = 4  # samples per low-resolution pixel of the noise (moment) pass
COST_SPP = 4  # of the ray-count pass
NOISE_SHARE = 0.8  # of the pre-pass's samples that go to the noise pass


def choose_downscale(width: int, height: int, full_spp: int, spp: int, budget: float, share: float = 1.0) -> int:
    """Smallest integer k so that one pass of `spp` at (W/k x H/k) uses <= share x budget/4 of the full
    render's samples."""
    allowed = max(budget, 1e-6) / 4 * share * full_spp * width * height
    k = 1
    while spp * math.ceil(width / k) * math.ceil(height / k) > allowed and (k < width or k < height):
        k += 1
    return k


def prepass(
    scene: Any,
    width: int | None = None,
    height: int | None = None,
    integrator: str = "path",
    max_depth: int = 8,
    threads: int | None = None,
    full_spp: int = 64,
    budget: float = 0.05,
    spp: int = PREPASS_SPP,
    seed: int = 0,
    cost_spp: int = COST_SPP,
    sensor: int = 0,
) -> ComplexityMap:
    """Estimate per-pixel cost and noise of `scene` (a loaded mi.Scene or a core.scene.scene.SceneSpec).

    `width`/`height` default to the scene film's size; `full_spp` is the spp of the render this
    pre-pass is for, and sets (with `budget`) how far each pass reduces the resolution; `spp` and
    `cost_spp` are the noise and ray-count passes' samples per low-resolution pixel. `integrator` is a
    plugin type or a standalone integrator XML (core.model.integrators.radiance_xml: the scene's own).
    Together the passes take at most `budget` / 4 of the full render's samples (the rest of the budget goes
    to fixed overhead): the noise pass NOISE_SHARE of them, the ray-count pass the rest, each at 1/k of the
    resolution per axis with its own k (the noise map gets the finer grid). Warm kernels make the passes
    themselves take milliseconds.
    """
    start = time.perf_counter()
    scene = _as_scene(scene, threads)
    mitsuba_env.require_vectorised("the rules' pre-pass (every level but off)")
    film = scene.sensors()[sensor].film()
    fw, fh = (int(v) for v in film.crop_size())  # the image: the film's crop window, as loaded
    width, height = width or fw, height or fh
    k = choose_downscale(width, height, full_spp, spp, budget, NOISE_SHARE)
    kc = choose_downscale(width, height, full_spp, cost_spp, budget, 1.0 - NOISE_SHARE)
    lw, lh = _low_size(width, height, k)
    cw, ch = _low_size(width, height, kc)
    with film_size(scene, lw, lh, sensor):
        noise_low, mean_low = _moment_pass(scene, integrator, max_depth, spp, seed, sensor)
    with film_size(scene, cw, ch, sensor):
        depth_rays = _ray_count_pass(scene, cw, ch, max_depth, cost_spp, seed + 1, sensor)
    cmap = ComplexityMap(
        cost=_upsample(depth_rays[-1], width, height),
        noise=_upsample(noise_low, width, height),
        mean=_upsample(finite_mean(mean_low), width, height),
        info={"downscale": k, "low_size": [lw, lh], "spp": spp, "full_spp": full_spp,
              "cost_downscale": kc, "cost_low_size": [cw, ch], "cost_spp": cost_spp,
              "nonfinite_noise": int(np.count_nonzero(~np.isfinite(mean_low)))},
        depth_rays=depth_rays,
    )
    cmap.seconds = time.perf_counter() - start
    return cmap


def _scaled_crop(film: dict[str, list[int]], w: int, h: int) -> dict[str, list[int]]:
    """The film's size, crop size and offset scaled so that its crop window becomes w x h."""
    scale = (w / film["crop_size"][0], h / film["crop_size"][1])
    low = [w, h]
    size = [max(n, round(f * s)) for n, f, s in zip(low, film["size"], scale, strict=True)]
    offset = [min(round(o * s), full - n) for o, s, full, n in zip(film["crop_offset"], scale, size, low, strict=True)]
    return {"size": size, "crop_size": low, "crop_offset": offset}


def _low_size(width: int, height: int, k: int) -> tuple[int, int]:
    return max(1, math.ceil(width / k)), max(1, math.ceil(height / k))


def _as_scene(scene: Any, threads: int | None) -> Any:
    if isinstance(scene, SceneSpec):
        return scene_mod.load(scene, threads=threads)
    if threads is not None:
        import mitsuba as mi

        mitsuba_env.init(mi.variant(), threads)
    return scene


@contextmanager
def film_size(scene: Any, w: int, h: int, sensor: int = 0) -> Iterator[None]:
    """Temporarily render the image of `scene`'s sensor (its film's crop window, as loaded) at w x h
    pixels, restoring the film afterwards. A cropped film is scaled as a whole, so that its crop window,
    scaled with it, is w x h: the low-resolution image covers the same part of the view."""
    import mitsuba as mi

    params = mi.traverse(scene.sensors()[sensor])
    names = list(params.keys())
    fields = ("size", "crop_size", "crop_offset")
    keys = {s: next(k for k in names if k == "film." + s or k.endswith(".film." + s)) for s in fields}
    saved = {s: list(params[k]) for s, k in keys.items()}

    def apply(values: dict[str, list[int]]) -> None:
        for s in fields:  # size first: the crop is checked against it
            params[keys[s]] = values[s]
        params.update()

    apply(_scaled_crop(saved, w, h))
    try:
        yield
    finally:
        apply(saved)


def _moment_pass(scene: Any, integrator: str, max_depth: int, spp: int, seed: int,
                 sensor: int = 0) -> tuple[np.ndarray, ...]:
    """Per-pixel per-sample variance (mean over RGB, non-finite -> the largest finite value) and mean, from
    Mitsuba's `moment` integrator wrapping the render's own (0.99 correlation with the error at fixed spp,
    docs/design.md section 3).
    It is what makes caustic-lit diffuse surfaces complex while plain glass is not; the mean lets the noise
    be taken relative to the brightness (ComplexityMap.relative_noise), as relMSE weighs a pixel's error."""
    import mitsuba as mi

    if integrator.lstrip().startswith("<"):
        nested: Any = mi.load_string(integrator)
    else:
        nested = {"type": integrator}
        if integrator != "direct":
            nested["max_depth"] = int(max_depth)
    moment = mi.load_dict({"type": "moment", "nested": nested})
    mi.render(scene, sensor=sensor, integrator=moment, spp=max(2, spp), seed=seed)
    img, names = film_channels(scene.sensors()[sensor].film())
    img = img.astype(np.float64)
    second_at = [i for i, n in enumerate(names) if n.startswith("m2_")][:3]  # the nested 2nd moment
    mean_at = [names.index(names[i][3:]) for i in second_at]  # its mean: the same name without m2_
    mean, second = img[..., mean_at], img[..., second_at]
    with np.errstate(invalid="ignore"):  # inf - inf from an infinite emitter: handled just below
        var = np.maximum(second - mean * mean, 0.0).mean(axis=2)
    finite = np.isfinite(var)
    var[~finite] = var[finite].max() if finite.any() else 0.0
    return var, mean


def finite_mean(mean_rgb: np.ndarray) -> np.ndarray:
    """Mean over RGB (H x W x C in), with non-finite or negative pixels set to 0: the noise pass already
    counts them as the noisiest, and a depth's light (planning.depthcut) leaves them out."""
    m = np.asarray(mean_rgb, dtype=np.float64).mean(axis=2)
    return np.where(np.isfinite(m) & (m > 0), m, 0.0)


def _ray_count_pass(scene: Any, w: int, h: int, max_depth: int, spp: int, seed: int,
                    sensor: int = 0) -> np.ndarray:
    """Mean rays per sample of each pixel (camera ray, one per bounce, one shadow ray per smooth hit) of
    paths cut at each depth: (depths, h, w), layer d - 1 for depth d. A cut changes no path before it, so
    one trace gives every depth. (Mitsuba casts no shadow ray at a path's last vertex: a depth's count is
    at most one ray high, alike at every depth.)

    The tracer follows the BSDF sampling and Russian roulette of Mitsuba's `path` integrator but shades
    nothing. Ray count is what a path tracer's time is made of (rank correlation 0.90 with true time,
    docs/design.md section 3); unlike per-tile timing it needs no crop (each new crop compiles a kernel, ~0.1 s)
    and it is per pixel. A pixel that hits nothing costs one ray; glass costs only the bounces it adds."""
    import drjit as dr
    import mitsuba as mi

    n = w * h * spp
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(seed, n)
    idx = dr.arange(mi.UInt32, n)
    pix = idx // spp
    pos = mi.Point2f(mi.Float(pix % w), mi.Float(pix // w)) + sampler.next_2d()
    ray, _ = scene.sensors()[sensor].sample_ray(0.0, sampler.next_1d(), pos / mi.ScalarVector2f(w, h),
                                           sampler.next_2d())
    rays, active, beta = mi.Float(0.0), mi.Bool(True), mi.UnpolarizedSpectrum(1.0)
    depth = MAX_TRACE_DEPTH if max_depth < 0 else max(1, max_depth)
    by_depth = []
    for bounce in range(depth):
        si = scene.ray_intersect(ray, active)
        rays += dr.select(active, 1.0, 0.0)
        active &= si.is_valid()
        bsdf = si.bsdf(ray)
        smooth = mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
        rays += dr.select(active & smooth, 1.0, 0.0)
        u1, u2 = sampler.next_1d(active), sampler.next_2d(active)
        bs, weight = bsdf.sample(mi.BSDFContext(), si, u1, u2, active)
        beta *= mi.unpolarized_spectrum(weight)  # a polarized variant's weight is a Mueller matrix
        active &= dr.max(beta) > 0
        if bounce + 1 >= RR_DEPTH:
            q = dr.minimum(dr.max(beta), 0.95)
            active &= sampler.next_1d(active) < q
            beta /= dr.maximum(q, 1e-8)
        ray = si.spawn_ray(si.to_world(bs.wo))
        dr.eval(rays, active, beta, ray)
        by_depth.append(dr.block_sum(rays, spp))  # each pixel's, on the device: a 1/spp share of the memory
    return np.stack([np.asarray(layer, dtype=np.float64) for layer in by_depth]).reshape(depth, h, w) / spp


def _upsample(low: np.ndarray, width: int, height: int) -> np.ndarray:
    """Nearest-neighbour map of a low-resolution (h, w) array onto (height, width)."""
    lh, lw = low.shape
    ys = np.minimum(np.arange(height) * lh // height, lh - 1)
    xs = np.minimum(np.arange(width) * lw // width, lw - 1)
    return low[np.ix_(ys, xs)]
