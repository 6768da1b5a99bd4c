"""A seam measure: whether an image's error against a reference steps across work-unit borders.

Where both images are unbiased renders of one scene, the error (test - reference, mean over RGB) only
wanders around 0; a compositor or band defect, or a unit rendered biased, makes it jump where one unit
meets the next. `seam_measure` tests the step across each piece of every border and returns a
`SeamMeasure`, whose `seam` says whether there is one (`quekaro diff --units`, `bench accuracy`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from statistics import NormalDist

import numpy as np

from core.errors import QuekaroError
from core.model.geometry import Rect

SEAM_Z = 4.0
SEAM_WIDTH = 3  # pixels on each side of a unit border that the measure compares
PIECE = 8  # pixels along a border per piece: long enough for a variance, short enough to localise
MIN_PIXELS = 6  # fewer pixels in a strip give no usable variance
MAX_LAG = 2  # Mitsuba's gaussian filter reaches 2 pixels: farther neighbours are uncorrelated
MIN_UNIT_PIXELS = 256  # smaller units bias the correlation (by -1/(n-1), their mean taken out): not used
_NORMAL = NormalDist()


@dataclass(frozen=True)
class SeamMeasure:
    """The border pieces' steps summed up. Under noise alone each piece's z^2 is chi-square with one
    degree of freedom, so `ratio` is near 1 and `z`, `unit_z` are standard normal deviates."""

    ratio: float  # the border pieces' mean calibrated z^2; 1 under noise alone
    z: float  # the border pieces' chi-square as a normal deviate
    worst_unit: int  # the unit whose border pieces are least like noise (-1: none)
    unit_z: float  # that unit's chi-square as a normal deviate
    unit_threshold: float  # unit_z at or above this is a seam (Bonferroni over the units)
    correlation: float  # the error's correlation between horizontal neighbours, measured inside units
    border_strips: int  # border pieces tested (a strip on each side)

    @property
    def seam(self) -> bool:
        """About one false alarm in 30,000 images of pure noise, by either test."""
        return self.z >= SEAM_Z or self.unit_z >= self.unit_threshold

    def to_dict(self) -> dict[str, float | int | bool]:
        return {"ratio": self.ratio, "z": self.z, "seam": self.seam, "worst_unit": self.worst_unit,
                "unit_z": self.unit_z, "unit_threshold": self.unit_threshold, "correlation": self.correlation,
                "border_strips": self.border_strips}


def unit_map(rects: Iterable[Rect], width: int, height: int) -> np.ndarray:
    """Each pixel's unit index (int32, -1 where no unit covers it); rects are the units' core rectangles."""
    ids = np.full((height, width), -1, dtype=np.int32)
    for i, r in enumerate(rects):
        if r.x < 0 or r.y < 0 or r.x + r.w > width or r.y + r.h > height:
            raise QuekaroError(f"unit {i} {r.as_list()} lies outside the {width}x{height} image")
        ids[r.y:r.y + r.h, r.x:r.x + r.w] = i
    return ids


def seam_measure(test: np.ndarray, reference: np.ndarray, rects: Iterable[Rect],
                 width: int = SEAM_WIDTH) -> SeamMeasure:
    """The seam measure of `test` against `reference` (H x W x C, RGB first) over the units `rects`;
    `width` is the strip's depth in pixels on each side of a border.

    Each border is cut into pieces of PIECE pixels, with a strip on either side. It tests the step between
    the two strips, not each strip's mean against 0: at a few spp a glossy or caustic region's error is
    skewed (most pixels miss the rare bright paths), so a strip's mean is off 0 even in Mitsuba's own image
    (measured: still-life at 12 spp read as a seam on a 3 x 3 grid in 4 of 4 seeds). Both sides share that
    region, so the step keeps expectation 0. A bias over the whole image is no seam: other metrics report it.
    """
    if test.shape[:2] != reference.shape[:2]:
        raise QuekaroError(f"images differ in size: {test.shape[:2]} vs {reference.shape[:2]}")
    if width < 1:
        raise QuekaroError(f"seam strip width {width}: must be at least 1 pixel")
    rects = list(rects)
    error = (np.asarray(test[..., :3], np.float64) - np.asarray(reference[..., :3], np.float64)).mean(axis=-1)
    ids = unit_map(rects, error.shape[1], error.shape[0])
    rho = _correlation(error, ids)
    steps = [(ua, ub, z) for ua, ub, strip_a, strip_b in _border_pieces(rects, width)
             if (z := _step_z(error[strip_a], error[strip_b], rho)) is not None]
    return _judge(steps, rho.get((0, 1), 0.0), len(rects))


def _judge(steps: list[tuple[int, int, float]], correlation: float, units: int) -> SeamMeasure:
    threshold = -_NORMAL.inv_cdf(_NORMAL.cdf(-SEAM_Z) / max(units, 1))
    if not steps:
        return SeamMeasure(1.0, 0.0, -1, 0.0, threshold, correlation, 0)
    a, b, z = (np.array(column) for column in zip(*steps, strict=True))
    z2 = z * z
    per_unit = {}
    for unit in set(a.tolist()) | set(b.tolist()):
        mine = (a == unit) | (b == unit)
        per_unit[unit] = _chi2_as_z(float(z2[mine].sum()), int(mine.sum()))
    worst = max(per_unit, key=per_unit.__getitem__)
    return SeamMeasure(float(z2.mean()), _chi2_as_z(float(z2.sum()), z2.size), worst, per_unit[worst],
                       threshold, correlation, int(z2.size))


def _step_z(side_a: np.ndarray, side_b: np.ndarray, rho: dict[tuple[int, int], float]) -> float | None:
    """The step between a border piece's two strips (2-D, a's and b's side) as a standard normal deviate;
    None where a strip is too small or neither side's pixels vary (e.g. black background in both images).

    Welch's t (noise differs with brightness and each unit's spp), on effective pixel counts corrected for
    the filter's correlation, turned into a normal deviate by Wallace's approximation (within 0.02 for 10
    or more pixels)."""
    sides = [side_a, side_b]
    if min(side.size for side in sides) < MIN_PIXELS:
        return None
    inflation = [_inflation(side.shape, rho, side.size) for side in sides]
    # With correlated pixels the sample variance reads low: (n - inflation) / (n - 1) of the pixels' variance.
    sigma2 = [float(side.var(ddof=1)) * (side.size - 1) / max(side.size - k, 1.0)
              for side, k in zip(sides, inflation, strict=True)]
    # Each side's mean varies `inflation` times more than independent pixels'. Covariance across the border
    # is left out: it would shrink the variance only where the compositor blends the two sides, and
    # assuming it where it does not (a hard cut) would read noise as a step.
    parts = [s2 * k / side.size for s2, k, side in zip(sigma2, inflation, sides, strict=True)]
    variance = sum(parts)
    if not variance > 0:
        return None
    t = (float(side_a.mean()) - float(side_b.mean())) / math.sqrt(variance)
    # Welch-Satterthwaite over the effective (independent) pixel counts n / inflation.
    effective = [max(side.size / k - 1.0, 1.0) for side, k in zip(sides, inflation, strict=True)]
    nu = max(variance ** 2 / sum(q * q / e for q, e in zip(parts, effective, strict=True) if q > 0), 1.0)
    return math.copysign(math.sqrt(nu * math.log1p(t * t / nu)) * (8 * nu + 1) / (8 * nu + 3), t)


def _inflation(shape: tuple[int, ...], rho: dict[tuple[int, int], float], n: int) -> float:
    """How many times more a mean over an h x w block varies than over n independent pixels."""
    h, w = shape
    pairs = sum(max(h - dy, 0) * max(w - abs(dx), 0) * r for (dy, dx), r in rho.items())
    return max(1.0 + 2.0 * pairs / n, 0.2)


def _correlation(error: np.ndarray, ids: np.ndarray) -> dict[tuple[int, int], float]:
    """The error's correlation at each lag (dy >= 0, half-plane) up to MAX_LAG, between pixels of one unit,
    each unit's error standardised by its own mean and deviation, so a biased unit does not count.

    Pixel filters correlate neighbours, so a strip's mean varies more than its pixels' variance says.
    Units under MIN_UNIT_PIXELS are left out; with none left, pixels count as independent."""
    flat = ids.ravel()
    covered = flat >= 0
    count = np.bincount(flat[covered], minlength=int(ids.max()) + 1).astype(np.float64)
    mean = np.bincount(flat[covered], error.ravel()[covered], minlength=count.size) / np.maximum(count, 1)
    sq = np.bincount(flat[covered], error.ravel()[covered] ** 2, minlength=count.size) / np.maximum(count, 1)
    std = np.where(count >= MIN_UNIT_PIXELS, np.sqrt(np.maximum(sq - mean ** 2, 0.0)), 0.0)
    safe = np.where(ids >= 0, ids, 0)
    r = np.where((ids >= 0) & (std[safe] > 0), (error - mean[safe]) / np.where(std[safe] > 0, std[safe], 1), 0)
    rho = {}
    h, w = error.shape
    for dy in range(MAX_LAG + 1):
        for dx in range(-MAX_LAG, MAX_LAG + 1):
            if (dy, dx) <= (0, 0) or dy >= h or abs(dx) >= w:
                continue
            a = (slice(0, h - dy), slice(max(0, -dx), w - max(0, dx)))
            b = (slice(dy, h), slice(max(0, dx), w - max(0, -dx)))
            same = (ids[a] == ids[b]) & (r[a] != 0)
            rho[(dy, dx)] = float((r[a] * r[b])[same].mean()) if same.any() else 0.0
    return rho


def _chi2_as_z(total: float, dof: int) -> float:
    """A chi-square value with `dof` degrees of freedom as a standard normal deviate (Wilson-Hilferty)."""
    k = 2.0 / (9.0 * dof)
    return ((total / dof) ** (1.0 / 3.0) - (1.0 - k)) / math.sqrt(k)


_Strip = tuple[slice, slice]


def _border_pieces(rects: list[Rect], width: int) -> Iterator[tuple[int, int, _Strip, _Strip]]:
    """(unit a, unit b, a's strip, b's strip) for each piece of every border between two units."""
    for a, ra in enumerate(rects):
        for b, rb in enumerate(rects):
            if rb.x == ra.x + ra.w:  # b lies right of a
                wa, wb = min(width, ra.w), min(width, rb.w)
                for y0, y1 in _pieces(max(ra.y, rb.y), min(ra.y + ra.h, rb.y + rb.h)):
                    rows = slice(y0, y1)
                    yield a, b, (rows, slice(rb.x - wa, rb.x)), (rows, slice(rb.x, rb.x + wb))
            if rb.y == ra.y + ra.h:  # b lies below a
                ha, hb = min(width, ra.h), min(width, rb.h)
                for x0, x1 in _pieces(max(ra.x, rb.x), min(ra.x + ra.w, rb.x + rb.w)):
                    cols = slice(x0, x1)
                    yield a, b, (slice(rb.y - ha, rb.y), cols), (slice(rb.y, rb.y + hb), cols)


def _pieces(lo: int, hi: int) -> Iterator[tuple[int, int]]:
    """[lo, hi) cut into PIECE-long pieces; a last piece shorter than half of one joins the one before."""
    starts = list(range(lo, hi, PIECE))
    if len(starts) > 1 and hi - starts[-1] < PIECE // 2:
        starts.pop()
    for i, s in enumerate(starts):
        yield s, (starts[i + 1] if i + 1 < len(starts) else hi)
