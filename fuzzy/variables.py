"""Input and output linguistic variables, including inputs whose sets are built at run time.

A static variable has its trapezoids and universe written in the rule file. A dynamic input (the paper's
C, S and Nd) only names its labels: `InputVariable.resolve` spreads its sets over the range observed in
the scene (`spread_sets`, `widen_degenerate`). `masyro_sets` builds MASYRO's per-job sets instead.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fuzzy.errors import FuzzyInputError
from fuzzy.terms import Trapezoid

# Relative width under which an observed range counts as degenerate (min == max up to rounding).
_DEGENERATE_REL = 1e-12
# Largest |value| a set vertex, universe, default or observed range may have. The exact centroid sums
# cubic terms of the vertices, and a set's width is a difference: far below this, neither overflows (near
# 1e154 the centroid's terms become inf, which would read as "no rule fired"). A unit's features stay
# below 1e12 (core.model), S below 2^32.
MAGNITUDE_MAX = 1e30


def spread_sets(n_labels: int, lo: float, hi: float) -> np.ndarray:
    """Vertices (n_labels, 4) of labels spread linearly over [lo, hi]: centres lo + i (hi - lo) / (n - 1),
    each label a triangle from the previous centre to the next, shoulders at both ends. The sets form a
    partition of unity: every input in range has memberships summing to 1, so it fires some label."""
    if n_labels == 1:
        return np.array([[lo, lo, hi, hi]], dtype=np.float64)
    centres = np.linspace(lo, hi, n_labels)
    left = np.concatenate(([lo], centres[:-1]))
    right = np.concatenate((centres[1:], [hi]))
    params = np.stack([left, centres, centres, right], axis=1)
    params[0, 0] = params[0, 1] = lo  # left shoulder
    params[-1, 2] = params[-1, 3] = hi  # right shoulder
    return params


def widen_degenerate(lo: float, hi: float) -> tuple[float, float]:
    """The range actually used for spreading: [lo, hi], or a symmetric widening when hi == lo (every unit
    alike), so that the common value sits in the middle ("normal" for the scene): membership 1 in the
    middle label for an odd number of labels, 0.5 in each of the two middle ones for an even number."""
    scale = max(1.0, abs(lo), abs(hi))
    if hi - lo > _DEGENERATE_REL * scale:
        return lo, hi
    half = 0.5 * max(1.0, abs(lo))
    return lo - half, lo + half


def checked_range(name: str, observed: tuple[float, float]) -> tuple[float, float]:
    """An observed (lo, hi) of input `name` as floats, refused where it is no range the sets can span."""
    lo, hi = (float(v) for v in observed)
    if not (abs(lo) <= MAGNITUDE_MAX and abs(hi) <= MAGNITUDE_MAX):
        raise FuzzyInputError(f"observed range of {name!r} is not finite or beyond +-{MAGNITUDE_MAX:g}: ({lo}, {hi})")
    if hi < lo:
        raise FuzzyInputError(f"observed range of {name!r} has max {hi} < min {lo}")
    return lo, hi


def masyro_sets(n_labels: int, lo: float, hi: float) -> np.ndarray:
    """MASYRO's per-job sets over the observed [lo, hi]: I = (hi - lo) / (n + 1), padded by `pad` on both
    sides (MASYRO adds 1 on a complexity scale spanning ~48 in its file: 1/48 of the range here), with
    shoulders at both ends and plateaus of one I in the middle label (its published file fits this). MASYRO's
    agent rebuilt its sets so for each job; the planner does so for C, Nd and S."""
    pad = (hi - lo) / 48.0
    step = (hi - lo) / (n_labels + 1)
    m, big = lo - pad, hi + pad
    if n_labels == 5:
        rows = [(m, m, m + step, m + 2 * step), (m + step, m + 2 * step, m + 2 * step, m + 3 * step),
                (m + 2 * step, m + 3 * step, big - 3 * step, big - 2 * step),
                (big - 3 * step, big - 2 * step, big - 2 * step, big - step), (big - 2 * step, big - step, big, big)]
    elif n_labels == 3:
        rows = [(m, m, m + step, m + 2 * step), (m + step, m + 2 * step, big - 2 * step, big - step),
                (big - 2 * step, big - step, big, big)]
    else:
        raise FuzzyInputError(f"MASYRO's per-job sets exist for 3 or 5 labels, not {n_labels}")
    return np.array(rows, dtype=np.float64)


@dataclass(frozen=True)
class InputVariable:
    """An input: static (sets and universe from the file) or dynamic (labels only). Inputs are clamped to
    the universe (or observed range), so a unit just outside it counts as one at its edge rather than
    firing nothing; `clamp` False gives membership 0 outside every set (MASYRO's meaning)."""

    name: str
    labels: tuple[str, ...]
    dynamic: bool
    sets: tuple[Trapezoid, ...] = ()
    universe: tuple[float, float] | None = None
    clamp: bool = True

    def resolve(self, observed: tuple[float, float] | None) -> tuple[np.ndarray, tuple[float, float]]:
        """The (L, 4) vertices and the clamping interval to use for one evaluation.

        `observed` is the scene's (lo, hi) for a dynamic variable and is ignored for a static one.
        """
        if not self.dynamic:
            params = np.array([s.vertices for s in self.sets], dtype=np.float64)
            return params, self.universe  # type: ignore[return-value]
        if observed is None:
            raise FuzzyInputError(f"input variable {self.name!r} is dynamic and needs an observed range")
        wlo, whi = widen_degenerate(*checked_range(self.name, observed))
        return spread_sets(len(self.labels), wlo, whi), (wlo, whi)


@dataclass(frozen=True)
class OutputVariable:
    """An output: its sets, its universe and the value it takes when no rule fires (None, MASYRO's dialect:
    no value, NaN, and the planner keeps the user's value)."""

    name: str
    sets: tuple[Trapezoid, ...]
    universe: tuple[float, float]
    default: float | None

    @property
    def labels(self) -> tuple[str, ...]:
        return tuple(s.label for s in self.sets)

    @property
    def params(self) -> np.ndarray:
        return np.array([s.vertices for s in self.sets], dtype=np.float64)
