"""Depth floors: per unit, the shallowest depth the rules may cut it to without losing more than
LOSS_TOLERANCE of its light (a cut unit lacks the longer paths' light, and its border shows as a seam).
`measure` finds them from low-resolution renders at the user's depth and each shallower one (`cut_depths`),
in stages (`StagedPasses`, `staged_floors`), where a cut may save more rays than its passes cost (`RayCost`).
The planner never renders a unit below its floor; the master refuses a tile that says it did.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from core.image.film import film_channels
from core.model.geometry import Rect
from core.rules.unit_params import DEPTH_STEPS
from planning.complexity import PREPASS_SPP, film_size, finite_mean

# At most 1 % of a unit's light (and, on average, of its lit pixels' own) may go with a cut: under the
# 1.21 % mean pixel difference the paper reports for its level S, and several times below a pixel's noise
# at the levels that cut.
LOSS_TOLERANCE = 0.01
Z_BOUND = 2.0  # the loss's upper bound: mean + 2 standard errors (about 2.5 % of units judged too leniently)
DARK = 1e-6  # a unit or pixel with less light than this (mean over RGB) loses nothing that can be seen
# Samples per unit and pass: the light of rare long paths is heavy-tailed, and fewer samples let a unit that
# loses more than the tolerance pass too often (tests/test_depth_floors.py counts how often).
MIN_UNIT_SAMPLES = 2048
MAX_FLOOR_SPP = 64  # a unit of fewer than 32 low-resolution pixels takes fewer samples
PROBE_SPP = 8  # the first stage's samples per pixel: a pass at 8 costs about a seventh of one at 57 (interior)
Z_FAIL = 3.0  # a probe refuses a cut whose loss is over the tolerance at mean - 3 standard errors
# A stage after the first renders with its own seed; this odd constant spreads a job's stage seeds apart, so
# that stage 1 of one seed is not stage 0 of the next.
STAGE_SEED_STEP = 0x9E3779B9


@dataclass(frozen=True)
class DepthFloors:
    """Each unit's floor (in unit order), the depths it is chosen from, what the passes took, and each
    pass rendered: (depth, spp)."""

    floors: tuple[int, ...]
    depths: tuple[int, ...]
    seconds: float
    spp: int
    renders: tuple[tuple[int, int], ...] = ()

    def to_info(self) -> dict[str, Any]:
        cut = sum(1 for f in self.floors if f < max(self.depths))  # measured, and allowed some cut
        return {"depth_floor_depths": list(self.depths), "depth_floor_seconds": self.seconds,
                "depth_floor_spp": self.spp, "depth_floor_units_cuttable": cut,
                "depth_floor_tolerance": LOSS_TOLERANCE, "depth_floor_renders": [list(r) for r in self.renders]}


@dataclass(frozen=True)
class RayCost:
    """The rays traced when paths are cut at each depth (column d - 1): per pixel of each unit as the
    render samples it (its spp times its rays per sample), and per sample of the floors' passes (over the
    whole film). A depth past the last column (the user's) costs what the last does: an underestimate of
    a saving, which refuses a cut, never allows one. Rays, not depth: a path that escapes or ends by
    Russian roulette before the cut costs the same at either depth, so an open scene's cut saves little
    where counting a sample's cost as its depth would say it halves the render."""

    unit_pixel: np.ndarray  # (units, depths)
    pass_sample: np.ndarray  # (depths,)

    @classmethod
    def from_rays(cls, depth_rays: np.ndarray, rects: Sequence[Rect], image_size: tuple[int, int],
                  samples: Sequence[int]) -> RayCost:
        """From a ray count (ComplexityMap.depth_rays: (depths, h, w) rays per sample over a low-resolution
        film) and each rect's spp."""
        windows = [_low_window(r, depth_rays.shape[1:], *image_size) for r in rects]
        per_sample = np.array([depth_rays[:, ys, xs].mean(axis=(1, 2)) for ys, xs in windows])
        return cls(per_sample * np.asarray(samples, dtype=np.float64)[:, None], depth_rays.mean(axis=(1, 2)))

    def saved(self, unit: int, deeper: int, depth: int) -> float:
        """Rays per pixel that cutting `unit` from `deeper` to `depth` saves."""
        return float(self.unit_pixel[unit, self._column(deeper)] - self.unit_pixel[unit, self._column(depth)])

    def per_sample(self, depth: int) -> float:
        """Rays per sample of a pass at `depth`."""
        return float(self.pass_sample[self._column(depth)])

    def _column(self, depth: int) -> int:
        return max(1, min(depth, len(self.pass_sample))) - 1


def cut_depths(depth: int) -> list[int]:
    """The depths below `depth` that the planner can choose (its DEPTH_STEPS, rounded as it rounds them)."""
    return sorted({max(1, round(depth * step)) for step in DEPTH_STEPS} - {depth}, reverse=True)


def measure(scene: Any, integrator_at: Callable[[int], str], depth: int, rects: Sequence[Rect],
            low_size: tuple[int, int], image_size: tuple[int, int], seed: int = 0, sensor: int = 0,
            needed: Sequence[int] | None = None, cost: RayCost | None = None) -> DepthFloors:
    """Render `scene` at `low_size` with `integrator_at(d)` (standalone integrator XML) for the user's
    `depth` and the cut depths, in stages, and return each rect's floor (rects in `image_size` pixels).
    `needed`: per rect, the depth its rules chose (None: 1): its floor is measured only as far as decides
    whether that depth is allowed. `cost`: the rays each rect's render traces by depth, which bounds what
    a cut can save (None: every stage is rendered). Why: a cut unit beside an uncut one shows a seam
    (interior at level VB: depth 4 beside depth 8, 20 % of a pixel's light gone), while where longer paths
    carry nothing (an open sky, a still life of few bounces) the cut only saves time."""
    start = time.perf_counter()
    depths = [depth, *cut_depths(depth)]
    spp = floor_spp(rects, low_size, image_size)
    with film_size(scene, *low_size, sensor):
        passes = StagedPasses(lambda d, n, s: _luminance(scene, integrator_at(d), n, s, sensor), stage_spp(spp), seed,
                              low_size[0] * low_size[1])
        floors = staged_floors(passes, depths, rects, image_size, needed, cost)
    return DepthFloors(tuple(floors), tuple(depths), time.perf_counter() - start, spp, tuple(passes.renders))


def stage_spp(spp: int) -> list[int]:
    """The samples per pixel of each stage: a probe of PROBE_SPP and the rest, or one stage where the rest
    would be smaller than the probe. Most cuts that fail, fail by far (a closed room loses several times
    the tolerance), so the probe settles them."""
    return [spp] if spp < 2 * PROBE_SPP else [PROBE_SPP, spp - PROBE_SPP]


class StagedPasses:
    """Luminance per depth and stage over `pixels` low-resolution pixels, each rendered once when first
    asked for (`render(depth, spp, seed)`); a depth's estimate over its first k stages is their samples'
    mean. Stage k renders with its own seed, the same at every depth, so that two depths' passes follow
    the same paths up to the shallower: their difference is the light of the longer paths alone."""

    def __init__(self, render: Callable[[int, int, int], np.ndarray], spp: Sequence[int], seed: int,
                 pixels: int) -> None:
        self._render, self.spp, self._seed, self.pixels = render, list(spp), seed, pixels
        self._done: dict[tuple[int, int], np.ndarray] = {}
        self.renders: list[tuple[int, int]] = []

    @property
    def stages(self) -> int:
        return len(self.spp)

    def done(self, depth: int, stage: int) -> bool:
        return (depth, stage) in self._done

    def light(self, depth: int, stages: int) -> np.ndarray:
        """The mean over the first `stages` stages at `depth`."""
        images = [self._stage(depth, k) for k in range(stages)]
        weights = self.spp[:stages]
        return sum(w * img for w, img in zip(weights, images, strict=True)) / sum(weights)

    def _stage(self, depth: int, k: int) -> np.ndarray:
        if (depth, k) not in self._done:
            seed = (self._seed + k * STAGE_SEED_STEP) % 2**32
            self._done[depth, k] = self._render(depth, self.spp[k], seed)
            self.renders.append((depth, self.spp[k]))
        return self._done[depth, k]


def floor_spp(rects: Sequence[Rect], low_size: tuple[int, int], image_size: tuple[int, int]) -> int:
    """Samples per low-resolution pixel that give the smallest rect MIN_UNIT_SAMPLES, within
    [PREPASS_SPP, MAX_FLOOR_SPP]. The lost light comes from rare long paths: a few samples mostly miss it,
    and then their spread looks small too."""
    low_shape = (low_size[1], low_size[0])
    pixels = min((_window_pixels(_low_window(r, low_shape, *image_size)) for r in rects), default=1)
    return int(np.clip(-(-MIN_UNIT_SAMPLES // pixels), PREPASS_SPP, MAX_FLOOR_SPP))


def _window_pixels(window: tuple[slice, slice]) -> int:
    ys, xs = window
    return (ys.stop - ys.start) * (xs.stop - xs.start)


def floors_from_passes(light: dict[int, np.ndarray], rects: Sequence[Rect],
                       image_size: tuple[int, int]) -> list[int]:
    """Each rect's floor from one stage of low-resolution luminance images per depth (the deepest is the
    user's): the shallowest depth that, with every deeper one, keeps the rect's loss within LOSS_TOLERANCE."""
    passes = StagedPasses(lambda d, _n, _s: light[d], [1], 0, light[max(light)].size)
    return staged_floors(passes, sorted(light, reverse=True), rects, image_size)


def staged_floors(passes: StagedPasses, depths: Sequence[int], rects: Sequence[Rect], image_size: tuple[int, int],
                  needed: Sequence[int] | None = None, cost: RayCost | None = None) -> list[int]:
    """Each rect's floor from `passes` (`depths[0]` is the user's, the rest deeper first); `needed` and
    `cost` as in measure. A rect refused a depth keeps the deeper one and is not tried shallower; one
    allowed a depth at or under its chosen one is not tried shallower either (a floor below its chosen
    depth changes nothing the planner renders)."""
    full_depth, n = depths[0], len(rects)
    floors = [full_depth] * n
    reach = [1] * n if needed is None else [int(d) for d in needed]
    still = [i for i in range(n) if reach[i] < full_depth]
    for deeper, depth in itertools.pairwise(depths):
        still = [i for i in still if reach[i] < deeper]  # else its chosen depth is allowed already
        # Against `deeper`: a unit refused this step keeps it
        gains = {i: 0.0 if cost is None else rects[i].area * cost.saved(i, deeper, max(depth, reach[i]))
                 for i in still}
        cut = _cut(passes, full_depth, depth, {i: rects[i] for i in still}, image_size, gains, cost)
        still = [i for i in still if i in cut]
        for i in still:
            floors[i] = depth
    return floors


def _cut(passes: StagedPasses, full_depth: int, depth: int, rects: dict[int, Rect], image_size: tuple[int, int],
         gains: dict[int, float], cost: RayCost | None) -> set[int]:
    """The keys of `rects` that may be cut from `full_depth` to `depth`: before the last stage a rect is
    refused where its loss is over the tolerance even at its lower bound (_beyond), at the last stage
    where it is not within it at its upper bound (_within). A stage is rendered only where the rects left
    could gain (`gains`: rays each saves if allowed) more than it costs (_cost; no `cost`: always); else
    they are all refused, and keep their depth: that costs time, never light."""
    undecided = list(rects)
    for k in range(1, passes.stages + 1):
        if not undecided or (cost is not None and
                             sum(gains[i] for i in undecided) <= _cost(passes, k - 1, full_depth, depth, cost)):
            return set()
        full, cut = passes.light(full_depth, k), passes.light(depth, k)
        windows = {i: _low_window(rects[i], full.shape, *image_size) for i in undecided}
        if k == passes.stages:
            return {i for i, w in windows.items() if _within(full[w], cut[w])}
        undecided = [i for i, w in windows.items() if not _beyond(full[w], cut[w])]
    return set()


def _cost(passes: StagedPasses, stage: int, full_depth: int, depth: int, cost: RayCost) -> float:
    """The rays of the stages from `stage` on: the low-resolution film at `depth`, and at `full_depth`
    where not yet rendered."""
    return sum(spp * passes.pixels * (cost.per_sample(depth) +
                                      (0.0 if passes.done(full_depth, k) else cost.per_sample(full_depth)))
               for k, spp in enumerate(passes.spp) if k >= stage)


def _within(full: np.ndarray, cut: np.ndarray) -> bool:
    """Whether the light lost between these pixels' full and cut passes is within LOSS_TOLERANCE both of
    their light together and, on average, of each lit pixel's own light, at the upper bound of each
    estimate. The second keeps a cut from a unit whose mean is a bright light's (its own emitter, or the
    film filter's spill of a neighbour's at low resolution) while its other pixels lose more: a seam shows
    against the pixels beside it, not against the unit's mean."""
    light, loss, relative = _losses(full, cut)
    if light <= DARK:
        return True
    return _bound(loss, Z_BOUND) <= LOSS_TOLERANCE * light and _bound(relative, Z_BOUND) <= LOSS_TOLERANCE


def _beyond(full: np.ndarray, cut: np.ndarray) -> bool:
    """Whether the cut loses more than LOSS_TOLERANCE for certain: either of _within's estimates is over it
    at its lower bound, Z_FAIL standard errors below its mean."""
    light, loss, relative = _losses(full, cut)
    if light <= DARK:
        return False
    return _bound(loss, -Z_FAIL) > LOSS_TOLERANCE * light or _bound(relative, -Z_FAIL) > LOSS_TOLERANCE


def _losses(full: np.ndarray, cut: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """These pixels' mean light, each pixel's loss, and each lit pixel's loss relative to its own light
    (in [0, 1] for paired passes: longer paths only add light)."""
    lit = full > DARK
    loss = full - cut
    return float(full.mean()), loss.ravel(), loss[lit] / full[lit]


def _bound(values: np.ndarray, z: float) -> float:
    """The mean of `values` plus `z` standard errors; one value is its own spread."""
    spread = float(values.std(ddof=1)) if values.size > 1 else abs(float(values[0]))
    return float(values.mean()) + z * spread / np.sqrt(values.size)


def _low_window(rect: Rect, low_shape: tuple[int, ...], width: int, height: int) -> tuple[slice, slice]:
    """The low-resolution pixels whose footprint overlaps `rect` (at least one)."""
    lh, lw = low_shape[:2]
    y0, x0 = rect.y * lh // height, rect.x * lw // width
    y1, x1 = -(-rect.y1 * lh // height), -(-rect.x1 * lw // width)
    return slice(y0, max(y1, y0 + 1)), slice(x0, max(x1, x0 + 1))


def _luminance(scene: Any, integrator: str, spp: int, seed: int, sensor: int) -> np.ndarray:
    """Mean over RGB of a render with this integrator, non-finite pixels as 0 (the noise pass counts them)."""
    import mitsuba as mi

    mi.render(scene, sensor=sensor, integrator=mi.load_string(integrator), spp=spp, seed=seed)
    img, _ = film_channels(scene.sensors()[sensor].film())
    return finite_mean(img[..., :3])
