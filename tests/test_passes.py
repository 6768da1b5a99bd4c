"""core.image.passes: passes merged as one render with all their samples, and the variance between them."""

from __future__ import annotations

import numpy as np
import pytest

from core.errors import TileError
from core.image.passes import FREE_MIN, MIN_PASSES, WEIGHT, UnitPasses, box3
from core.image.tiles import Tile
from core.model.geometry import Rect

WINDOW, CORE = Rect(0, 0, 6, 4), Rect(1, 1, 4, 2)
CHANNELS = ("R", "G", "B", "A", WEIGHT)


def pass_tile(sums: np.ndarray, weight: np.ndarray, spp: int = 4) -> Tile:
    """A pass as a render returns it: developed values (sums / weight) and the weight plane."""
    developed = np.where(weight[..., None] > 0, sums / np.where(weight > 0, weight, 1)[..., None], 0)
    return Tile(np.concatenate([developed, weight[..., None]], axis=-1), WINDOW, CORE,
                {"unit_index": 0, "spp": spp, "seconds": 0.5}, CHANNELS)


def test_merge_is_one_film_with_every_pass_splatted() -> None:
    rng = np.random.default_rng(1)
    sums = [rng.uniform(0, 5, (4, 6, 4)) for _ in range(3)]
    weights = [rng.uniform(0.5, 3, (4, 6)) for _ in range(3)]
    merged = UnitPasses.first(pass_tile(sums[0], weights[0]))
    for s, w in zip(sums[1:], weights[1:], strict=True):
        merged.add(pass_tile(s, w))
    expected = sum(sums) / sum(weights)[..., None]
    np.testing.assert_allclose(merged.pixels(), expected, rtol=1e-6)  # float32 tiles: their rounding only
    assert (merged.passes, merged.spp, merged.seconds) == (3, 12, 1.5)
    tile = merged.tile({"unit_index": 0})
    assert tile.channels == CHANNELS[:-1] and tile.rect == WINDOW and tile.core == CORE


def test_a_pixel_no_pass_weighted_stays_black() -> None:
    weight = np.ones((4, 6))
    weight[0, 0] = 0.0
    merged = UnitPasses.first(pass_tile(np.ones((4, 6, 4)), weight))
    merged.add(pass_tile(np.ones((4, 6, 4)) * 3, weight))
    assert merged.pixels()[0, 0].tolist() == [0, 0, 0, 0] and merged.pixels()[1, 1, 0] == 2.0
    assert merged.variance()[0, 0].tolist() == [0, 0, 0]


def test_the_estimates_edges_where_one_pass_holds_nearly_all_of_a_pixels_weight() -> None:
    """The denominator (sum W)^2 - sum W^2 is 2 W1 W2 for two passes. Where one pass holds all of a pixel's
    weight, or all but under FREE_MIN of its square, the variance is unknown: 0, finite. Above that it
    equals the definition sum W_k^2 (L_k - L)^2 / (2 W1 W2) to 1e-6 (relative)."""
    first_w, second_w = np.ones((4, 6)), np.ones((4, 6))
    second_w[0, 0], second_w[0, 1], second_w[0, 2] = 0.0, 1e-9, 1e-3
    merged = UnitPasses.first(pass_tile(np.ones((4, 6, 4)), first_w))
    merged.add(pass_tile(np.full((4, 6, 4), 3.0) * second_w[..., None], second_w))
    variance = merged.variance()
    assert np.isfinite(variance).all() and variance[0, 0].tolist() == variance[0, 1].tolist() == [0, 0, 0]
    assert 2 * 1e-9 < FREE_MIN < 2 * 1e-3  # the second pass's share of the squared weight at (0, 1) and (0, 2)
    w2 = 1e-3
    mean = (1.0 + 3.0 * w2) / (1.0 + w2)
    expected = ((1.0 - mean) ** 2 + w2 ** 2 * (3.0 - mean) ** 2) / (2.0 * w2)
    assert variance[0, 2] == pytest.approx([expected] * 3, rel=1e-6)
    assert variance[1, 1] == pytest.approx([1.0, 1.0, 1.0])  # equal passes of 1 and 3: s^2 / k = 2 / 2


def test_variance_unknown_before_two_passes() -> None:
    merged = UnitPasses.first(pass_tile(np.ones((4, 6, 4)), np.ones((4, 6))))
    assert MIN_PASSES == 2 and merged.variance() is None and merged.relmse() is None


