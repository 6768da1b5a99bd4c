"""Adaptive jobs (`--adaptive`, in one process or on a farm): the rules say how many samples a level spends
(`level_spp`), the pre-pass's noise says where they go (`shares`). All of it is planned before any unit
renders, so a farm needs no second round of awards. Each unit then renders in two passes
(core.render.adaptive.render_adaptive): `first_spp` per pixel, then the rest of its share where that pass
is noisy.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from core.errors import QuekaroError
from core.model.geometry import Rect
from core.model.units import SPP_MAX, WorkUnit
from core.render.adaptive import BLUR_PX, PAYS_BELOW, blurred, first_spp, second_pass
from core.rules.unit_params import RenderParams


def level_spp(units: Sequence[WorkUnit], chosen: Sequence[RenderParams]) -> int:
    """The level's samples per pixel: the rules' spp of each unit of the level's own partition, weighted by
    its area."""
    area = sum(u.rect.area for u in units)
    total = sum(p.spp * u.rect.area for u, p in zip(units, chosen, strict=True))
    return max(1, round(total / max(area, 1)))


@dataclass(frozen=True)
class Shares:
    """Each render unit's mean spp (in unit order), the level's mean and the first pass's spp, and what
    the pre-pass predicted of its allocation: relMSE over uniform spp's, and whether that was low enough
    to split unequally."""

    spp: tuple[int, ...]
    mean_spp: int
    first: int
    predicted: float
    adapted: bool

    def to_dict(self) -> dict[str, Any]:
        return {"mean_spp": self.mean_spp, "first_spp": self.first, "unit_spp": list(self.spp),
                "predicted_relmse_ratio": self.predicted, "adapted": self.adapted}


def shares(noise: np.ndarray, rects: Sequence[Rect], mean_spp: int) -> Shares:
    """Split `mean_spp` x the image's pixels over `rects` (the render units, a plain grid) by the pre-pass's
    per-pixel relative noise (H x W): each rect's mean of the image-wide two-pass allocation on that noise,
    blurred (core.render.adaptive.second_pass: Neyman above the first pass, never below it), rounded to whole
    spp, at most SPP_MAX. Equal shares unless the pre-pass predicts that the allocation pays (PAYS_BELOW).
    The rects then place their own samples from their own first pass, so the image-wide split is what the
    pre-pass contributes; its samples are independent of the render's, so no pixel's neighbourhood is left out."""
    if noise.ndim != 2 or not np.isfinite(noise).all() or (noise < 0).any():
        raise QuekaroError(f"pre-pass noise map {noise.shape} is not a finite non-negative image")
    first = first_spp(mean_spp)
    extra, predicted = second_pass(blurred(noise, BLUR_PX), first, mean_spp, np.random.default_rng(0))
    adapted = predicted < PAYS_BELOW
    if not adapted:
        return Shares(tuple(mean_spp for _ in rects), mean_spp, first, predicted, False)
    split = tuple(min(SPP_MAX, first + round(float(extra[r.y:r.y1, r.x:r.x1].mean()))) for r in rects)
    return Shares(split, mean_spp, first, predicted, True)


def describe(shares: dict[str, Any]) -> str:
    """An adaptive job's plan (`Shares.to_dict`, as reports and the job API carry it) in one sentence, as
    `quekaro render`, `quekaro status JOB` and the job's web page show it."""
    spp, predicted = shares["unit_spp"], shares["predicted_relmse_ratio"]
    how = (f"shared by the pre-pass's noise ({min(spp)}-{max(spp)} spp; it predicted {predicted:.2f} of "
           f"uniform's relMSE)" if shares["adapted"]
           else f"shared equally (the pre-pass predicted {predicted:.2f} of uniform's relMSE)")
    return (f"{shares['mean_spp']} spp per pixel from the rules, {how}; each unit renders "
            f"{shares['first_spp']} spp uniformly, then the rest where that pass is noisy")
