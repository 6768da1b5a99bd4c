"""Partition: split the image into work units of similar estimated cost, with a bounded set of sizes.

`partition(cmap, target_units, sizes)` is the MAgArRO scheme on a fixed grid hierarchy: a unit is a cell of
the global grid of one of `sizes`, clipped to the image, so there are at most 4 * len(sizes) distinct unit
rectangles (whole, right-edge, bottom-edge and corner cells) and Dr.Jit's kernel cache stays warm.
`units_from_rects` gives units their C, S, Nd and neighbours; `equal_tiles` is the naive split.
"""

from __future__ import annotations

import heapq
import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from core.errors import QuekaroError
from core.model.geometry import Rect
from core.model.units import WorkUnit
from planning.complexity import ComplexityMap

DEFAULT_SIZES = (32, 64, 128)  # no 16 px units: each render call costs ~0.05 s, ~20 spp of a 40 px unit
# After reaching the unit count, still split units costing this many target costs. 2.5, not 2: with the
# finer noise map of the pre-pass (planning/complexity.py), at 2 the 512 px scaling scene's 8-agent job was
# cut into 40 units instead of 34, each paying its bands (simulated efficiency 0.895 against 0.904); the
# allocation (`quekaro bench allocation`) is the same within its noise (S 0.624 against 0.625).
HALVE_FACTOR = 2.5
VARIATION = 1.0  # a cell whose complexity std exceeds this many image-mean complexities splits early
WORK_WEIGHTED = True  # balance units by rays x relative noise (the samples the rules will give), not rays
MERGE_TOLERANCE = 0.25  # merge cheap siblings whose mean complexities differ by less than this (relative)


class PartitionError(QuekaroError):
    """Partition arguments a user can get wrong (unit sizes, unit count)."""


class _Stats:
    """Summed-area tables of cost, complexity and complexity squared: O(1) sums over any rectangle.

    Complexity here is the per-pixel relative std per sample (absolute without the map's mean)."""

    def __init__(self, cmap: ComplexityMap) -> None:
        c = np.sqrt(cmap.relative_noise())
        self.relative = cmap.mean is not None
        self.mean_c = float(c.mean())
        # Work: rays per sample times the samples the rules will give the pixel, which grow with its
        # relative noise (see units_from_rects); without a mean, just the rays.
        work = cmap.cost * c / max(self.mean_c, 1e-12) if self.relative and WORK_WEIGHTED else cmap.cost
        self.tables = [self._table(a) for a in (cmap.cost, c, c * c, work)]

    @staticmethod
    def _table(a: np.ndarray) -> np.ndarray:
        t = np.zeros((a.shape[0] + 1, a.shape[1] + 1), dtype=np.float64)
        t[1:, 1:] = a.cumsum(axis=0).cumsum(axis=1)
        return t

    def sums(self, r: Rect) -> tuple[float, float, float]:
        return tuple(  # type: ignore[return-value]
            float(t[r.y1, r.x1] - t[r.y, r.x1] - t[r.y1, r.x] + t[r.y, r.x]) for t in self.tables
        )

    def cost(self, r: Rect) -> float:
        return self.sums(r)[0]

    def work(self, r: Rect) -> float:
        return self.sums(r)[3]

    def complexity(self, r: Rect) -> tuple[float, float]:
        """Mean and standard deviation of the per-pixel complexity over r."""
        _, s, s2, _ = self.sums(r)
        mean = s / r.area
        return mean, math.sqrt(max(s2 / r.area - mean * mean, 0.0))


def check_sizes(sizes: Sequence[int]) -> tuple[int, ...]:
    """Sorted unit sides; each must be a positive integer and a multiple of the next smaller one."""
    try:
        out = tuple(sorted({int(s) for s in sizes}))
    except (TypeError, ValueError) as exc:
        raise PartitionError(f"unit sizes must be integers, got {sizes!r}") from exc
    if not out or out[0] < 1:
        raise PartitionError(f"unit sizes must be a non-empty set of positive integers, got {sizes!r}")
    for small, big in itertools.pairwise(out):
        if big % small:
            raise PartitionError(f"unit size {big} is not a multiple of {small} (sizes {out})")
    return out


def _grid(r: Rect, side: int) -> list[Rect]:
    """Cells of the global `side` grid that meet r, clipped to r (r is aligned to that grid)."""
    return [Rect(x, y, min(side, r.x1 - x), min(side, r.y1 - y))
            for y in range(r.y, r.y1, side) for x in range(r.x, r.x1, side)]


def _alike(rects: list[Rect], stats: _Stats) -> bool:
    means = [stats.complexity(r)[0] for r in rects]
    return max(means) - min(means) <= MERGE_TOLERANCE * max(stats.mean_c, 1e-12)


@dataclass
class _Node:
    rect: Rect
    level: int
    parent: int | None
    children: list[int] = field(default_factory=list)


