"""Trapezoidal membership functions, vectorised over inputs and over sets.

A trapezoid (a, b, c, d) with a <= b <= c <= d rises from 0 at `a` to 1 at `b`, stays 1 up to `c`
and falls to 0 at `d`. Degenerate shapes are allowed and well defined without any division by zero:
a == b is a vertical left edge (membership 1 from `a` on), c == d a vertical right edge, and
a == b == c == d a singleton (membership 1 at that one point only).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Trapezoid:
    """One fuzzy set: its label and its four vertices."""

    label: str
    a: float
    b: float
    c: float
    d: float

    @property
    def vertices(self) -> tuple[float, float, float, float]:
        return (self.a, self.b, self.c, self.d)


def membership(x: np.ndarray, params: np.ndarray) -> np.ndarray:
    """Membership of every `x` in every set: `x` shaped (n,), `params` (L, 4) -> (n, L).

    Vertical edges take the value of the plateau at the vertex itself (a point exactly at a == b
    has membership 1), so inputs exactly at set boundaries get the membership the set declares.
    """
    return membership_t(x, params).T


def membership_t(x: np.ndarray, params: np.ndarray) -> np.ndarray:
    """`membership` laid out (L, n): sets first, units last (the engine's layout, fast for large n)."""
    x = np.asarray(x, dtype=np.float64)[None, :]
    out = np.empty((len(params), x.shape[1]))
    for i, (a, b, c, d) in enumerate(np.asarray(params, dtype=np.float64)):
        # a vertical edge (a == b or c == d) is a step that includes its vertex
        rise = (x[0] - a) / (b - a) if b > a else np.where(x[0] >= a, 1.0, 0.0)
        fall = (d - x[0]) / (d - c) if d > c else np.where(x[0] <= d, 1.0, 0.0)
        np.clip(np.minimum(rise, fall), 0.0, 1.0, out=out[i])
    return out
