"""Is an image statistically the render plain Mitsuba makes of the same file? The one helper for it.

Plain Mitsuba renders the scene K times (K seeds, same variant, spp and sensor): per pixel channel, the
mean m and the variance v of one render. The image under test (one render, or several) is compared per
pixel channel as Mitsuba's own render tests compare theirs, by a test on the means that uses both sides'
variances: t = (mean_test - m) / sqrt(v_test / n_test + v / K), with v_test = v where the test side has
a single render (under the hypothesis both come from the same distribution), against Student's t with K
- 1 degrees of freedom (the variance is estimated from K renders). The standard error has a floor of
FLOAT_TOLERANCE of the value: float32 rounding of the blend (a constant 1.0 composes to 0.9999998) is
not a difference. The significance is Sidak-corrected over all pixel channels: alpha_px = 1 - (1 -
alpha)^(1/N). Pixel channels whose reference variance is 0 must agree to 1e-4 (relative). Where both
sides are read from files of a lower precision (`file_quantum`: float16, Mitsuba's default, or RGBE's
shared exponent), one step of that precision is added to both tolerances: the same value a float32
rounding apart can round to neighbouring steps. Beside the
means, the variance: the median over pixel channels of (x - m)^2 / (v (1 + 1/K)) must be within
VARIANCE_BOUNDS of its median for an independent render of the same noise (the median of F(1, K - 1); a
median, so that a rare firefly does not move it): an image rendered with half the samples, or with extra
noise, fails it even when no single pixel does. It needs VARIANCE_MIN_CHANNELS pixel channels: the
median of a few is too noisy for those bounds (a one-pixel radiance meter's three channels, rendered as
Mitsuba renders them, fell outside them on the farm), and there the verdict says it was not tested.
ALPHA is per comparison (the suite makes ~30 a run). A pixel's values are far from normal where a rare
path carries much light (a firefly): the t-test does not model that tail, so up to FIREFLY_CLUSTERS
fireflies pass. A firefly is a clump of touching significant pixels within FIREFLY_EXTENT pixels a side:
the film's filter spreads one bright sample over its footprint (Mitsuba's default gaussian 4 px, Lanczos
6), so a single rare path can make 3 touching pixels significant. Measured on the suite (Mitsuba against
Mitsuba, 200 new seeds per scene): the most firefly-prone scene (a uint32 film) made 0.28 clumps per
render; if clumps come as a Poisson count, more than 3 has a chance of 2e-4 per comparison, near ALPHA,
and more than 2 of 3e-3. The same tail where the reference never saw the rare path (its variance 0: an alpha that a ray
escaping past a wall's edge lowers once in a few hundred renders) counts toward them too. Every defect met
so far moves hundreds or thousands of pixel channels, or a line along a unit border (a tiled particle
tracer 2475 pixel channels, another integrator 2369, a noiseless AOV 16, a quarter of the samples fails
the variance test).

False failures: measured by `python tests/render_check.py` (plain Mitsuba against plain Mitsuba, other
seeds, every scene of the compatibility suite): FALSE_FAILURES below.
"""

from __future__ import annotations

import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import stats

ALPHA = 1e-4  # per comparison; the suite makes ~30 of them per run
REFERENCE_RENDERS = 32
VARIANCE_BOUNDS = (0.6, 1.6)
VARIANCE_MIN_CHANNELS = 300
FLOAT_TOLERANCE = 1e-5
FIREFLY_CLUSTERS = 3  # clumps of significant pixels tolerated as fireflies (see the module docstring)
FIREFLY_EXTENT = 6  # the widest clump a firefly makes, in pixels a side (Lanczos' footprint: 2 x 3 lobes)
# Written from the last run of `python tests/render_check.py` (see __main__ below).
FALSE_FAILURES = "0 of 7000 (200 trials on each of 35 scenes: Mitsuba's files against Mitsuba's files, new seeds)"


@dataclass
class Verdict:
    """The outcome of one comparison, with what a failure report needs."""

    passed: bool
    failing: int  # pixel channels whose means differ significantly; -1: the shapes differ
    tested: int
    worst_p: float
    variance_ratio: float
    detail: str
    pixels: int = 0  # pixels with at least one significant channel
    clumps: tuple[int, ...] = ()  # the side (pixels) of each clump of touching significant pixels

    @property
    def only_fireflies(self) -> bool:
        """Whether the significant pixels are at most FIREFLY_CLUSTERS clumps a firefly can make: the means'
        verdict, without the variance's (images averaged over jobs have another variance)."""
        return self.failing >= 0 and _fireflies(self.clumps)

    def __str__(self) -> str:
        return (f"{'same' if self.passed else 'DIFFERENT'}: {self.failing} of {self.tested} pixel channels "
                f"significant ({self.pixels} pixels in clumps of side {list(self.clumps)}), smallest p "
                f"{self.worst_p:.3g}, variance ratio {self.variance_ratio:.3f}; {self.detail}")


