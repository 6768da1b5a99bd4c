"""Composition: blend the returned tiles (unit core plus interpolation band) into one image.

A tile weighs 1 on its core, falls linearly across its band, and weighs 0 on the band's outer `reach`
pixels, whose truncated filter is not Mitsuba's (`tile_weight`, `blend_weights`). A pixel is the weighted
mean of the tiles that cover it. Tiles whose samples were drawn on their cores alone (their last channel
`WEIGHT`: the filter's weight per sample a pixel, their bands the samples' spill) add up instead: a pixel
is the sum of their values times that weight over the sum of the weights, the image one render of all the
cores gives. Entry points: `compose` and `compose_planar` (the image, a band of rows
at a time), `compose_shrunk` (a preview); `ComposeReport` counts what was more than plain blending.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from core.errors import TileError
from core.model.geometry import Rect

# A pass tile's last channel: the film's filter weight sum per pixel (core.image.passes); a merged unit's
# tile that adds up ends with it too, as the weight per sample a pixel.
WEIGHT = "quekaro.weight"


class TileLike(Protocol):
    pixels: np.ndarray
    rect: Rect
    core: Rect
    channels: tuple[str, ...]


@dataclass
class ComposeReport:
    """What composition had to do beyond plain blending."""

    nonfinite: dict[tuple[int, int, int, int], int] = field(default_factory=dict)  # core -> count
    filled: int = 0  # covered pixels with no finite contribution, filled from their neighbours
    uncovered: int = 0  # pixels no tile covers (only with allow_uncovered=True)
    duplicates_ignored: int = 0
    tiles_used: int = 0

    def to_dict(self) -> dict:
        return {
            "nonfinite": [{"core": list(k), "count": v} for k, v in sorted(self.nonfinite.items())],
            "nonfinite_total": sum(self.nonfinite.values()),
            "filled": self.filled,
            "uncovered": self.uncovered,
            "duplicates_ignored": self.duplicates_ignored,
            "tiles_used": self.tiles_used,
        }


def ramp(start: int, stop: int, core_start: int, core_stop: int, cut_before: int = 0,
         cut_after: int = 0) -> np.ndarray:
    """1-D weights over [start, stop): 1 on [core_start, core_stop), linear fall-off across each band's
    usable part, 0 on the `cut_*` outermost pixels of each band (never inside the core)."""
    pos = np.arange(start, stop, dtype=np.float64)
    before = np.maximum(core_start - pos, 0.0)  # distance outside the core, left/top
    after = np.maximum(pos - (core_stop - 1), 0.0)  # distance outside the core, right/bottom
    usable_before = max(core_start - start - cut_before, 0)
    usable_after = max(stop - core_stop - cut_after, 0)
    w = (1.0 - before / (usable_before + 1)) * (1.0 - after / (usable_after + 1))
    w[(before > usable_before) | (after > usable_after)] = 0.0  # the cut pixels (and nothing negative)
    return w


def tile_weight(rect: Rect, core: Rect, reach: int = 0, image: tuple[int, int] | None = None,
                rows: slice = slice(None)) -> np.ndarray:
    """Un-normalised weight (h, w) of a tile over its rendered rectangle (only its `rows`, if given): 1 on
    its core, 0 on the `reach` outer pixels of each side that is not the edge of the `image` (width,
    height), > 0 between.

    At distance d outside the core, on a side with band b and usable part u = b - reach, the weight is
    1 - d / (u + 1) for d <= u, else 0. The reach pixels lack the filter's samples beyond the window, so
    their mean is not Mitsuba's; at the image's edge Mitsuba lacks them too, so nothing is cut there. The
    cut never enters the core: the planners make every band at least the reach."""
    width, height = image if image is not None else (rect.x1, rect.y1)
    if reach and image is None:
        raise ValueError("tile_weight: a reach needs the image size, to know which sides are its edges")
    wx = ramp(rect.x, rect.x1, core.x, core.x1, reach * (rect.x > 0), reach * (rect.x1 < width))
    wy = ramp(rect.y, rect.y1, core.y, core.y1, reach * (rect.y > 0), reach * (rect.y1 < height))
    return np.outer(wy[rows], wx)


def blend_weights(geometry: Sequence[tuple[Rect, Rect]], width: int, height: int,
                  reach: int = 0) -> list[np.ndarray]:
    """Normalised weights of each (rect, core) tile over its rect; they sum to one at every covered pixel
    (a pixel covered by a single tile takes that tile's value)."""
    total = np.zeros((height, width), dtype=np.float64)
    raw = [tile_weight(rect, core, reach, (width, height)) for rect, core in geometry]
    for (rect, _), w in zip(geometry, raw, strict=True):
        total[rect.slices()] += w
    return [np.divide(w, total[rect.slices()], out=np.zeros_like(w), where=w > 0)
            for (rect, _), w in zip(geometry, raw, strict=True)]


@dataclass(frozen=True)
class TileSource:
    """A tile known by its header (where it lies, its channels and meta), loaded only when needed."""

    rect: Rect
    core: Rect
    channels: tuple[str, ...]
    load: Callable[[], TileLike]
    meta: dict[str, Any] = field(default_factory=dict)


def _as_source(tile: TileLike | TileSource) -> TileSource:
    if isinstance(tile, TileSource):
        return tile
    return TileSource(tile.rect, tile.core, _channels(tile), lambda: tile, dict(getattr(tile, "meta", {})))


def compose(
    tiles: Iterable[TileLike], width: int, height: int, allow_uncovered: bool = False, reach: int = 0
) -> tuple[np.ndarray, ComposeReport]:
    """Blend tiles into a float32 (height, width, channels) image; compose_planar states the rules."""
    planar, report = compose_planar(tiles, width, height, allow_uncovered, reach=reach)
    return np.ascontiguousarray(planar.transpose(1, 2, 0)), report


def compose_planar(tiles: Iterable[TileLike | TileSource], width: int, height: int,
                   allow_uncovered: bool = False, band_rows: int = 128,
                   reach: int = 0) -> tuple[np.ndarray, ComposeReport]:
    """Blend tiles into a float32 (channels, height, width) image, a band of rows at a time; `reach` is
    core.model.geometry.filter_reach of the film's filter (0: every band pixel blends, for tiles without a filter).

    Every channel (alpha, AOVs, moments) blends with the same weights; all tiles must carry the same
    channels in the same order (TileError otherwise). Awkward cases, counted in the report: a non-finite
    pixel weighs 0 in its tile, so it never spreads; a covered pixel with no finite value takes the mean of
    its finite 3x3 neighbours, or 0 (`filled`); a pixel no tile covers raises TileError, or is 0 with
    `allow_uncovered`; a second tile for one core (a late delivery) is ignored: the first wins.
    Memory: the planar output (one plane per channel, as an EXR is written), a band's float64 sums and the
    tiles of one row of units: well under twice the output image for any size."""
    report = ComposeReport()
    chosen = _dedupe([_as_source(t) for t in tiles], width, height, report)
    depth = len(image_channels(chosen[0].channels)) if chosen else 3
    image = np.zeros((depth, height, width), dtype=np.float32)
    covered = np.zeros((height, width), dtype=bool)
    has = np.zeros((height, width), dtype=bool)
    for y0, mean, band_has, band_covered in _blended_bands(chosen, width, height, depth, band_rows, reach, report):
        y1 = y0 + band_has.shape[0]
        image[:, y0:y1][:, band_has] = mean[:, band_has].astype(np.float32)
        has[y0:y1], covered[y0:y1] = band_has, band_covered
    _check_coverage(covered, allow_uncovered, report)
    holes = covered & ~has
    report.filled = int(np.count_nonzero(holes))
    if report.filled:
        _fill_holes(image, holes, has)
    return image, report


def compose_shrunk(tiles: Iterable[TileLike | TileSource], width: int, height: int, factor: int,
                   planes: int = 3, reach: int = 0) -> np.ndarray:
    """The first `planes` channels of the composed image, shrunk `factor` times on each side: a float32
    (planes, ceil(height / factor), ceil(width / factor)) image whose pixel is the mean of the blended
    pixels of its factor x factor block (pixels no tile covers, and holes, left out; a block with none is
    0). For a preview of a large image: it never holds the image at full size, only a band of it."""
    if factor < 1 or planes < 1:
        raise ValueError(f"compose_shrunk: factor {factor} and planes {planes} must be at least 1")
    report = ComposeReport()
    chosen = _dedupe([_as_source(t) for t in tiles], width, height, report)
    depth = min(planes, len(image_channels(chosen[0].channels))) if chosen else planes
    out = np.zeros((depth, -(-height // factor), -(-width // factor)), dtype=np.float32)
    band_rows = factor * max(1, 32 // factor)  # float64 sums of a band: small, as the image is large
    for y0, mean, has, _ in _blended_bands(chosen, width, height, depth, band_rows, reach, report):
        sums = _block_sums(mean, factor)  # 0 where nothing was blended
        counts = _block_sums(has[None].astype(np.float32), factor)[0]
        rows = slice(y0 // factor, y0 // factor + counts.shape[0])
        np.divide(sums, counts, out=out[:, rows], where=counts > 0, casting="unsafe")
    return out


def _block_sums(planar: np.ndarray, factor: int) -> np.ndarray:
    """Sums of each factor x factor block of a planar (c, h, w) array (the last blocks of a row or column
    may be smaller), without a padded copy."""
    _, h, w = planar.shape
    rows = np.add.reduceat(planar, np.arange(0, h, factor), axis=1)
    return np.add.reduceat(rows, np.arange(0, w, factor), axis=2)


def _blended_bands(chosen: list[TileSource], width: int, height: int, depth: int, band_rows: int, reach: int,
                   report: ComposeReport) -> Iterator[tuple[int, np.ndarray, np.ndarray, np.ndarray]]:
    """Blend the first `depth` channels a band of rows at a time, reading each tile only while a band needs
    it: yields (first row, the band's float64 weighted means (depth, rows, width), where a finite value
    was blended, where a tile covers). A mean is 0 where nothing was blended."""
    loaded: dict[int, TileLike] = {}
    for y0 in range(0, height, band_rows):
        y1 = min(height, y0 + band_rows)
        acc = np.zeros((depth, y1 - y0, width), dtype=np.float64)
        wsum = np.zeros((y1 - y0, width), dtype=np.float64)
        covered = np.zeros((y1 - y0, width), dtype=bool)
        for i, source in enumerate(chosen):
            if source.rect.y < y1 and source.rect.y1 > y0:
                tile = loaded.get(i) or loaded.setdefault(i, _loaded(source, report))
                _accumulate(tile, y0, y1, acc, wsum, covered, reach, (width, height))
                if source.rect.y1 <= y1:
                    loaded.pop(i)  # no later band needs it
        has = wsum > 0
        np.divide(acc, wsum, out=acc, where=has)
        yield y0, acc, has, covered
    report.tiles_used = len(chosen)


def _loaded(source: TileSource, report: ComposeReport) -> TileLike:
    """The tile's pixels, checked against its header; its non-finite pixels counted once."""
    tile = source.load()
    where = f"tile for unit {source.core.as_list()}"
    expected = (source.rect.h, source.rect.w, len(source.channels))
    if np.shape(tile.pixels) != expected:
        raise TileError(f"{where}: pixels have shape {np.shape(tile.pixels)}, expected {expected}")
    bad = int((~np.isfinite(tile.pixels)).any(axis=2).sum())
    if bad:
        report.nonfinite[tuple(source.core.as_list())] = bad
    return tile


def _accumulate(tile: TileLike, y0: int, y1: int, acc: np.ndarray, wsum: np.ndarray, covered: np.ndarray,
                reach: int, image: tuple[int, int]) -> None:
    """Add the rows [y0, y1) of a tile's first acc.shape[0] channels, weighted, to a band's sums (a pixel
    with any of them non-finite weighs 0) and mark the band's pixels it `covered`."""
    rect = tile.rect
    top, bottom = max(y0, rect.y), min(y1, rect.y1)
    rows = slice(top - rect.y, bottom - rect.y)
    pixels = np.asarray(tile.pixels[rows, :, :acc.shape[0]], dtype=np.float64)
    finite = np.all(np.isfinite(pixels), axis=2)
    if adds_up(tile.channels):
        placed = np.asarray(tile.pixels[rows, :, -1], dtype=np.float64)
    else:
        placed = tile_weight(rect, tile.core, reach, image, rows)
    w = placed * finite
    cols = slice(rect.x, rect.x1)
    acc[:, top - y0:bottom - y0, cols] += np.moveaxis(np.where(finite[..., None], pixels, 0.0) * w[..., None], 2, 0)
    wsum[top - y0:bottom - y0, cols] += w
    covered[top - y0:bottom - y0, cols] |= placed > 0  # a cut band pixel covers nothing; a non-finite one is a hole


def _dedupe(tiles: Iterable[TileSource], width: int, height: int, report: ComposeReport) -> list[TileSource]:
    """Validate every tile's place and keep the first one delivered per core."""
    seen: set[Rect] = set()
    chosen: list[TileSource] = []
    for tile in tiles:
        _validate(tile, width, height)
        if chosen and tile.channels != chosen[0].channels:
            raise TileError(f"tile for unit {tile.core.as_list()}: channels {list(tile.channels)[:8]} differ "
                            f"from the first tile's {list(chosen[0].channels)[:8]}")
        if tile.core in seen:
            report.duplicates_ignored += 1
            continue
        seen.add(tile.core)
        chosen.append(tile)
    return chosen


def _validate(tile: TileSource, width: int, height: int) -> None:
    rect, core = tile.rect, tile.core
    where = f"tile for unit {core.as_list()}"
    if rect.x < 0 or rect.y < 0 or rect.x1 > width or rect.y1 > height:
        raise TileError(f"{where}: rectangle {rect.as_list()} lies outside the {width}x{height} image")
    if core.intersect(rect) != core or core.area == 0:
        raise TileError(f"{where}: core is empty or not inside the rendered rectangle {rect.as_list()}")


def adds_up(channels: Sequence[str]) -> bool:
    """Whether tiles of these channels add up (their last is `WEIGHT`) rather than blend across bands."""
    return bool(channels) and channels[-1] == WEIGHT


def image_channels(channels: Sequence[str]) -> tuple[str, ...]:
    """A tile's channels that the image has: all but a `WEIGHT` last."""
    return tuple(channels[:-1] if adds_up(channels) else channels)


def _channels(tile: TileLike) -> tuple[str, ...]:
    return tuple(getattr(tile, "channels", ("R", "G", "B")))


def _check_coverage(covered: np.ndarray, allow_uncovered: bool, report: ComposeReport) -> None:
    missing = int(covered.size - np.count_nonzero(covered))
    if missing and not allow_uncovered:
        y, x = np.argwhere(~covered)[0]
        raise TileError(f"{missing} pixel(s) covered by no tile, the first at x={x}, y={y}")
    report.uncovered = missing


def _fill_holes(image: np.ndarray, holes: np.ndarray, good: np.ndarray) -> None:
    """Set each hole of the planar image to the mean of the blended (`good`) pixels in its 3x3
    neighbourhood (else 0)."""
    h, w = holes.shape
    for y, x in np.argwhere(holes):
        ys, xs = slice(max(0, y - 1), min(h, y + 2)), slice(max(0, x - 1), min(w, x + 2))
        mask = good[ys, xs]
        image[:, y, x] = image[:, ys, xs][:, mask].mean(axis=1) if mask.any() else 0.0
