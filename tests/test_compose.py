"""core.image.compose: weights sum to one for any layout, NaN never spreads, and no seam shows (statistically)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core.errors import TileError
from core.image.compose import blend_weights, compose, compose_planar, compose_shrunk, tile_weight
from core.image.tiles import Tile
from core.model.geometry import Rect, filter_reach
from planning.complexity import ComplexityMap
from planning.partition import equal_tiles, partition


def smooth_image(width: int, height: int) -> np.ndarray:
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    img = np.stack([np.sin(x / 9.0) + 1.5, np.cos(y / 7.0) + 1.5, (x + y) / (width + height) + 0.2], axis=2)
    return img.astype(np.float32)


def tiles_of(image: np.ndarray, cores: list[Rect], bands: list[int], noise: float = 0.0,
             seed: int = 0) -> list[Tile]:
    """Crop each core plus its band from `image`, each tile with its own independent noise."""
    h, w, _ = image.shape
    rng = np.random.default_rng(seed)
    out = []
    for core, band in zip(cores, bands, strict=True):
        rect = core.window(band, w, h)
        pixels = image[rect.slices()] + rng.normal(0.0, noise, (rect.h, rect.w, 3)) if noise else \
            image[rect.slices()].copy()
        out.append(Tile(pixels=pixels, rect=rect, core=core))
    return out


@st.composite
def layouts(draw: st.DrawFn) -> tuple[int, int, list[Rect], list[int]]:
    """Any exact cover of an image by units (equal tiles or a partition), each with its own band."""
    width, height = draw(st.integers(1, 120)), draw(st.integers(1, 120))
    if draw(st.booleans()):
        cores = equal_tiles(width, height, draw(st.integers(1, 40)))
    else:
        rng = np.random.default_rng(draw(st.integers(0, 999)))
        cmap = ComplexityMap(rng.gamma(1, 1, (height, width)), rng.gamma(1, 1, (height, width)))
        sizes = draw(st.sampled_from([(4, 8), (2, 4, 16), (5,)]))
        cores = [u.rect for u in partition(cmap, draw(st.integers(1, 30)), sizes)]
    bands = draw(st.lists(st.integers(0, 40), min_size=len(cores), max_size=len(cores)))
    return width, height, cores, bands


@settings(max_examples=150, deadline=None)
@given(layouts())
def test_weights_sum_to_one_at_every_pixel(layout) -> None:
    width, height, cores, bands = layout
    geometry = [(c.window(b, width, height), c) for c, b in zip(cores, bands, strict=True)]
    total = np.zeros((height, width))
    for (rect, _), w in zip(geometry, blend_weights(geometry, width, height), strict=True):
        assert np.all(w > 0) and np.all(w <= 1 + 1e-12)
        total[rect.slices()] += w
    np.testing.assert_allclose(total, 1.0, atol=1e-6)


@settings(max_examples=60, deadline=None)
@given(layouts())
def test_tiles_cut_from_one_image_compose_back_to_it(layout) -> None:
    width, height, cores, bands = layout
    image = smooth_image(width, height)
    out, report = compose(tiles_of(image, cores, bands), width, height)
    assert out.dtype == np.float32 and out.shape == (height, width, 3)
    np.testing.assert_allclose(out, image, rtol=1e-5, atol=1e-5)
    assert report.filled == 0 and report.uncovered == 0 and not report.nonfinite


@settings(max_examples=150, deadline=None)
@given(layouts(), st.integers(0, 3))
def test_weights_with_a_reach_sum_to_one_and_never_use_cut_pixels(layout, reach) -> None:
    width, height, cores, bands = layout
    geometry = [(c.window(max(b, reach), width, height), c) for c, b in zip(cores, bands, strict=True)]
    total = np.zeros((height, width))
    for (rect, _), w in zip(geometry, blend_weights(geometry, width, height, reach), strict=True):
        assert np.all(w >= 0) and np.all(w <= 1 + 1e-12)
        x0, y0 = reach * (rect.x > 0), reach * (rect.y > 0)
        x1, y1 = rect.w - reach * (rect.x1 < width), rect.h - reach * (rect.y1 < height)
        outside = np.ones((rect.h, rect.w), dtype=bool)
        outside[y0:y1, x0:x1] = False
        assert np.all(w[outside] == 0)  # the reach at every side that is not the image's edge
        total[rect.slices()] += w
    np.testing.assert_allclose(total, 1.0, atol=1e-6)


@settings(max_examples=60, deadline=None)
@given(layouts(), st.integers(1, 3))
def test_cut_pixels_never_reach_the_image(layout, reach) -> None:
    """Tiles whose `reach` outer pixels hold garbage (as a truncated filter's would be, only worse) compose
    to the image they were cut from."""
    width, height, cores, bands = layout
    image = smooth_image(width, height)
    tiles = tiles_of(image, cores, [max(b, reach) for b in bands])
    for t in tiles:
        r = t.rect
        if r.x > 0:
            t.pixels[:, :reach] = 1e6
        if r.x1 < width:
            t.pixels[:, r.w - reach:] = -1e6
        if r.y > 0:
            t.pixels[:reach] = 1e6
        if r.y1 < height:
            t.pixels[r.h - reach:] = -1e6
    out, report = compose(tiles, width, height, reach=reach)
    np.testing.assert_allclose(out, image, rtol=1e-5, atol=1e-5)
    assert report.filled == 0 and report.uncovered == 0


@settings(max_examples=80, deadline=None)
@given(layouts(), st.integers(1, 7), st.integers(0, 2), st.integers(0, 2**32 - 1))
def test_a_shrunk_composition_is_the_block_mean_of_the_covered_pixels(layout, factor, reach, seed) -> None:
    """compose_shrunk (the page's preview of a large image) against the full composition: each block's mean
    over the pixels some landed tile covers, to float32's precision; blocks with none are 0."""
    width, height, cores, bands = layout
    rng = np.random.default_rng(seed)
    landed = [t for t in tiles_of(smooth_image(width, height), cores, [max(b, reach) for b in bands], noise=0.1,
                                  seed=seed) if rng.random() < 0.7]
    full, _ = compose_planar(landed, width, height, allow_uncovered=True, reach=reach)
    covered = np.zeros((height, width), dtype=bool)
    for t in landed:
        covered[t.rect.slices()] |= tile_weight(t.rect, t.core, reach, (width, height)) > 0
    blocks = (-(-height // factor), factor, -(-width // factor), factor)
    padded = np.zeros((4, blocks[0] * factor, blocks[2] * factor))
    padded[:3, :height, :width], padded[3, :height, :width] = full * covered, covered
    sums = padded.reshape(4, *blocks).sum(axis=(2, 4))
    expected = np.divide(sums[:3], sums[3], out=np.zeros_like(sums[:3]), where=sums[3] > 0)
    shrunk = compose_shrunk(landed, width, height, factor, reach=reach)
    assert shrunk.shape == (3, blocks[0], blocks[2]) and shrunk.dtype == np.float32
    np.testing.assert_allclose(shrunk, expected, rtol=1e-5, atol=1e-5)


def test_a_shrunk_composition_keeps_only_the_planes_asked_and_never_shows_nan() -> None:
    cores = equal_tiles(20, 10, 2)
    tiles = [Tile(np.full((c.h, c.w, 4), v, np.float32), c, c, channels=("R", "G", "B", "A"))
             for c, v in zip(cores, (np.nan, 2.0), strict=True)]
    shrunk = compose_shrunk(tiles, 20, 10, 4)
    assert shrunk.shape == (3, 3, 5) and np.isfinite(shrunk).all()
    assert (shrunk[:, :, :2] == 0).all() and (shrunk[:, :, 3:] == 2.0).all()  # block 2 straddles both: 2.0
    assert (shrunk[:, :, 2] == 2.0).all()
    with pytest.raises(ValueError, match="factor 0"):
        compose_shrunk(tiles, 20, 10, 0)


def test_filter_reach_is_where_a_pixel_misses_samples_past_the_edge() -> None:
    # a pixel d inside the edge has its centre at d + 0.5: box 0.5, tent 1, gaussian 2, lanczos 3
    assert [filter_reach(r) for r in (0.5, 1.0, 1.6, 2.0, 2.5, 3.0)] == [0, 1, 2, 2, 2, 3]


def test_the_reach_is_cut_inside_the_image_only() -> None:
    w = tile_weight(Rect(2, 0, 12, 4), Rect(6, 0, 4, 4), reach=2, image=(20, 4))
    np.testing.assert_allclose(w[0], [0, 0, 1 / 3, 2 / 3, 1, 1, 1, 1, 2 / 3, 1 / 3, 0, 0])
    edge = tile_weight(Rect(0, 0, 8, 4), Rect(0, 0, 4, 4), reach=2, image=(8, 4))
    np.testing.assert_allclose(edge[0], [1, 1, 1, 1, 0.8, 0.6, 0.4, 0.2])  # the image's edge: no cut
    with pytest.raises(ValueError, match="image size"):
        tile_weight(Rect(2, 0, 12, 4), Rect(6, 0, 4, 4), reach=2)


def test_weight_is_one_on_the_core_and_ramps_across_the_band() -> None:
    w = tile_weight(Rect(0, 0, 10, 6), Rect(3, 0, 4, 6))
    np.testing.assert_allclose(w[:, 3:7], 1.0)
    np.testing.assert_allclose(w[0, :3], [0.25, 0.5, 0.75])
    np.testing.assert_allclose(w[0, 7:], [0.75, 0.5, 0.25])


def test_nan_in_one_tile_never_spreads() -> None:
    width, height = 48, 32
    image = smooth_image(width, height)
    cores = equal_tiles(width, height, 6)
    clean, _ = compose(tiles_of(image, cores, [4] * 6), width, height)
    tiles = tiles_of(image, cores, [4] * 6)
    tiles[2].pixels[5, 5, 1] = np.nan  # a NaN in a band overlap, seen by another tile too
    tiles[2].pixels[0, 0, 0] = np.inf
    core = tiles[4].core
    tiles[4].pixels[core.y - tiles[4].rect.y + 3, core.x - tiles[4].rect.x + 3, :] = np.nan  # covered once
    out, report = compose(tiles, width, height)
    assert np.all(np.isfinite(out))
    assert report.nonfinite == {tuple(tiles[2].core.as_list()): 2, tuple(tiles[4].core.as_list()): 1}
    assert report.to_dict()["nonfinite_total"] == 3
    # pixels with another finite contribution keep the clean value; the single-cover hole is filled
    np.testing.assert_allclose(out, clean, rtol=1e-5, atol=1e-5)
    assert report.filled <= 1


def test_a_tile_of_nan_is_filled_from_its_neighbours_and_counted() -> None:
    width, height = 12, 4
    cores = [Rect(0, 0, 6, 4), Rect(6, 0, 6, 4)]
    tiles = [Tile(np.ones((4, 6, 3)), cores[0], cores[0]),
             Tile(np.full((4, 6, 3), np.nan), cores[1], cores[1])]
    out, report = compose(tiles, width, height)
    assert report.filled == 24 and report.nonfinite == {(6, 0, 6, 4): 24}
    np.testing.assert_allclose(out[:, 6], 1.0)  # the column next to finite pixels takes their mean
    np.testing.assert_allclose(out[:, 7:], 0.0)  # no finite neighbour: 0 by rule


def test_uncovered_pixels_are_an_error_unless_allowed() -> None:
    tile = Tile(np.ones((4, 4, 3)), Rect(0, 0, 4, 4), Rect(0, 0, 4, 4))
    with pytest.raises(TileError, match="16 pixel"):
        compose([tile], 8, 4)
    out, report = compose([tile], 8, 4, allow_uncovered=True)
    assert report.uncovered == 16 and np.all(out[:, 4:] == 0) and np.all(out[:, :4] == 1)


def test_duplicate_tiles_first_delivery_wins() -> None:
    core, other_core = Rect(0, 0, 4, 4), Rect(4, 0, 2, 4)
    first = Tile(np.ones((4, 4, 3)), core, core)
    late = Tile(np.full((4, 6, 3), 7.0), Rect(0, 0, 6, 4), core)  # same unit, another band
    other = Tile(np.full((4, 2, 3), 2.0), other_core, other_core)
    for order in ([first, other, late], [first, late, other]):
        out, report = compose(order, 6, 4)
        assert report.duplicates_ignored == 1 and report.tiles_used == 2
        assert np.all(out[:, :4] == 1) and np.all(out[:, 4:] == 2)


def test_malformed_tiles_name_the_unit() -> None:
    class Bad:
        pixels = np.ones((3, 4, 3))
        rect = Rect(0, 0, 4, 4)
        core = Rect(0, 0, 4, 4)

    with pytest.raises(TileError, match=r"unit \[0, 0, 4, 4\].*shape"):
        compose([Bad()], 4, 4)
    Bad.pixels, Bad.rect = np.ones((4, 5, 3)), Rect(0, 0, 5, 4)
    with pytest.raises(TileError, match="outside"):
        compose([Bad()], 4, 4)


def border_mask(cores: list[Rect], width: int, height: int, reach: int) -> np.ndarray:
    """Pixels within `reach` of a border between two units."""
    mask = np.zeros((height, width), dtype=bool)
    for c in cores:
        if c.x > 0:
            mask[c.y:c.y1, max(0, c.x - reach):c.x + reach] = True
        if c.y > 0:
            mask[max(0, c.y - reach):c.y + reach, c.x:c.x1] = True
    return mask


def seam_excess(errors: np.ndarray, border: np.ndarray) -> tuple[float, float, float]:
    """Mean squared error on borders and inside, and the standard error of their difference."""
    eb, ei = errors[border], errors[~border]
    se = np.sqrt(eb.var() / eb.size + ei.var() / ei.size)
    return float(eb.mean()), float(ei.mean()), float(se)


def test_no_seam_with_synthetic_noisy_tiles() -> None:
    width, height, band = 160, 120, 3
    image = smooth_image(width, height)
    cores = equal_tiles(width, height, 20)
    out, _ = compose(tiles_of(image, cores, [band] * len(cores), noise=0.2, seed=7), width, height)
    errors = ((out - image) ** 2).mean(axis=2)
    border = border_mask(cores, width, height, band)
    eb, ei, se = seam_excess(errors, border)
    print(f"synthetic seam test: border MSE {eb:.5f}, interior MSE {ei:.5f}, SE {se:.5f}")
    assert eb <= ei + 3 * se
    # the test can fail: the same tiles summed with their ramps but not normalised show seams
    bad = np.zeros_like(image)
    for t in tiles_of(image, cores, [band] * len(cores), noise=0.2, seed=7):
        bad[t.rect.slices()] += t.pixels * tile_weight(t.rect, t.core)[..., None]
    eb_bad, ei_bad, se_bad = seam_excess(((bad - image) ** 2).mean(axis=2), border)
    assert eb_bad > ei_bad + 3 * se_bad


SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "scenes" / "mitsuba-data"


@pytest.mark.slow
@pytest.mark.skipif(not SHARED.is_dir(), reason="../shared scenes absent")
def test_no_seam_with_real_mitsuba_tiles() -> None:
    """Cornell box 64x64 as 9 tiles (band 3) at 16 spp against a plain 16 spp render, both vs 1024 spp."""
    from core.model.job import SceneSpec
    from core.render.process import RenderRequest, render_full, render_job_here

    spec, size, spp, band = SceneSpec(SHARED / "cbox" / "cbox.xml", {"res": "64"}), 64, 16, 3
    ref = render_full(spec, "llvm_ad_rgb", "path", 6, 1024, seed=99, threads=1)
    plain = render_full(spec, "llvm_ad_rgb", "path", 6, spp, seed=98, threads=1)
    cores = equal_tiles(size, size, 9)
    tiles = [render_job_here(RenderRequest(spec, "llvm_ad_rgb", "path", 6, spp, 1000 + i, size, size, core,
                                     band=band, threads=1)) for i, core in enumerate(cores)]
    out, report = compose(tiles, size, size)
    assert report.tiles_used == 9 and not report.nonfinite
    tm = lambda a: a / (1.0 + a)  # noqa: E731 - tonemapped, so the bright luminaire does not swamp the test
    excess = ((tm(out) - tm(ref)) ** 2).mean(axis=2) - ((tm(plain) - tm(ref)) ** 2).mean(axis=2)
    border = border_mask(cores, size, size, band)
    eb, ei, se = seam_excess(excess, border)
    print(f"mitsuba seam test: excess MSE over a plain render: border {eb:.6f}, interior {ei:.6f}, "
          f"SE {se:.6f}")
    assert eb <= ei + 3 * se
    # and the tiled image is the plain one within noise overall
    assert abs(float(out.mean() - plain.mean())) < 0.02 * float(ref.mean())
