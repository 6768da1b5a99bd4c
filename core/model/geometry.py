"""Pixel rectangles, the one geometry type that every part of the farm passes around, and how far a
reconstruction filter reaches past a rectangle's edge."""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True, order=True)
class Rect:
    """A pixel rectangle: origin top-left, y down, half-open ([x, x + w) x [y, y + h))."""

    x: int
    y: int
    w: int
    h: int

    def __post_init__(self) -> None:
        if self.w < 0 or self.h < 0:
            raise ValueError(f"rectangle with negative size: {self}")

    @property
    def x1(self) -> int:
        return self.x + self.w

    @property
    def y1(self) -> int:
        return self.y + self.h

    @property
    def area(self) -> int:
        return self.w * self.h

    def window(self, band: int, width: int, height: int) -> Rect:
        """The rectangle a unit renders: this one grown by `band` on every side, but at the image's edge
        shifted inside (the band it cannot have there is added on the opposite side) rather than clipped,
        so that every unit of one size and band renders a window of one size and Dr.Jit compiles one
        kernel for them all. An axis shorter than the grown size is the whole axis."""
        x, w = _window_axis(self.x, self.w, band, width)
        y, h = _window_axis(self.y, self.h, band, height)
        return Rect(x, y, w, h)

    def intersect(self, other: Rect) -> Rect:
        x0, y0 = max(self.x, other.x), max(self.y, other.y)
        x1, y1 = min(self.x1, other.x1), min(self.y1, other.y1)
        return Rect(x0, y0, max(0, x1 - x0), max(0, y1 - y0))

    def bounding(self, other: Rect) -> Rect:
        """The least rectangle holding both."""
        x0, y0 = min(self.x, other.x), min(self.y, other.y)
        return Rect(x0, y0, max(self.x1, other.x1) - x0, max(self.y1, other.y1) - y0)

    def slices(self) -> tuple[slice, slice]:
        """Numpy index (rows, columns) of this rectangle in a full image."""
        return slice(self.y, self.y1), slice(self.x, self.x1)

    def as_list(self) -> list[int]:
        return [self.x, self.y, self.w, self.h]

    @classmethod
    def from_list(cls, values: list[int] | tuple[int, int, int, int]) -> Rect:
        x, y, w, h = (int(v) for v in values)
        return cls(x, y, w, h)


def _window_axis(start: int, size: int, band: int, full: int) -> tuple[int, int]:
    """(start, size) of a window along one axis of `full` pixels: see Rect.window."""
    grown = size + 2 * band
    if grown >= full:
        return 0, full
    return min(max(start - band, 0), full - grown), grown


# Mitsuba's default reconstruction filter, a gaussian of standard deviation 0.5 px cut at 4 of them.
DEFAULT_FILTER_RADIUS = 2.0


def filter_reach(radius: float) -> int:
    """Pixels at a window's edge whose reconstruction filter (of `radius`) reaches past it: a pixel d whole
    pixels inside the edge has its centre at d + 0.5, so it misses samples when d + 0.5 < radius (gaussian
    r = 2: 2 pixels, tent: 1, box: 0, lanczos r = 3: 3)."""
    return max(0, math.ceil(radius - 0.5))
