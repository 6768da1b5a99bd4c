"""Defuzzifiers, vectorised over units: the exact centroid of the aggregate, and MASYRO's centre of sums.

Both take the activation of every output label per unit, `h` shaped (n, L) with values in [0, 1]
(each label's trapezoid is clipped at its activation: Mamdani min implication), and return (n,) crisp
values, NaN where the aggregate has no area *and* no label fired (the engine then uses the default).
Entry points: `plan_centroid` and `centroid` (exact, no sampling), `centre_of_sums`.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from fuzzy.terms import membership


@dataclass(frozen=True)
class CentroidPlan:
    """The fixed geometry of one output variable, precomputed for the exact centroid."""

    x0: np.ndarray  # (J,) interval starts
    x1: np.ndarray  # (J,) interval ends
    slot_set: np.ndarray  # (J, K) label index of each active piece; L (a zero dummy) for padding
    slot_v0: np.ndarray  # (J, K) the piece's value at x0 (its one-sided limit inside the interval)
    slot_slope: np.ndarray  # (J, K)
    slot_inv: np.ndarray  # (J, K) 1 / slope, 0 for flat pieces (their crossings collapse onto x0)
    midpoints: np.ndarray  # (L,) (b + c) / 2, for the zero-area fallback


def _edge_lines(params: np.ndarray) -> list[tuple[float, float, float, float]]:
    """Sloped edges as (x_start, x_end, y_start, y_end)."""
    lines = []
    for a, b, c, d in params:
        if b > a:
            lines.append((a, b, 0.0, 1.0))
        if d > c:
            lines.append((c, d, 1.0, 0.0))
    return lines


def _edge_crossings(params: np.ndarray) -> list[float]:
    lines = _edge_lines(params)
    xs = []
    for i, (p0, p1, u0, u1) in enumerate(lines):
        for q0, q1, w0, w1 in lines[i + 1 :]:
            lo, hi = max(p0, q0), min(p1, q1)
            if lo >= hi:
                continue
            s1 = (u1 - u0) / (p1 - p0)
            s2 = (w1 - w0) / (q1 - q0)
            if s1 == s2:
                continue
            # u0 + s1 (x - p0) = w0 + s2 (x - q0)
            x = (w0 - s2 * q0 - u0 + s1 * p0) / (s1 - s2)
            if lo < x < hi:
                xs.append(float(x))
    return xs


def _piece(params_row: np.ndarray, x0: float, x1: float) -> tuple[float, float] | None:
    """The straight piece of one set on (x0, x1) as (value at x0, slope), or None where it is zero."""
    a, b, c, d = params_row
    m = 0.5 * (x0 + x1)
    if m <= a or m >= d:
        return None
    if m < b:
        slope = 1.0 / (b - a)
        return (x0 - a) * slope, slope
    if m <= c:
        return 1.0, 0.0
    slope = -1.0 / (d - c)
    return (d - x0) / (d - c), slope


def plan_centroid(params: np.ndarray) -> CentroidPlan:
    """Fixed intervals and their active pieces for sets `params` (L, 4), found once per output variable.

    The aggregate mu(x) = max_l min(h_l, T_l(x)) is piecewise linear. Its fixed kinks are the sets'
    vertices and the points where edges of different sets cross. Between two of them each set is one
    straight piece (zero, rising, plateau or falling), so only the few non-zero ("active") sets matter."""
    params = np.asarray(params, dtype=np.float64)
    n_sets = len(params)
    points = np.unique(np.concatenate([params.ravel(), _edge_crossings(params)]))
    intervals = []
    for x0, x1 in itertools.pairwise(points):
        if x1 <= x0:
            continue
        pieces = [(i, *p) for i in range(n_sets) if (p := _piece(params[i], x0, x1)) is not None]
        if pieces:
            intervals.append((x0, x1, pieces))
    k = max((len(p) for _, _, p in intervals), default=1)
    n_int = len(intervals)
    slot_set = np.full((n_int, k), n_sets, dtype=np.intp)
    slot_v0 = np.zeros((n_int, k))
    slot_slope = np.zeros((n_int, k))
    for j, (_, _, pieces) in enumerate(intervals):
        for s, (i, v0, slope) in enumerate(pieces):
            slot_set[j, s], slot_v0[j, s], slot_slope[j, s] = i, v0, slope
    with np.errstate(divide="ignore"):
        slot_inv = np.where(slot_slope != 0.0, 1.0 / np.where(slot_slope != 0.0, slot_slope, 1.0), 0.0)
    return CentroidPlan(
        x0=np.array([iv[0] for iv in intervals]),
        x1=np.array([iv[1] for iv in intervals]),
        slot_set=slot_set,
        slot_v0=slot_v0,
        slot_slope=slot_slope,
        slot_inv=slot_inv,
        midpoints=0.5 * (params[:, 1] + params[:, 2]),
    )


def centroid(plan: CentroidPlan, h: np.ndarray) -> np.ndarray:
    """Exact centroid of the union of clipped sets for every unit: `h` (n, L) -> (n,)."""
    return centroid_t(plan, np.asarray(h, dtype=np.float64).T)


def _normal_levels(h: np.ndarray) -> np.ndarray:
    """Clip levels in (0, smallest normal double) raised to it: subnormal levels lose all relative
    precision in the products below, and the two defuzzifiers would disagree (seen at h = 5e-324)."""
    tiny = np.finfo(np.float64).tiny
    return np.where((h > 0.0) & (h < tiny), tiny, h)


def centroid_t(plan: CentroidPlan, h_t: np.ndarray) -> np.ndarray:
    """`centroid` with activations laid out (L, n).

    The moving kinks, where an edge crosses a clip level, are found per interval from its active pieces
    only. Between all kinks mu is linear, so area and first moment follow exactly from its value and slope
    at each piece's midpoint. Vertical edges (a == b, c == d) are fixed points, never a midpoint, so jumps
    are integrated exactly too. No sampling, and no division by a set's width."""
    h_t = _normal_levels(h_t)
    n = h_t.shape[1]
    if plan.x0.size == 0 or n == 0:
        return _fallback(plan.midpoints, h_t, np.zeros(n), np.zeros(n))
    # units on the last axis throughout: numpy's inner loops then run over n, not over 2-5 sets
    ht = np.concatenate([h_t, np.zeros((1, n))], axis=0)
    k = plan.slot_set.shape[1]
    x0 = plan.x0[:, None]
    x1 = plan.x1[:, None]
    levels = [ht[plan.slot_set[:, s]] for s in range(k)]  # each (J, n): clip level of piece s
    # moving kinks: sloped piece s meets the clip level of piece t; kept inside the interval
    cross = []
    for s in range(k):
        v0, inv = plan.slot_v0[:, s, None], plan.slot_inv[:, s, None]
        if not inv.any():
            continue
        cross.extend(_crossing(levels[t], v0, inv, x0, x1) for t in range(k))
    pts = [np.broadcast_to(x0, (len(x0), n)), *_sorted(cross), np.broadcast_to(x1, (len(x0), n))]
    area = np.zeros((len(x0), n))
    moment = np.zeros((len(x0), n))
    for xl, xr in itertools.pairwise(pts):
        # the aggregate is linear on [xl, xr]: integrate it from its value and slope at the midpoint,
        # which stays exact when a kink computed a rounding error away lands on an end point
        dx = xr - xl
        mid = 0.5 * (xl + xr)
        mu, slope = _aggregate_at(plan, levels, mid - x0)
        area += dx * mu
        moment += dx * (mid * mu + slope * dx * dx * (1.0 / 12.0))
    return _fallback(plan.midpoints, h_t, area.sum(axis=0), moment.sum(axis=0))


