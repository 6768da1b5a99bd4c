"""Reading a film back after a render: every channel it holds, as `mitsuba` writes them, with the
non-finite values a broken emitter can leave set to 0 and counted; and the job's image back in the
film's own colour channels."""

from __future__ import annotations

from typing import Any

import numpy as np

from core.errors import RenderError
from core.model.job import FILM_COLOURS, RGB


def sanitize(pixels: np.ndarray) -> tuple[np.ndarray, int]:
    """(pixels with every non-finite value set to 0, number of pixels that had one)."""
    bad = ~np.isfinite(pixels)
    count = int(bad.any(axis=-1).sum())
    if count:
        pixels = np.where(bad, np.float32(0.0), pixels).astype(np.float32)
    return pixels, count


def film_channels(film: Any) -> tuple[np.ndarray, tuple[str, ...]]:
    """Every channel the film holds after a render, as `mitsuba` writes them, its colour first as R, G, B
    (H x W x C, names): an X, Y, Z film's X, Y, Z are named R, G, B, a luminance film's Y is repeated
    thrice, so that every tile carries colour alike; `film_output` gives the job's image the film's own."""
    bitmap = film.bitmap()
    names = bitmap_names(bitmap)
    array = np.array(bitmap, dtype=np.float32, copy=True)
    if array.ndim == 2:
        array = array[..., None]
    colour = colour_of(names)
    if colour is None:
        raise RenderError(f"film channels {list(names)[:8]} start with no colour channels quekaro knows "
                          f"(R, G, B; X, Y, Z; Y: hdrfilm's pixel formats)")
    if len(colour) == 1:
        array = np.concatenate([np.repeat(array[..., :1], 3, axis=-1), array[..., 1:]], axis=-1)
    return np.ascontiguousarray(array), RGB + names[len(colour):]


def film_weight(film: Any, share: np.ndarray | None = None) -> np.ndarray:
    """The film's per-pixel filter weight sum after a render (H x W, float32): Mitsuba's raw `W` channel,
    divided by `share` where samples were splatted with that weight (core.render.per_pixel)."""
    raw = film.bitmap(raw=True)
    names = bitmap_names(raw)
    if "W" not in names:
        raise RenderError(f"film {film.class_name()} keeps no weight channel (raw channels {list(names)[:8]}): "
                          "its renders cannot be merged in passes")
    weight = np.array(raw, dtype=np.float32).reshape(raw.height(), raw.width(), -1)[..., names.index("W")]
    return weight if share is None else (weight / share).astype(np.float32)


def bitmap_names(bitmap: Any) -> tuple[str, ...]:
    """The channel names of a Mitsuba bitmap, in its order."""
    return tuple(bitmap.struct_()[i].name for i in range(bitmap.channel_count()))


def colour_of(names: tuple[str, ...]) -> tuple[str, ...] | None:
    """The colour channels a film's channel names start with (core.model.job.FILM_COLOURS), or None."""
    return next((c for c in FILM_COLOURS.values() if names[:len(c)] == c), None)


def film_output(planar: np.ndarray, channels: tuple[str, ...],
                colour: tuple[str, ...]) -> tuple[np.ndarray, tuple[str, ...]]:
    """A planar (C x H x W) image whose colour is R, G, B (as `film_channels` names it) in the film's own
    colour channels `colour`, as plain Mitsuba writes them: renamed, or for Y its first plane alone."""
    if tuple(channels[:3]) != RGB or colour == RGB:
        return planar, tuple(channels)
    if len(colour) == 1:  # its three colour planes are equal: the last of them, and the rest, unrenamed
        return planar[2:], colour + tuple(channels[3:])
    return planar, colour + tuple(channels[3:])


# Linear sRGB from CIE XYZ (IEC 61966-2-1, D65), the matrix Mitsuba's xyz_to_srgb applies.
XYZ_TO_SRGB = np.array([[3.240479, -1.537150, -0.498535],
                        [-0.969256, 1.875991, 0.041556],
                        [0.055648, -0.204043, 1.057311]], dtype=np.float32)


def display_rgb(planar: np.ndarray, colour: tuple[str, ...]) -> np.ndarray:
    """The first three planes of a planar image (colour as `film_channels` names it) as linear sRGB, for
    a preview: an X, Y, Z film's colour converted, any other as it is."""
    if colour != ("X", "Y", "Z"):
        return planar[:3]
    return np.einsum("ij,jhw->ihw", XYZ_TO_SRGB, planar[:3]).astype(np.float32)