def _fireflies(sides: tuple[int, ...]) -> bool:
    """Whether clumps of these sides are at most FIREFLY_CLUSTERS that a firefly can make."""
    return len(sides) <= FIREFLY_CLUSTERS and all(side <= FIREFLY_EXTENT for side in sides)


def clumps(significant: np.ndarray) -> tuple[int, ...]:
    """The side of each clump of touching (8-connected) True pixels in an (H, W) mask, largest first: the
    larger of its bounding box's height and width."""
    from scipy import ndimage

    labels, count = ndimage.label(significant, structure=np.ones((3, 3), dtype=bool))
    boxes = ndimage.find_objects(labels, max_label=count)
    return tuple(sorted((max(b[0].stop - b[0].start, b[1].stop - b[1].start) for b in boxes), reverse=True))


def reference_renders(scene: Path, variant: str, spp: int, sensor: int = 0, defines: dict[str, str] | None = None,
                      renders: int = REFERENCE_RENDERS, seed0: int = 10_000,
                      search_paths: tuple[Path, ...] = (), as_file: bool = False) -> tuple[np.ndarray, tuple[str, ...]]:
    """`renders` plain Mitsuba renders of the file (every channel the film writes): (K, H, W, C), names.
    `search_paths` are appended to Mitsuba's file resolver while loading, as its `-a` does. `as_file`: each
    render as the film's file holds it (written and read back), for tests of a job's file; else the film's
    bitmap, for tests of pixels in memory."""
    import mitsuba as mi

    from core.model.job import SceneSpec
    from core.scene.scene import load

    # core.scene.scene.load is mi.load_file with the -a folders appended to Mitsuba's resolver meanwhile.
    loaded = load(SceneSpec(scene, defines or {}, search_paths), variant, threads=2)
    images = []
    names: tuple[str, ...] = ()
    with tempfile.TemporaryDirectory(prefix="quekaro-ref-") as tmp:
        for k in range(renders):
            mi.render(loaded, sensor=sensor, spp=spp, seed=seed0 + k)
            film = loaded.sensors()[sensor].film()
            # The film as Mitsuba writes it (not quekaro's reading of it: its names are the test's).
            bitmap = _written_bitmap(film, Path(tmp) / f"ref{k}") if as_file else film.bitmap()
            names = tuple(bitmap.struct_()[i].name for i in range(bitmap.channel_count()))
            pixels = np.array(bitmap, dtype=np.float64).reshape(*bitmap.size()[::-1], len(names))
            if bitmap.component_format() == mi.Struct.Type.UInt32:
                pixels /= 4294967295.0  # quekaro reads a uint32 file back scaled to [0, 1]
            images.append(pixels.astype(np.float32))
    return np.stack(images), names


def _written_bitmap(film, stem: Path):
    """The film's file as Mitsuba writes it (format, precision, channel names), read back by Mitsuba."""
    import mitsuba as mi

    film.write(str(stem))
    (written,) = stem.parent.glob(f"{stem.name}.*")
    return mi.Bitmap(str(written))


def file_quantum(kind: tuple[str, str], mean: np.ndarray) -> np.ndarray | None:
    """One step of a file's precision at the values `mean` (H, W, C), for `compare`: float16's at each
    value (2^-10 of it, above its subnormals), RGBE's at each pixel's largest channel (2^-7: its 8-bit
    mantissas share that channel's exponent); None for float32 and uint32 files."""
    suffix, component = kind
    if component == "Float16":
        return 2.0**-10 * np.abs(mean) + 2.0**-24
    if suffix == ".rgbe":
        return np.broadcast_to(2.0**-7 * np.abs(mean).max(axis=-1, keepdims=True), mean.shape)
    return None