class _Tree:
    """The split/merge state: grid cells as nodes, the current units as leaves."""

    def __init__(self, width: int, height: int, sizes: tuple[int, ...], stats: _Stats) -> None:
        self.sizes, self.stats = sizes, stats
        self.nodes: list[_Node] = []
        self.leaves: set[int] = set()
        self.heap: list[tuple[float, int]] = []  # (-priority, node) of splittable leaves
        for cell in _grid(Rect(0, 0, width, height), sizes[-1]):
            self._add(_Node(cell, len(sizes) - 1, None))

    def _add(self, node: _Node) -> int:
        i = len(self.nodes)
        self.nodes.append(node)
        self.leaves.add(i)
        finer = self.sizes[node.level - 1] if node.level > 0 else 0
        if node.level > 0 and (node.rect.w > finer or node.rect.h > finer):
            heapq.heappush(self.heap, (-self._priority(node.rect), i))
        return i

    def _priority(self, r: Rect) -> float:
        # A cell whose complexity varies strongly is split as if it cost twice as much (MAgArRO's std test).
        varied = self.stats.complexity(r)[1] > VARIATION * max(self.stats.mean_c, 1e-12)
        return self.stats.work(r) * (2.0 if varied else 1.0)

    def top_cost(self) -> float:
        return self.stats.work(self.nodes[self.heap[0][1]].rect) if self.heap else 0.0

    def split_top(self) -> None:
        _, i = heapq.heappop(self.heap)
        node = self.nodes[i]
        self.leaves.discard(i)
        for cell in _grid(node.rect, self.sizes[node.level - 1]):
            node.children.append(self._add(_Node(cell, node.level - 1, i)))

    def mean_cost(self) -> float:
        return sum(self.stats.work(self.nodes[i].rect) for i in self.leaves) / len(self.leaves)

    def merge_cheap(self) -> None:
        """Merge back siblings that are all whole, together no costlier than the mean unit, and alike."""
        mean = self.mean_cost()
        for i in range(len(self.nodes) - 1, -1, -1):  # children come after parents: deepest first
            node = self.nodes[i]
            if not node.children or not all(c in self.leaves for c in node.children):
                continue
            rects = [self.nodes[c].rect for c in node.children]
            if self.stats.work(node.rect) <= mean and _alike(rects, self.stats):
                self.leaves.difference_update(node.children)
                self.leaves.add(i)

    def rects(self) -> list[Rect]:
        return sorted((self.nodes[i].rect for i in self.leaves), key=lambda r: (r.y, r.x))


def partition(
    cmap: ComplexityMap, target_units: int = 16, sizes: Sequence[int] = DEFAULT_SIZES
) -> list[WorkUnit]:
    """Units of similar estimated cost covering the image exactly once, with sides drawn from `sizes`.

    A unit's cost here is its work: rays per sample times each pixel's relative noise over the image's mean
    (rays alone without the map's mean), since at an optimised level the rules give noisy pixels more
    samples: a scene's noisy corner splits into small units, its quiet wall stays in big ones. Starting from
    the coarsest grid, the costliest unit is split into the cells of the next finer grid first (one whose
    complexity varies strongly counts double) until there are `target_units` (fewer when the grid allows no
    more); units still costing over HALVE_FACTOR times total / target_units are then halved (up to twice
    that count), and cheap alike siblings merged back, so the final count is near, not exactly,
    `target_units`. The coarsest grid's cells are never merged, so there are at least that many units.
    """
    if target_units < 1:
        raise PartitionError(f"target_units must be at least 1, got {target_units}")
    stats = _Stats(cmap)
    tree = _Tree(cmap.width, cmap.height, check_sizes(sizes), stats)
    while tree.heap and len(tree.leaves) < target_units:
        tree.split_top()
    target_cost = tree.stats.work(Rect(0, 0, cmap.width, cmap.height)) / target_units
    while tree.heap and len(tree.leaves) < 2 * target_units:
        if tree.top_cost() <= HALVE_FACTOR * target_cost:
            break
        tree.split_top()
    tree.merge_cheap()
    return units_from_rects(cmap, tree.rects(), stats)


def units_from_rects(cmap: ComplexityMap, rects: Sequence[Rect], stats: _Stats | None = None) -> list[WorkUnit]:
    """Units for the given rectangles (which must tile the image): C, S, Nd, cost and neighbours.

    C is the unit's mean per-pixel *relative* std per sample, sqrt(noise / (mean^2 + 0.01)) from the
    pre-pass: at a given spp a unit's relative MSE (the benchmark's error) is C^2 / spp, so C says
    where samples buy the most error (at a fixed time a unit's spp should grow with it: Neyman
    allocation). It correlates 0.57-0.73 with the measured relative noise of caustic-corner's units,
    and allocating by it reaches 0.77x the uniform error where rays per sample (the former C) reaches
    0.93x. The mean of the per-pixel std, not the rms, so that one firefly of the few-sample pre-pass
    does not make a unit complex. Without the map's mean (old callers), C is the rays per sample.
    Nd is the largest |C - C_neighbour|, S the area. `stats`: the map's tables, when the caller has them.
    """
    stats = stats or _Stats(cmap)
    labels = label_image(rects, cmap.width, cmap.height)
    neighbours = _neighbours(labels, len(rects))
    per_sample = (lambda r: stats.complexity(r)[0]) if stats.relative else (lambda r: stats.cost(r) / r.area)
    cs = [per_sample(r) for r in rects]
    units = []
    for i, r in enumerate(rects):
        nd = max((abs(cs[i] - cs[j]) for j in neighbours[i]), default=0.0)
        units.append(WorkUnit(index=i, rect=r, C=cs[i], S=r.area, Nd=nd, cost=stats.cost(r),
                          neighbours=tuple(sorted(neighbours[i]))))
    return units


