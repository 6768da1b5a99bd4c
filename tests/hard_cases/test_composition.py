"""Hard cases of composition beyond tests/test_compose.py: extreme finite values in overlapping bands.

The blend is a convex combination (weights positive, summing to one), so every composed pixel must lie
between the smallest and largest value the tiles covering it hold, even at float32's limits, where a
float32 weighted sum would overflow to inf or underflow to 0.
"""

from __future__ import annotations

import warnings

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from core.image.compose import compose
from core.image.tiles import Tile
from core.model.geometry import Rect
from planning.partition import equal_tiles

F32_MAX = float(np.finfo(np.float32).max)
F32_TINY = float(np.finfo(np.float32).smallest_subnormal)


def _tiles(width: int, height: int, n: int, bands: list[int], values: list[float]) -> list[Tile]:
    out = []
    for i, core in enumerate(equal_tiles(width, height, n)):
        rect = core.window(bands[i % len(bands)], width, height)
        out.append(Tile(np.full((rect.h, rect.w, 3), values[i % len(values)], np.float32), rect, core))
    return out


def _bounds(tiles: list[Tile], width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    lo = np.full((height, width), np.inf)
    hi = np.full((height, width), -np.inf)
    for t in tiles:
        s = t.rect.slices()
        lo[s] = np.minimum(lo[s], t.pixels[..., 0])
        hi[s] = np.maximum(hi[s], t.pixels[..., 0])
    return lo, hi


@settings(max_examples=60, deadline=None)
@given(
    width=st.integers(1, 40), height=st.integers(1, 40), n=st.integers(1, 9),
    bands=st.lists(st.integers(0, 50), min_size=1, max_size=4),
    values=st.lists(st.sampled_from([0.0, F32_TINY, 1e-30, 1.0, 1e30, F32_MAX]), min_size=1, max_size=4),
)
def test_blend_stays_within_the_covering_tiles_at_float32_limits(width, height, n, bands, values):
    tiles = _tiles(width, height, n, bands, values)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an overflow in the blend would warn before it showed
        image, report = compose(tiles, width, height)
    assert image.dtype == np.float32 and np.isfinite(image).all()
    lo, hi = _bounds(tiles, width, height)
    # float32 rounding of the float64 blend: within one ulp of the bounds
    with np.errstate(over="ignore"):  # one ulp above float32's largest value is inf: a fine bound
        below = np.nextafter(lo.astype(np.float32), np.float32(-np.inf))
        above = np.nextafter(hi.astype(np.float32), np.float32(np.inf))
    assert (image[..., 0] >= below).all() and (image[..., 0] <= above).all()
    assert report.nonfinite == {} and report.filled == 0


def test_largest_float_beside_a_subnormal_neighbour():
    a = Tile(np.full((4, 8, 3), F32_MAX, np.float32), Rect(0, 0, 8, 4), Rect(0, 0, 6, 4))
    b = Tile(np.full((4, 8, 3), F32_TINY, np.float32), Rect(4, 0, 8, 4), Rect(6, 0, 6, 4))
    image, _ = compose([a, b], 12, 4)
    assert np.isfinite(image).all()
    assert (image[:, :4] == np.float32(F32_MAX)).all()  # covered by `a` alone
    assert (image[:, 8:] == np.float32(F32_TINY)).all()  # covered by `b` alone: not flushed to 0
    assert (np.diff(image[0, :, 0].astype(np.float64)) <= 0).all()  # a monotone ramp across the band