def _crossing(level: np.ndarray, v0: np.ndarray, inv: np.ndarray, x0: np.ndarray, x1: np.ndarray) -> np.ndarray:
    """Where a sloped piece (value v0 at x0, 1/slope inv) reaches `level`, kept inside [x0, x1]."""
    x = level - v0
    x *= inv
    x += x0
    np.maximum(x, x0, out=x)
    np.minimum(x, x1, out=x)
    return x


def _aggregate_at(
    plan: CentroidPlan, levels: list[np.ndarray], offset: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Value and slope of max over pieces of min(piece, its clip level) at x0 + offset, each (J, n)."""
    mu = slope = None
    for s, level in enumerate(levels):
        piece = plan.slot_slope[:, s, None]
        v = piece * offset
        v += plan.slot_v0[:, s, None]
        below = v < level
        np.minimum(v, level, out=v)  # v is now the clipped value
        piece_slope = np.where(below, piece, 0.0)  # not below * piece: False * inf is NaN
        if mu is None:
            mu, slope = v, piece_slope
            continue
        higher = v > mu
        np.copyto(slope, piece_slope, where=higher)
        np.maximum(mu, v, out=mu)
    return mu, slope


def _sorted(arrays: list[np.ndarray]) -> list[np.ndarray]:
    """Element-wise sort of a few same-shaped arrays (odd-even transposition network; np.sort if many).
    The arrays are reordered in place: pass arrays that nothing else holds."""
    m = len(arrays)
    if m > 9:
        stacked = np.sort(np.stack(arrays), axis=0)
        return list(stacked)
    out = list(arrays)
    for rnd in range(m):
        for i in range(rnd % 2, m - 1, 2):
            lo = np.minimum(out[i], out[i + 1])
            np.maximum(out[i], out[i + 1], out=out[i + 1])
            out[i] = lo
    return out


def centre_of_sums(params: np.ndarray, h: np.ndarray) -> np.ndarray:
    """MASYRO's defuzzifier: area-weighted mean of the clipped sets' own centroids: (n, L) -> (n,)."""
    return centre_of_sums_t(params, np.asarray(h, dtype=np.float64).T)


def centre_of_sums_t(params: np.ndarray, h: np.ndarray) -> np.ndarray:
    """`centre_of_sums` with activations laid out (L, n)."""
    h = _normal_levels(h)
    a, b, c, d = (params[:, i][:, None] for i in range(4))
    p = a + h * (b - a)  # the clipped top runs from p to q
    q = d - h * (d - c)
    left, top, right = 0.5 * h * (p - a), h * (q - p), 0.5 * h * (d - q)
    area = left + top + right
    moment = left * (a + 2 * p) / 3.0 + top * (p + q) * 0.5 + right * (2 * q + d) / 3.0
    return _fallback(0.5 * (params[:, 1] + params[:, 2]), h, area.sum(axis=0), moment.sum(axis=0))


def _fallback(midpoints: np.ndarray, h: np.ndarray, area: np.ndarray, moment: np.ndarray) -> np.ndarray:
    """moment / area; the weighted plateau midpoints where the area is zero (only singleton sets,
    a == b == c == d, fired); NaN where nothing fired.

    `h` is laid out (L, n).
    """
    out = np.full(h.shape[1], np.nan)
    has_area = area > 0.0
    out[has_area] = moment[has_area] / area[has_area]
    if has_area.all():
        return out
    hsum = h.sum(axis=0)
    singular = ~has_area & (hsum > 0.0)
    if singular.any():
        out[singular] = (h[:, singular] * midpoints[:, None]).sum(axis=0) / hsum[singular]
    return out


def aggregate(params: np.ndarray, h: np.ndarray, x: np.ndarray) -> np.ndarray:
    """mu(x) for one unit (`h` shaped (L,)) on points `x`: the reference for numerical checks."""
    return np.minimum(membership(x, params), np.asarray(h)[None, :]).max(axis=1)


def numeric_centroid(params: np.ndarray, h: np.ndarray, points: int = 1_000_000) -> float:
    """Centroid of one unit's aggregate by the trapezoid rule on `points` samples (a check, not for use)."""
    x = np.linspace(params[:, 0].min(), params[:, 3].max(), points)
    y = aggregate(params, h, x)
    dx = np.diff(x)
    area = float((dx * (y[1:] + y[:-1])).sum() * 0.5)
    moment = float((dx * (x[1:] * y[1:] + x[:-1] * y[:-1])).sum() * 0.5)
    return moment / area if area > 0 else float("nan")
