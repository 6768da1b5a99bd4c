"""Adaptive jobs (`--adaptive`, in one process or on a farm): the rules say how many samples a level spends,
the measured noise says where they go.

All of it is planned before any unit renders, so a farm needs no second round of awards:
- `level_spp`: the level's mean samples per pixel, the rules' spp over the level's own partition weighted
  by unit area;
- `shares`: that budget split over the render units (a plain grid) in proportion to each unit's sum of
  sqrt(relative noise) from the complexity pre-pass, never below the first pass: with each unit's pixels
  then placed by Neyman allocation, a unit's error is (sum sqrt v)^2 / its samples, which this split
  minimises. Equal shares unless the pre-pass predicts the split pays (PAYS_BELOW);
- each unit renders in two passes (core.render.adaptive.render_adaptive): `first_spp` per pixel, then the
  rest of its share where that first pass's noise is.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from core.errors import QuekaroError
from core.model.geometry import Rect
from core.model.units import WorkUnit
from core.render.adaptive import PAYS_BELOW, first_spp
from core.render.planner import RenderParams


def level_spp(units: Sequence[WorkUnit], chosen: Sequence[RenderParams]) -> int:
    """The level's samples per pixel: the rules' spp of each unit weighted by its area."""
    area = sum(u.rect.area for u in units)
    total = sum(p.spp * u.rect.area for u, p in zip(units, chosen, strict=True))
    return max(1, round(total / max(area, 1)))


@dataclass(frozen=True)
class Shares:
    """Each render unit's mean spp (in unit order), the level's mean and the first pass's spp, and what
    the pre-pass predicted of the split: relMSE over equal shares', and whether that was low enough."""

    spp: tuple[int, ...]
    mean_spp: int
    first: int
    predicted: float
    adapted: bool

    def to_dict(self) -> dict[str, Any]:
        return {"mean_spp": self.mean_spp, "first_spp": self.first, "unit_spp": list(self.spp),
                "predicted_relmse_ratio": self.predicted, "adapted": self.adapted}


def shares(noise: np.ndarray, rects: Sequence[Rect], mean_spp: int) -> Shares:
    """Split `mean_spp` x the image's pixels over `rects` by the pre-pass's per-pixel relative noise
    (H x W): each rect's samples max(first x area, lam x sum sqrt(noise)), lam by bisection to 1e-9
    relative so that they add up to the budget; each rect's mean rounded to whole spp."""
    if noise.ndim != 2 or not np.isfinite(noise).all() or (noise < 0).any():
        raise QuekaroError(f"pre-pass noise map {noise.shape} is not a finite non-negative image")
    first = first_spp(mean_spp)
    area = np.array([r.area for r in rects], dtype=np.float64)
    weight = np.array([np.sqrt(noise[r.y:r.y1, r.x:r.x1]).sum() for r in rects])
    budget = mean_spp * area.sum()
    equal = tuple(mean_spp for _ in rects)
    if not weight.any() or budget <= first * area.sum():
        return Shares(equal, mean_spp, first, 1.0, False)
    lo, hi = 0.0, budget / weight[weight > 0].min()
    while hi - lo > 1e-9 * hi:
        lam = 0.5 * (lo + hi)
        lo, hi = (lo, lam) if np.maximum(first * area, lam * weight).sum() > budget else (lam, hi)
    samples = np.maximum(first * area, lo * weight)
    predicted = float(np.sum(weight**2 / samples) / np.sum(weight**2 / (mean_spp * area)))
    if predicted >= PAYS_BELOW:
        return Shares(equal, mean_spp, first, predicted, False)
    split = tuple(max(first, round(s / a)) for s, a in zip(samples, area, strict=True))
    return Shares(split, mean_spp, first, predicted, True)
