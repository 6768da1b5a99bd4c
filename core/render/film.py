"""Reading a film back after a render: every channel it holds, as `mitsuba` writes them, with the
non-finite values a broken emitter can leave set to 0 and counted."""

from __future__ import annotations

from typing import Any

import numpy as np

from core.errors import RenderError


def sanitize(pixels: np.ndarray) -> tuple[np.ndarray, int]:
    """(pixels with every non-finite value set to 0, number of pixels that had one)."""
    bad = ~np.isfinite(pixels)
    count = int(bad.any(axis=-1).sum())
    if count:
        pixels = np.where(bad, np.float32(0.0), pixels).astype(np.float32)
    return pixels, count


def film_channels(film: Any) -> tuple[np.ndarray, tuple[str, ...]]:
    """Every channel the film holds after a render, as `mitsuba` writes them: (H x W x C, names)."""
    bitmap = film.bitmap()
    names = tuple(bitmap.struct_()[i].name for i in range(bitmap.channel_count()))
    array = np.array(bitmap, dtype=np.float32, copy=True)
    if array.ndim == 2:
        array = array[..., None]
    if names[:3] != ("R", "G", "B"):
        if names[:1] in (("Y",), ("L",)):  # a mono film: its one channel is the image
            return np.repeat(array[..., :1], 3, axis=-1), ("R", "G", "B")
        raise RenderError(f"film channels {list(names)[:8]} do not start with R, G, B")
    return np.ascontiguousarray(array), names
