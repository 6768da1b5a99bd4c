"""Two-round jobs (`quekaro render --adaptive`): the rules say how many samples a level spends and each
unit's depth and band; where the samples go is measured.

Round one renders every unit at FIRST_SHARE of the level's mean spp, the same everywhere, and returns each
pixel's noise (core.render.counts.NOISE_CHANNEL). The composed noise, blurred across unit borders, places
the rest image-wide (core.render.adaptive.second_pass: Neyman allocation where it predicts a gain, else
uniform). Round two renders each unit's window of those counts, and the two composed images are averaged
per pixel by their counts, so each pixel's expectation stays Mitsuba's.

Why the rules' per-unit spp is not the placement: at equal render time it gave more relMSE than uniform
spp on five of the six suite scenes (docs/benchmarks/inprocess/accuracy.md, "uniform, equal render
time"), while placement from a measured first round gave less on four (docs/benchmarks/adaptive).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from core.errors import QuekaroError
from core.model.geometry import Rect
from core.model.job import JobPlan
from core.render.adaptive import (
    BLUR_PX,
    FIRST_SHARE,
    PAYS_BELOW,
    blurred,
    combine_passes,
    exclusion_px,
    second_pass,
)
from core.render.counts import NOISE_CHANNEL
from core.render.planner import RenderParams


@dataclass(frozen=True)
class Budget:
    """A two-round job's samples: `mean_spp` per pixel on average over both rounds (what the rules chose
    for all units together), `first` per pixel in round one."""

    mean_spp: int
    first: int

    def to_dict(self) -> dict[str, int]:
        return {"mean_spp": self.mean_spp, "first_spp": self.first}


def budget(plan: JobPlan, chosen: Sequence[RenderParams]) -> Budget:
    """The level's samples per pixel (the rules' spp weighted by unit area), and round one's share."""
    total = sum(p.spp * u.rect.area for u, p in zip(plan.units, chosen, strict=True))
    mean = max(1, round(total / (plan.width * plan.height)))
    return Budget(mean, max(1, round(mean * FIRST_SHARE)))


@dataclass(frozen=True)
class SecondRound:
    """Round two's samples per pixel (image-sized), and what round one's noise predicted of them:
    relMSE over uniform's at the same spp, and whether that was low enough to adapt (else uniform)."""

    counts: np.ndarray
    predicted: float
    adapted: bool

    def window(self, rect: Rect) -> np.ndarray:
        """The counts of a unit's rendered window."""
        return np.ascontiguousarray(self.counts[rect.y:rect.y1, rect.x:rect.x1])

    def to_dict(self) -> dict[str, float | bool]:
        return {"predicted_relmse_ratio": self.predicted, "adapted": self.adapted,
                "second_mean_spp": float(self.counts.mean())}


def second_round(noise: np.ndarray, plan_budget: Budget, seed: int, filter_radius: float) -> SecondRound:
    """Round two's counts from round one's composed per-pixel noise (H x W), blurred without the pixels
    within the film's reconstruction filter's reach (`filter_radius`, so that counts and round one's
    values are independent: core.render.adaptive.blurred)."""
    noise = blurred(noise, BLUR_PX, exclusion_px(filter_radius))
    counts, predicted = second_pass(noise, plan_budget.first, plan_budget.mean_spp, np.random.default_rng(seed))
    return SecondRound(counts, predicted, predicted < PAYS_BELOW)


def split_noise(image: np.ndarray, channels: Sequence[str]) -> tuple[np.ndarray, tuple[str, ...], np.ndarray]:
    """A composed planar round-one image (channels, H, W) as (the film's channels, their names, the noise)."""
    names = tuple(channels)
    if not names or names[-1] != NOISE_CHANNEL:
        raise QuekaroError(f"round one's tiles carry no {NOISE_CHANNEL} channel (channels {list(names)[-4:]})")
    return image[:-1], names[:-1], image[-1]


def combine(first_image: np.ndarray, second_image: np.ndarray, plan_budget: Budget,
            second: SecondRound) -> np.ndarray:
    """The job's image: both rounds' planar images averaged per pixel by their sample counts."""
    if first_image.shape != second_image.shape:
        raise QuekaroError(f"round images differ in shape: {first_image.shape} and {second_image.shape}")
    return combine_passes(first_image, second_image, plan_budget.first, second.counts, axis=0)
