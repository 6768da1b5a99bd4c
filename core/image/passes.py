"""A unit rendered in passes: the passes merged exactly, and each pixel's noise estimated between them.

A pass tile carries the film's developed channels and, last, its per-pixel filter weight sum
(`WEIGHT`, Mitsuba's raw `W` channel). Mitsuba develops a pixel as sum(w f) / sum(w), linearly, so the
weight-averaged passes are the image one render with all their samples gives, for any reconstruction
filter (`UnitPasses.tile`). The passes are independent estimates of each pixel, so their spread gives
its variance (batch means, `UnitPasses.variance`), an estimate that improves with every pass.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from core.errors import TileError
from core.image.compose import WEIGHT
from core.image.metrics import RELMSE_EPSILON
from core.image.tiles import Tile
from core.model.geometry import Rect

MIN_PASSES = 2  # a variance from fewer passes is unknown
# A pixel's variance is unknown (0) where one pass holds all but this share of its squared weight: the
# spread's expanded form is exact to ~1e-16 of sum W^2 L^2, so below it rounding would pass for noise
# (at FREE_MIN a relMSE of ~1e-10 at most).
FREE_MIN = 1e-6


def split_weight(tile: Tile) -> tuple[np.ndarray, np.ndarray, tuple[str, ...]]:
    """(the film's channels, float64, H x W x C; the weight plane, H x W; their names) of a pass tile."""
    if not tile.channels or tile.channels[-1] != WEIGHT:
        raise TileError(f"unit {tile.meta.get('unit_index', '?')}: a pass tile ends with channel {WEIGHT!r}, "
                        f"this one with {tile.channels[-1]!r}")
    weight = tile.pixels[..., -1].astype(np.float64)
    if not np.isfinite(weight).all() or (weight < 0).any():
        raise TileError(f"unit {tile.meta.get('unit_index', '?')}: a pass tile's weights are negative or not finite")
    return tile.pixels[..., :-1].astype(np.float64), weight, tile.channels[:-1]


@dataclass
class UnitPasses:
    """The running sums of one unit's passes over its window (H x W pixels, film channels C).

    Per pixel: `sum` = sum_k W_k L_k (C channels), `weight` = sum_k W_k, and over the colour (R, G, B)
    `sq` = sum_k W_k^2 L_k^2, `cross` = sum_k W_k^2 L_k, `wsq` = sum_k W_k^2; `passes` k and `spp` the
    samples per pixel of all passes. float64, so the variance's expanded form loses ~1e-16 relative."""

    window: tuple[int, int, int, int]
    core: tuple[int, int, int, int]
    channels: tuple[str, ...]
    sum: np.ndarray
    weight: np.ndarray
    sq: np.ndarray
    cross: np.ndarray
    wsq: np.ndarray
    passes: int = 0
    spp: int = 0
    seconds: float = 0.0
    spill: bool = False  # its passes drew samples on the core alone (RenderRequest.spill): the tile adds up

    @classmethod
    def first(cls, tile: Tile) -> UnitPasses:
        """The sums of a unit's first pass."""
        values, weight, channels = split_weight(tile)
        h, w = weight.shape
        made = cls(tuple(tile.rect.as_list()), tuple(tile.core.as_list()), channels,
                   np.zeros_like(values), np.zeros((h, w)), np.zeros((h, w, 3)), np.zeros((h, w, 3)),
                   np.zeros((h, w)), spill=bool(tile.meta.get("spill")))
        made.add(tile)
        return made

    def add(self, tile: Tile) -> None:
        """Merge one more pass of this unit (same window, same channels)."""
        values, weight, channels = split_weight(tile)
        shape = (tuple(tile.rect.as_list()), tuple(tile.core.as_list()), channels, bool(tile.meta.get("spill")))
        if shape != (self.window, self.core, self.channels, self.spill):
            raise TileError(f"unit {tile.meta.get('unit_index', '?')}: a pass of window {tile.rect} and "
                            f"{len(channels)} channels (spill {shape[3]}) does not match the unit's others "
                            f"({self.window}, {len(self.channels)} channels, spill {self.spill})")
        w = weight[..., None]
        colour = values[..., :3]
        self.sum += w * values
        self.weight += weight
        self.sq += w * w * colour * colour
        self.cross += w * w * colour
        self.wsq += weight * weight
        self.passes += 1
        self.spp += int(tile.meta.get("spp", 0))
        self.seconds += float(tile.meta.get("seconds", 0.0))

    def pixels(self) -> np.ndarray:
        """The merged image of the window (float32, H x W x C): sum / weight; 0 where no pass had weight."""
        return self._developed(self.sum).astype(np.float32)

    def merged_colour(self) -> np.ndarray:
        """The merged colour (H x W x 3) in float64, as the estimate needs it: float32 would round each
        pass's difference from it by ~1e-7 of the value."""
        return self._developed(self.sum[..., :3])

    def _developed(self, sums: np.ndarray) -> np.ndarray:
        """`sums` (H x W x C) over the weight, float64; 0 where no pass had weight."""
        w = self.weight[..., None]
        return np.where(w > 0, sums / np.where(w > 0, w, 1.0), 0.0)

    def variance(self, colour: np.ndarray | None = None) -> np.ndarray | None:
        """Per pixel and colour channel, the estimated variance of the merged value (H x W x 3), or None
        before MIN_PASSES passes: sum_k W_k^2 (L_k - L)^2 / ((sum_k W_k)^2 - sum_k W_k^2), the batch-means
        variance of a weighted mean, unbiased where a pass's variance is proportional to 1 / W_k (for
        equal weights s^2 / k). With equal passes' correction instead, k / (k - 1) over (sum_k W_k)^2, the
        halving and doubling passes the goals order read ~0.8 of the truth (tests/test_passes.py). The
        squared weights, not the weights, because a large pass's spread is less heavy-tailed than a small
        one's: on lognormal samples its estimate spreads less. Pixels without weight: 0. `colour`: the
        merged colour (float64, H x W x 3) where the caller has it already."""
        if self.passes < MIN_PASSES:
            return None
        merged = self.merged_colour() if colour is None else colour
        spread = self.sq - 2.0 * merged * self.cross + merged * merged * self.wsq[..., None]
        free = self.weight * self.weight - self.wsq  # 2 W1 W2 for two passes: 0 where one holds all the weight
        ok = free > FREE_MIN * self.weight * self.weight
        return np.maximum(spread, 0.0) / np.where(ok, free, 1.0)[..., None] * ok[..., None]

    def relmse(self, epsilon: float = RELMSE_EPSILON) -> float | None:
        """The estimated relMSE of the unit's own pixels (its core, band cut away), as
        core.image.metrics.relmse defines it: the mean over pixels and colour channels of variance /
        (value^2 + epsilon), the value standing for the reference being the lesser of the pixel's merged
        value and its mean over the 3 x 3 pixels around (`box3`). A pixel's own merged value carries its
        rare bright samples, which inflate the denominator exactly where they inflate the variance: with
        it, the units of the suite's still life said to be under TAU were at 1.28 TAU (median) and up to
        1.5 (bench threshold); the lesser of the two is conservative at edges too (the neighbours' mean
        only brightens a dark pixel beside a bright one). None before MIN_PASSES passes."""
        if self.passes < MIN_PASSES:
            return None
        merged = self.merged_colour()
        variance = self.variance(merged)
        x, y, w, h = self.core
        wx, wy = self.window[:2]
        cut = (slice(y - wy, y - wy + h), slice(x - wx, x - wx + w))
        value = np.minimum(merged, box3(merged))[cut]
        return float(np.mean(variance[cut] / (value * value + epsilon)))

    def account(self) -> dict[str, Any]:
        """The unit's line in a job's report: its samples, passes and estimated error."""
        relmse = self.relmse()
        return {"spp": self.spp, "passes": self.passes, "relmse_estimate": relmse,
                "relative_error_estimate": None if relmse is None else relmse ** 0.5}

    def tile(self, meta: dict) -> Tile:
        """The merged unit as a tile: the film's channels; where its passes spill (`spill`), then the weight
        per sample a pixel (`WEIGHT`: the weight over the unit's spp), by which composition adds the tiles
        that overlap, so that units of unequal spp weigh each sample by the density it was drawn at."""
        if not self.spill:
            return Tile(self.pixels(), Rect(*self.window), Rect(*self.core), meta, self.channels)
        density = (self.weight / max(self.spp, 1)).astype(np.float32)[..., None]
        return Tile(np.concatenate([self.pixels(), density], axis=-1), Rect(*self.window), Rect(*self.core),
                    {**meta, "spill": True}, (*self.channels, WEIGHT))


def merge_pass(sums: dict[int, UnitPasses], unit: int, tile: Tile) -> UnitPasses:
    """Merge a pass's tile into `sums[unit]` (its first pass starts them); the unit's sums."""
    if unit in sums:
        sums[unit].add(tile)
    else:
        sums[unit] = UnitPasses.first(tile)
    return sums[unit]


def box3(image: np.ndarray) -> np.ndarray:
    """Each pixel's mean over the 3 x 3 pixels around it (H x W x C), the edges repeated outward."""
    padded = np.pad(image, ((1, 1), (1, 1), (0, 0)), mode="edge")
    h, w = image.shape[:2]
    return sum(padded[dy:dy + h, dx:dx + w] for dy in range(3) for dx in range(3)) / 9.0