def file_kind(path: Path) -> tuple[str, str]:
    """An image file's suffix and component format, named as Mitsuba names them (e.g. (".exr", "Float16")).
    An EXR is read by OpenEXR: Mitsuba's own EXR reader hangs at a Dr.Jit thread count of 1 (3.9.1)."""
    import mitsuba as mi
    import OpenEXR

    path = Path(path)
    if OpenEXR.isOpenExrFile(str(path)):
        with OpenEXR.File(str(path), separate_channels=True) as exr:
            kinds = {v.pixels.dtype for v in exr.channels().values()}
        names = {np.dtype(np.float16): "Float16", np.dtype(np.float32): "Float32", np.dtype(np.uint32): "UInt32"}
        return path.suffix, "/".join(sorted(names[k] for k in kinds))
    return path.suffix, mi.Bitmap(str(path)).component_format().name


def mitsuba_file_kind(scene: Path, variant: str, sensor: int = 0, defines: dict[str, str] | None = None,
                      search_paths: tuple[Path, ...] = ()) -> tuple[str, str]:
    """`file_kind` of the file plain Mitsuba writes for the scene's film (rendered at 1 spp)."""
    import mitsuba as mi

    from core.model.job import SceneSpec
    from core.scene.scene import load

    loaded = load(SceneSpec(scene, defines or {}, search_paths), variant, threads=2)
    mi.render(loaded, sensor=sensor, spp=1)
    with tempfile.TemporaryDirectory(prefix="quekaro-kind-") as tmp:
        loaded.sensors()[sensor].film().write(str(Path(tmp) / "image"))
        (written,) = Path(tmp).glob("image.*")
        return file_kind(written)


def by_name(image: np.ndarray, names: tuple[str, ...], order: tuple[str, ...]) -> np.ndarray:
    """The image's channels in `order` (AssertionError naming what is missing)."""
    missing = [c for c in order if c not in names]
    assert not missing, f"channels {missing} missing (image has {list(names)})"
    return np.stack([image[..., names.index(c)] for c in order], axis=-1)


def compare(test: np.ndarray | list[np.ndarray], reference: np.ndarray, alpha: float = ALPHA,
            quantum: np.ndarray | None = None) -> Verdict:
    """Test images (one (H, W, C) image or a list) against K reference renders (K, H, W, C); `quantum`
    (H, W, C): the files' precision step both sides were read at (`file_quantum`), else None."""
    tests = np.stack(test if isinstance(test, list) else [test]).astype(np.float64)
    ref = np.asarray(reference, dtype=np.float64)
    if tests.shape[1:] != ref.shape[1:]:
        return Verdict(False, -1, 0, 0.0, np.nan, f"shape {tests.shape[1:]} != reference {ref.shape[1:]}",
                       pixels=max(1, int(np.prod(tests.shape[1:3]))))  # no pixel is the reference's
    k, n_t = ref.shape[0], tests.shape[0]
    m, v = ref.mean(axis=0), ref.var(axis=0, ddof=1)
    mt = tests.mean(axis=0)
    vt = tests.var(axis=0, ddof=1) if n_t > 1 else v
    noisy = v > 0
    step = np.zeros(m.shape) if quantum is None else np.asarray(quantum, dtype=np.float64)
    rounding = FLOAT_TOLERANCE * np.maximum(1.0, np.abs(m[noisy]))
    floor = rounding + step[noisy]
    se = np.sqrt(vt[noisy] / n_t + v[noisy] / k + floor**2)
    t = (mt[noisy] - m[noisy]) / se
    p = 2.0 * stats.t.sf(np.abs(t), df=k - 1)
    n = int(noisy.sum())
    alpha_px = 1.0 - (1.0 - alpha) ** (1.0 / max(n, 1))
    failing = int((p < alpha_px).sum())
    significant = np.zeros(m.shape, dtype=bool)
    significant[noisy] = p < alpha_px
    differs = np.abs(mt[~noisy] - m[~noisy]) > 1e-4 * np.maximum(1.0, np.abs(m[~noisy])) + step[~noisy]
    significant[~noisy] = differs
    per_pixel = significant.any(axis=-1)
    pixels = int(per_pixel.sum())
    exact_bad = int(differs.sum())
    # Only where the noise is well above float rounding: elsewhere the floor, not the noise, sets the scale.
    real = v[noisy] > (100 * rounding + 10 * step[noisy]) ** 2  # a file's step: its noise is step / sqrt(12)
    squared = (tests[0][noisy][real] - m[noisy][real]) ** 2 / (v[noisy][real] * (1 + 1 / k))
    ratio = float(np.median(squared) / stats.f.median(1, k - 1)) if real.any() else 1.0
    var_tested = int(real.sum()) >= VARIANCE_MIN_CHANNELS
    var_ok = VARIANCE_BOUNDS[0] <= ratio <= VARIANCE_BOUNDS[1] or not var_tested
    where = "" if var_tested else f"variance not tested ({int(real.sum())} pixel channels); "
    if failing or exact_bad:
        idx = np.argwhere(noisy)[np.argmin(p)] if failing else np.argwhere(~noisy)[0]
        where += f"worst at (y, x, channel) {tuple(int(i) for i in idx)}; "
    detail = f"{where}{exact_bad} noiseless channels differ; Sidak alpha per channel {alpha_px:.2g}"
    sides = clumps(per_pixel)
    return Verdict(_fireflies(sides) and var_ok, failing + exact_bad, n, float(p.min()) if n else 1.0, ratio,
                   detail, pixels, sides)