def label_image(rects: Sequence[Rect], width: int, height: int) -> np.ndarray:
    """(height, width) array of the index of the rectangle covering each pixel.

    Raises PartitionError when a pixel is covered twice or not at all, or a rectangle leaves the image.
    """
    labels = np.full((height, width), -1, dtype=np.int64)
    for i, r in enumerate(rects):
        if r.x < 0 or r.y < 0 or r.x1 > width or r.y1 > height or r.area == 0:
            raise PartitionError(f"unit {i} {r.as_list()} is empty or outside the {width}x{height} image")
        if np.any(labels[r.slices()] >= 0):
            raise PartitionError(f"unit {i} {r.as_list()} overlaps another unit")
        labels[r.slices()] = i
    if np.any(labels < 0):
        y, x = np.argwhere(labels < 0)[0]
        raise PartitionError(f"pixel x={x}, y={y} is in no unit")
    return labels


def _neighbours(labels: np.ndarray, n: int) -> list[set[int]]:
    """Units sharing a border of positive length: label pairs across horizontal and vertical edges."""
    pairs = [np.stack([labels[:, :-1].ravel(), labels[:, 1:].ravel()], axis=1),
             np.stack([labels[:-1, :].ravel(), labels[1:, :].ravel()], axis=1)]
    both = np.concatenate(pairs)
    both = np.unique(both[both[:, 0] != both[:, 1]], axis=0)
    out: list[set[int]] = [set() for _ in range(n)]
    for a, b in both:
        out[int(a)].add(int(b))
        out[int(b)].add(int(a))
    return out


def equal_tiles(width: int, height: int, n: int) -> list[Rect]:
    """Exactly min(n, width x height) tiles of near-equal area covering the image: a grid whose tiles are at
    most 2:1 where n factors so, else rows of near-square tiles whose row heights follow their tile counts.
    Exactly n, not "about n": a farm asks for a multiple of its agents, and 9 equal units on 2 agents end
    with one agent idle for a unit's time (measured: cbox, 2 agents, level off, 9 units ended 1 s after the
    other agent)."""
    if n < 1 or width < 1 or height < 1:
        raise PartitionError(f"equal_tiles needs positive width, height and n, got {width}, {height}, {n}")
    n = min(n, width * height)
    rows = _grid_rows(width, height, n)
    if rows is not None:
        return _rows_of(width, height, [n // rows] * rows)
    rows = min(max(round(math.sqrt(n * height / width)), -(-n // width), 1), n, height)
    counts = [n // rows + (i < n % rows) for i in range(rows)]
    return _rows_of(width, height, counts)


def _grid_rows(width: int, height: int, n: int) -> int | None:
    """The row count of the rows x cols = n grid whose tiles are closest to square, if within 2:1."""
    best: tuple[float, int] | None = None
    for rows in range(1, n + 1):
        if n % rows or rows > height or n // rows > width:
            continue
        skew = abs(math.log((width / (n // rows)) / (height / rows)))
        if skew <= math.log(2.0) + 1e-12 and (best is None or skew < best[0]):
            best = (skew, rows)
    return None if best is None else best[1]


def _rows_of(width: int, height: int, counts: list[int]) -> list[Rect]:
    """Rows holding counts[i] tiles each, a row's height in proportion to its count (at least 1 px)."""
    total = sum(counts)
    ys = [0]
    for i in range(len(counts)):
        ideal = round(height * sum(counts[: i + 1]) / total)
        ys.append(min(max(ideal, ys[-1] + 1), height - (len(counts) - 1 - i)))
    rects = []
    for row, k in enumerate(counts):
        xs = [round(i * width / k) for i in range(k + 1)]
        rects += [Rect(xs[i], ys[row], xs[i + 1] - xs[i], ys[row + 1] - ys[row]) for i in range(k)]
    return rects


def distinct_sizes(units: Sequence[WorkUnit] | Sequence[Rect]) -> set[tuple[int, int]]:
    """The distinct (w, h) of the units' rectangles: each costs a kernel compilation once."""
    return {(r.w, r.h) for r in (u.rect if isinstance(u, WorkUnit) else u for u in units)}