def test_equal_weights_give_the_sample_variance_over_k() -> None:
    values = [1.0, 2.0, 4.0]
    merged = None
    for v in values:
        tile = pass_tile(np.full((4, 6, 4), v), np.ones((4, 6)))
        merged = UnitPasses.first(tile) if merged is None else merged.add(tile) or merged
    np.testing.assert_allclose(merged.variance(), np.var(values, ddof=1) / 3, rtol=1e-12)


# Pass sizes as the jobs order them: equal, a budget's (budget_passes(16): a small first pass, then halving
# ones), halving alone, a noise goal's first passes then doubling ones (planning.progressive), and a mixed one.
PASS_SIZES = {"equal": [4] * 6, "budget": [1, 7, 4, 2, 2], "halving": [8, 4, 2, 1, 1],
              "doubling": [8, 8, 8, 8, 32, 64], "mixed": [1, 2, 3, 1, 2, 3, 1, 2]}


@pytest.mark.parametrize("sizes", PASS_SIZES.values(), ids=PASS_SIZES.keys())
def test_variance_estimate_tracks_the_true_variance_of_the_merge(sizes) -> None:
    """Passes of these sizes around a known mean: the estimate's mean over pixels and trials is within 5 % of
    the merge's true variance (measured by repeating the merge; 400 trials of 72 pixel channels, the
    estimate's own spread well under 2 %), and relMSE is that over value^2 + epsilon. Unequal passes need
    the weighted estimator's own correction: with k / (k - 1), as for equal passes, the halving passes
    read 0.83 of the truth and the doubling ones 0.81."""
    rng = np.random.default_rng(7)
    sigma, trials = 0.5, 400
    estimates, merges = [], []
    for _ in range(trials):
        merged = None
        for spp in sizes:  # each pass's value has variance sigma^2 / spp
            w = np.full((4, 6), float(spp))
            value = 2.0 + rng.normal(0, sigma / np.sqrt(spp), (4, 6, 4))
            tile = pass_tile(value * w[..., None], w, spp)
            merged = UnitPasses.first(tile) if merged is None else merged.add(tile) or merged
        estimates.append(merged.variance().mean())
        merges.append(merged.pixels()[..., :3])
    true = np.var(np.stack(merges), axis=0).mean()
    assert true == pytest.approx(sigma ** 2 / sum(sizes), rel=0.05)
    assert abs(np.mean(estimates) / true - 1) < 0.05
    rel = merged.relmse(epsilon=0.0)
    colour = merged.pixels()[..., :3].astype(np.float64)
    value = np.minimum(colour, box3(colour))[1:3, 1:5]
    assert rel == pytest.approx(float(np.mean(merged.variance()[1:3, 1:5] / value ** 2)))


def test_box3_is_the_mean_of_the_nine_pixels_around_with_edges_repeated():
    image = np.arange(12, dtype=np.float64).reshape(3, 4, 1)
    out = box3(image)
    assert out[1, 1, 0] == pytest.approx(image[0:3, 0:3].mean())
    assert out[0, 0, 0] == pytest.approx(np.mean([0, 0, 1, 0, 0, 1, 4, 4, 5]))
    assert box3(np.full((1, 1, 3), 2.5)).tolist() == [[[2.5, 2.5, 2.5]]]


def test_a_tile_without_the_weight_or_of_another_window_is_refused() -> None:
    plain = Tile(np.ones((4, 6, 4), np.float32), WINDOW, CORE, {"unit_index": 3}, ("R", "G", "B", "A"))
    with pytest.raises(TileError, match=r"unit 3: a pass tile ends with channel 'quekaro\.weight'"):
        UnitPasses.first(plain)
    merged = UnitPasses.first(pass_tile(np.ones((4, 6, 4)), np.ones((4, 6))))
    other = Tile(np.ones((4, 7, 5), np.float32), Rect(0, 0, 7, 4), CORE, {"unit_index": 0}, CHANNELS)
    with pytest.raises(TileError, match="does not match the unit's others"):
        merged.add(other)
    negative = pass_tile(np.ones((4, 6, 4)), np.ones((4, 6)))
    negative.pixels[0, 0, -1] = -1
    with pytest.raises(TileError, match="negative or not finite"):
        merged.add(negative)