def moment_channels(image: np.ndarray, names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """(mean, per-sample variance) of a render by Mitsuba's `moment` integrator, from its channels."""
    second = [i for i, n in enumerate(names) if n.startswith("m2_")]
    first = [names.index(names[i][3:]) for i in second]
    mean = image[..., first].astype(np.float64)
    return mean, np.maximum(image[..., second].astype(np.float64) - mean**2, 0.0)


def compare_moment_renders(a: tuple[np.ndarray, np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray, np.ndarray],
                           alpha: float = ALPHA) -> Verdict:
    """Two single renders of one job, each (mean, per-sample variance, samples per pixel) from the moment
    integrator: a per-pixel Z-test of the means, (ma - mb) / sqrt(va / na + vb / nb), Sidak-corrected, with
    the same float floor and firefly allowance as `compare`. For renders whose spp differs per pixel (an
    optimisation level), na and nb are each pixel's least spp among the tiles covering it (conservative)."""
    (ma, va, na), (mb, vb, nb) = a, b
    var = va / na[..., None] + vb / nb[..., None] + (FLOAT_TOLERANCE * np.maximum(1.0, np.abs(mb))) ** 2
    z = np.abs(ma - mb) / np.sqrt(var)
    p = 2.0 * stats.norm.sf(z)
    alpha_px = 1.0 - (1.0 - alpha) ** (1.0 / p.size)
    significant = p < alpha_px
    per_pixel = significant.any(axis=-1)
    detail = f"Sidak alpha per channel {alpha_px:.2g}"
    if per_pixel.any():
        detail = f"worst at (y, x, channel) {tuple(int(i) for i in np.unravel_index(np.argmin(p), p.shape))}; " + detail
    sides = clumps(per_pixel)
    return Verdict(_fireflies(sides), int(significant.sum()), p.size, float(p.min()), 1.0, detail,
                   int(per_pixel.sum()), sides)


def least_spp(report: dict) -> np.ndarray:
    """Each pixel's least spp among the tiles covering it (unit grown by its band), from a job report."""
    height, width = report["image"]["height"], report["image"]["width"]
    spp = np.full((height, width), np.inf)
    for unit in report["units"]:
        x, y, w, h = unit["rect"]
        band = unit.get("band") or 0
        ys, xs = slice(max(0, y - band), min(height, y + h + band)), slice(max(0, x - band), min(width, x + w + band))
        spp[ys, xs] = np.minimum(spp[ys, xs], unit["spp"])
    return spp


def _measure_false_failures(trials: int = 200) -> str:
    """Mitsuba against Mitsuba (other seeds) on every compatibility scene, both read from the film's file
    at its precision as the suite compares a job's file: how often `compare` fails."""
    from compat_cases import CASES, SCENES

    fails, total = 0, 0
    for case in CASES:
        search = tuple(SCENES / f for f in case.search)
        ref, _ = reference_renders(case.scene, case.variant, case.spp, case.sensor, case.defines,
                                   search_paths=search, as_file=True)
        kind = mitsuba_file_kind(case.scene, case.variant, case.sensor, case.defines, search)
        for trial in range(trials):
            other, _ = reference_renders(case.scene, case.variant, case.spp, case.sensor, case.defines, renders=1,
                                         seed0=90_000 + trial, search_paths=search, as_file=True)
            verdict = compare(other[0], ref, quantum=file_quantum(kind, ref.mean(axis=0)))
            fails += not verdict.passed
            total += 1
            if not verdict.passed:
                print(f"{case.name} trial {trial}: {verdict}", file=sys.stderr)
    return (f"{fails} of {total} ({trials} trials on each of {len(CASES)} scenes: Mitsuba's files against "
            "Mitsuba's files)")


if __name__ == "__main__":
    print(_measure_false_failures())
