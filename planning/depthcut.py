"""Depth floors: per unit, the shallowest depth the rules may cut it to without losing a measurable share
of its light.

The rules cut a unit's depth (Rl) at strong optimisation levels. Paths longer than the cut carry light
that the unit then lacks, so a cut unit reads darker than its uncut neighbour and the border shows as a
seam (interior at level VB: depth 4 beside depth 8, 20 % of a pixel's light gone). Where longer paths
carry nothing (an open sky, a still life of few bounces) the cut only saves time. This pass measures which
is which, so that depth is cut only where the scene does not call for the deeper paths.

At the noise pre-pass's low resolution the scene renders at the user's depth and at each shallower depth
the planner can choose (core.render.planner.DEPTH_STEPS), with one seed: each sample follows the same
path up to the cut, so the difference of two passes is the light of the longer paths alone. That light
comes from rare long paths, so a few samples mostly miss it, and then their spread is small too: the
passes take enough samples per pixel that the smallest unit has MIN_UNIT_SAMPLES (at most
MAX_FLOOR_SPP). A unit's floor is the shallowest of those depths (and every deeper one) whose loss over
the unit, its mean plus Z_BOUND standard errors over the unit's low-resolution pixels, stays within
LOSS_TOLERANCE of the unit's light, and whose loss relative to each lit pixel's own light does too, on
average over those pixels (a seam shows against the pixels beside it, not against the unit's mean).
The planner never renders a unit below its floor; the master refuses a tile that says it did."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from core.model.geometry import Rect
from core.render.film import film_channels
from core.render.planner import DEPTH_STEPS
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


@dataclass(frozen=True)
class DepthFloors:
    """Each unit's floor (in unit order), the depths measured, and what the passes took."""

    floors: tuple[int, ...]
    depths: tuple[int, ...]
    seconds: float
    spp: int

    def to_info(self) -> dict[str, Any]:
        cut = sum(1 for f in self.floors if f < max(self.depths))
        return {"depth_floor_depths": list(self.depths), "depth_floor_seconds": self.seconds,
                "depth_floor_spp": self.spp, "depth_floor_units_cuttable": cut,
                "depth_floor_tolerance": LOSS_TOLERANCE}


def cut_depths(depth: int) -> list[int]:
    """The depths below `depth` that the planner can choose (its DEPTH_STEPS, rounded as it rounds them)."""
    return sorted({max(1, round(depth * step)) for step in DEPTH_STEPS} - {depth}, reverse=True)


def measure(scene: Any, integrator_at: Callable[[int], str], depth: int, rects: Sequence[Rect],
            low_size: tuple[int, int], image_size: tuple[int, int], seed: int = 0, sensor: int = 0) -> DepthFloors:
    """Render `scene` at `low_size` with `integrator_at(d)` (standalone integrator XML) for the user's
    `depth` and each cut depth, one seed, and return each rect's floor (rects in `image_size` pixels)."""
    start = time.perf_counter()
    depths = [depth, *cut_depths(depth)]
    spp = floor_spp(rects, low_size, image_size)
    with film_size(scene, *low_size, sensor):
        light = {d: _luminance(scene, integrator_at(d), spp, seed, sensor) for d in depths}
    floors = floors_from_passes(light, rects, image_size)
    return DepthFloors(tuple(floors), tuple(depths), time.perf_counter() - start, spp)


def floor_spp(rects: Sequence[Rect], low_size: tuple[int, int], image_size: tuple[int, int]) -> int:
    """Samples per low-resolution pixel that give the smallest rect MIN_UNIT_SAMPLES, within
    [PREPASS_SPP, MAX_FLOOR_SPP]."""
    low_shape = (low_size[1], low_size[0])
    pixels = min((_window_pixels(_low_window(r, low_shape, *image_size)) for r in rects), default=1)
    return int(np.clip(-(-MIN_UNIT_SAMPLES // pixels), PREPASS_SPP, MAX_FLOOR_SPP))


def _window_pixels(window: tuple[slice, slice]) -> int:
    ys, xs = window
    return (ys.stop - ys.start) * (xs.stop - xs.start)


def floors_from_passes(light: dict[int, np.ndarray], rects: Sequence[Rect],
                       image_size: tuple[int, int]) -> list[int]:
    """Each rect's floor from low-resolution luminance images per depth (the deepest is the user's):
    the shallowest depth that, with every deeper one, keeps the rect's loss within LOSS_TOLERANCE."""
    full_depth = max(light)
    full = light[full_depth]
    width, height = image_size
    floors = []
    for rect in rects:
        ys, xs = _low_window(rect, full.shape, width, height)
        floor = full_depth
        for d in sorted(light, reverse=True)[1:]:  # deeper first: stop at the first cut that loses too much
            if not _within(full[ys, xs], light[d][ys, xs]):
                break
            floor = d
        floors.append(floor)
    return floors


def _within(full: np.ndarray, cut: np.ndarray) -> bool:
    """Whether the light lost between these pixels' full and cut passes is within LOSS_TOLERANCE both of
    their light together and, on average, of each lit pixel's own light, at the upper bound of each
    estimate. The second keeps a cut from a unit whose mean is a bright light's (its own emitter, or the
    film filter's spill of a neighbour's at low resolution) while its other pixels lose more."""
    light = float(full.mean())
    if light <= DARK:
        return True
    loss, lit = full - cut, full > DARK
    relative = loss[lit] / full[lit]  # in [0, 1] for paired passes: longer paths only add light
    return _upper_bound(loss.ravel()) <= LOSS_TOLERANCE * light and _upper_bound(relative) <= LOSS_TOLERANCE


def _upper_bound(values: np.ndarray) -> float:
    """The mean of `values` plus Z_BOUND standard errors; one value is its own spread."""
    spread = float(values.std(ddof=1)) if values.size > 1 else abs(float(values[0]))
    return float(values.mean()) + Z_BOUND * spread / np.sqrt(values.size)


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
