"""The image of a job as far as its tiles have landed: a PNG the page reloads when a tile arrives.

`Previews.png` blends the tiles recorded so far by `core.image.compose` (the final image's own weights;
pixels no tile covers left black) into `preview.png` beside the job (`write_preview`). An image wider or
taller than `MAX_SIDE` is shrunk by a whole factor (`shrink_factor`): a page never asks the master for a
16k image's gigabytes, nor the browser to decode them.

A denoised job's preview is denoised too, once its AOV pass exists (`planning.pipeline.load_aov_pass`),
as its result will be; before that it is the raw composition. A shrunk preview is denoised shrunk, its
AOVs shrunk by the same blocks: denoising a 16k image whole for each preview would take minutes.
"""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from core.image.compose import compose_shrunk
from core.image.denoise import denoise_planar
from core.image.film import display_rgb
from core.image.imageio import write_png_planar
from core.image.tiles import tile_source
from core.model.job import RGB
from master.pass_merge import merged_sources
from master.store import ResultRecord
from planning.pipeline import load_aov_pass

MIN_INTERVAL_S = 1.0
MAX_SIDE = 2048  # pixels: twice the page's widest view, for high-density screens
PREVIEW_NAME = "preview.png"


@dataclass
class _JobPreview:
    lock: asyncio.Lock = field(default_factory=asyncio.Lock)
    shows: tuple[frozenset[int], bool] | None = None  # unit indices in the PNG on disk, and if it is denoised
    done_at: float = 0.0  # monotonic time the last composition ended
    took_s: float = 0.0


@dataclass
class Previews:
    """The previews of every job the page has asked for."""

    jobs: dict[str, _JobPreview] = field(default_factory=dict)

    async def png(self, job_id: str, folder: Path, width: int, height: int, results: list[ResultRecord],
                  reach: int = 0, colour: tuple[str, ...] = RGB, aov: Path | None = None,
                  passes_of: int | None = None) -> Path:
        """The PNG showing `results`' tiles (composed again if a tile was added since the last one, or the
        AOV pass at `aov`, a denoised job's, appeared), their bands cut by `reach` as in the final image
        (core.image.compose), in the film's `colour` (`passes_of`: as `write_preview`).

        Composing costs time on large images, so it runs in a thread, once at a time per job, and again
        only after MIN_INTERVAL_S or twice the last composition's time, whichever is longer."""
        state = self.jobs.setdefault(job_id, _JobPreview())
        path = folder / PREVIEW_NAME
        denoised = aov is not None and aov.is_file()  # written whole or not at all
        wanted = (frozenset(r.index for r in results), denoised)
        async with state.lock:
            if state.shows == wanted and path.is_file():
                return path
            wait = state.done_at + max(MIN_INTERVAL_S, 2 * state.took_s) - time.monotonic()
            if wait > 0:
                await asyncio.sleep(wait)
            started = time.monotonic()
            await asyncio.to_thread(write_preview, path, width, height, results, reach, colour,
                                    aov if denoised else None, passes_of)
            state.shows, state.done_at, state.took_s = wanted, time.monotonic(), time.monotonic() - started
        return path

    def forget(self, job_id: str) -> None:
        self.jobs.pop(job_id, None)


def shrink_factor(width: int, height: int) -> int:
    """The smallest whole factor that brings a width x height image within MAX_SIDE on both sides (each
    preview pixel is then the mean of a block, composed a band at a time)."""
    return max(1, -(-max(width, height) // MAX_SIDE))


def write_preview(path: Path, width: int, height: int, results: list[ResultRecord], reach: int = 0,
                  colour: tuple[str, ...] = RGB, aov: Path | None = None, passes_of: int | None = None) -> Path:
    """Blend the tiles of `results` into a PNG at `path`, of the image's size shrunk by `shrink_factor`;
    pixels no tile covers are black. `colour` is the film's colour channels (core.image.film.display_rgb);
    `aov`, a denoised job's AOV pass, denoises the image where it exists; `passes_of`: a progressive job's
    unit count, whose results are passes, each unit shown with all its passes so far merged.
    8-bit sRGB, encoded by Pillow (already the master's for the final PNG; no other image library)."""
    factor = shrink_factor(width, height)
    if passes_of is not None:
        tiles = merged_sources(results, passes_of)
    else:
        tiles = [tile_source(r.tile_path, unit_index=r.index) for r in results if Path(r.tile_path).is_file()]
    planar = compose_shrunk(tiles, width, height, factor, reach=reach)
    aux = load_aov_pass(aov) if aov is not None else None
    if aux is not None:
        planar = denoise_planar(planar, colour, block_means(aux, factor))
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_png_planar(path, display_rgb(planar, colour))


def block_means(planar: np.ndarray, factor: int) -> np.ndarray:
    """A planar (c, h, w) image shrunk as `compose_shrunk` shrinks: each pixel the mean of its factor x
    factor block (the last blocks of a row or column may be smaller)."""
    if factor == 1:
        return planar
    _, h, w = planar.shape
    rows, cols = np.arange(0, h, factor), np.arange(0, w, factor)
    sums = np.add.reduceat(np.add.reduceat(planar, rows, axis=1, dtype=np.float64), cols, axis=2)
    counts = np.outer(np.diff(rows, append=h), np.diff(cols, append=w))
    return (sums / counts).astype(np.float32)
