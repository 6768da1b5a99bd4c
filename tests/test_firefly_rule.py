"""The firefly allowance of tests/render_check.py at its edges, on synthetic renders (Gaussian noise, so the
t-test's assumptions hold and only the planted pixels can be significant): a clump a film's filter makes
passes, the same pixels apart or a line along a unit border fail."""

from __future__ import annotations

import numpy as np
import pytest
from render_check import FIREFLY_CLUSTERS, FIREFLY_EXTENT, clumps, compare

SIZE, CHANNELS, K = 48, 3, 32


def _renders(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """K reference renders and one test render of the same noise: (K, H, W, C), (H, W, C)."""
    rng = np.random.default_rng(seed)
    drawn = 0.5 + 0.05 * rng.standard_normal((K + 1, SIZE, SIZE, CHANNELS))
    return drawn[:K], drawn[K]


def _planted(pixels: list[tuple[int, int]], seed: int = 1):
    refs, test = _renders(seed)
    for y, x in pixels:
        test[y, x, 0] += 5.0  # 100 standard deviations: significant at any Sidak alpha here
    return compare(test, refs)


def test_an_unplanted_render_passes_and_its_clumps_are_empty():
    verdict = _planted([])
    assert verdict.passed and verdict.clumps == () and verdict.pixels == 0, verdict


def test_a_three_pixel_clump_is_one_firefly_and_passes():
    verdict = _planted([(10, 10), (10, 11), (11, 11)])
    assert verdict.pixels == 3 and verdict.clumps == (2,), verdict
    assert verdict.passed and verdict.only_fireflies, verdict


LONE = [(5, 5), (20, 30), (40, 8), (30, 44), (12, 40)]


def test_as_many_lone_pixels_as_fireflies_allowed_pass_and_one_more_fails():
    allowed = _planted(LONE[:FIREFLY_CLUSTERS])
    assert allowed.clumps == (1,) * FIREFLY_CLUSTERS and allowed.passed, allowed
    verdict = _planted(LONE[:FIREFLY_CLUSTERS + 1])
    assert verdict.clumps == (1,) * (FIREFLY_CLUSTERS + 1), verdict
    assert not verdict.passed and not verdict.only_fireflies, verdict


def test_a_clump_of_the_widest_filters_footprint_passes_and_one_pixel_wider_fails():
    widest = [(20, 20 + i) for i in range(FIREFLY_EXTENT)]
    assert _planted(widest).passed
    verdict = _planted([*widest, (20, 20 + FIREFLY_EXTENT)])
    assert verdict.clumps == (FIREFLY_EXTENT + 1,) and not verdict.passed, verdict


def test_a_seam_along_a_unit_border_fails():
    verdict = _planted([(y, 24) for y in range(SIZE)])
    assert verdict.clumps == (SIZE,) and not verdict.passed, verdict


def test_diagonal_neighbours_touch():
    mask = np.zeros((8, 8), dtype=bool)
    mask[2, 2] = mask[3, 3] = mask[4, 4] = True
    mask[7, 0] = True
    assert clumps(mask) == (3, 1)


@pytest.mark.parametrize("shape", [(SIZE, SIZE + 1, CHANNELS), (SIZE, SIZE, CHANNELS + 1), (1, 1, CHANNELS)])
def test_another_shape_is_never_fireflies(shape):
    refs, _ = _renders(2)
    verdict = compare(np.zeros(shape), refs)
    assert not verdict.passed and not verdict.only_fireflies, verdict
