"""The images the benchmarks write beside their reports: at a reader's size, 8 bits a pixel, and rewritten
only when what they show changed, so that a rerun commits no image again for nothing. Each image's
full-size copy goes into the folder `full-size/` beside it, which git ignores (.gitignore)."""

from __future__ import annotations

import io
from pathlib import Path
from typing import NamedTuple

import numpy as np
from matplotlib.figure import Figure
from PIL import Image

from core.files import written_atomically

FULL_SIZE = "full-size"  # the folder beside an image that holds its full-size copy (ignored by git)
DIFF_SIDE = 128  # a difference image's longest side at most, in pixels: 192 of them fit the docs' budget
PLOT_DPI, FULL_DPI = 100, 200  # a plot's resolution for a reader, and of its full-size copy
PLOT_COLOURS = 256  # a plot's palette: 8 bits a pixel


class Sameness(NamedTuple):
    """Two images show the same when at least `share` of their pixels differ by at most `levels` (of 255)."""

    levels: int
    share: float


DIFF_SAME = Sameness(levels=2, share=0.999)  # a rerun's noise, not a change of where the error is
PLOT_SAME = Sameness(levels=0, share=1.0)  # one moved point is a changed plot


def full_size(path: Path) -> Path:
    """Where the full-size copy of the image at `path` goes."""
    return path.parent / FULL_SIZE / path.name


def write_difference(path: Path, value: np.ndarray) -> bool:
    """A grey difference image, (H, W) values with white at 1 (clipped): 8-bit grey at full size into
    `full_size(path)`, and at most DIFF_SIDE px at `path` unless the one there shows the same (DIFF_SAME).
    True when `path` was written."""
    write_png(full_size(path), Image.fromarray(grey_levels(value), mode="L"))
    return write_if_changed(path, Image.fromarray(grey_levels(reader_sized(value)), mode="L"), DIFF_SAME)


def write_plot(path: Path, fig: Figure) -> bool:
    """A matplotlib figure: at FULL_DPI into `full_size(path)`, and at PLOT_DPI with an 8-bit palette at
    `path` unless the one there shows the same (PLOT_SAME). True when `path` was written."""
    write_png(full_size(path), rendered(fig, FULL_DPI))
    return write_if_changed(path, palette(rendered(fig, PLOT_DPI)), PLOT_SAME)


def rendered(fig: Figure, dpi: int) -> Image.Image:
    """The figure drawn at `dpi`, as an RGB image (its background is opaque)."""
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi)
    return Image.open(buffer).convert("RGB")


def palette(image: Image.Image) -> Image.Image:
    """An RGB image with at most PLOT_COLOURS colours, undithered: a plot's flat colours stay flat."""
    return image.quantize(PLOT_COLOURS, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)


def reader_sized(value: np.ndarray) -> np.ndarray:
    """The (H, W) image with its longest side at most DIFF_SIDE, each pixel the mean of the ones it covers
    (Pillow's box resampling: the mean is kept); never enlarged."""
    scale = DIFF_SIDE / max(value.shape)
    if scale >= 1:
        return value
    size = (max(1, round(value.shape[1] * scale)), max(1, round(value.shape[0] * scale)))
    return np.asarray(Image.fromarray(value.astype(np.float32)).resize(size, Image.Resampling.BOX))


def grey_levels(value: np.ndarray) -> np.ndarray:
    """Values in [0, 1] (clipped) as 8-bit grey levels: 256 equal bins, the last one closed (1.0 is 255)."""
    return np.minimum(np.clip(value, 0.0, 1.0) * 256, 255).astype(np.uint8)


def write_if_changed(path: Path, image: Image.Image, same: Sameness) -> bool:
    """Write `image` at `path` unless the image there shows the same; True when written."""
    if path.is_file() and shows_same(path, image, same):
        return False
    write_png(path, image)
    return True


def shows_same(path: Path, image: Image.Image, same: Sameness) -> bool:
    """Whether the PNG at `path` (one that cannot be read shows nothing) and `image` show the same."""
    try:
        with Image.open(path) as old:
            before = np.asarray(old.convert("RGB"), dtype=np.int16)
    except OSError:
        return False
    after = np.asarray(image.convert("RGB"), dtype=np.int16)
    if before.shape != after.shape:
        return False
    close = np.abs(before - after).max(axis=-1) <= same.levels
    return bool(close.mean() >= same.share)


def write_png(path: Path, image: Image.Image) -> None:
    """The image as an optimised PNG, written whole or not at all (no metadata: equal images, equal bytes)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    written_atomically(path, lambda tmp: image.save(tmp, format="PNG", optimize=True), "a PNG image")
