"""The per-pixel sample-count render (core.render.adaptive) against plain Mitsuba rendering the same file:
the same image statistically at uniform counts (means and variance), the same means with counts that
vary per pixel (and the variance each pixel's count predicts), and refusals that say why."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from render_check import VARIANCE_BOUNDS, by_name, compare, reference_renders
from scipy import ndimage, stats

from core.errors import RenderError
from core.model.job import SceneSpec
from core.render.adaptive import (
    PAYS_BELOW,
    blurred,
    neyman_counts,
    neyman_scale,
    render_adaptive,
    second_pass,
    separable,
)
from core.render.per_pixel import render_counts
from core.scene.scene import load

SCENES = Path(__file__).resolve().parent / "compat" / "scenes"
RGB, SPECTRAL = "llvm_ad_rgb", "llvm_ad_spectral"
SPP = 16
KINDS = [("rgba.xml", RGB), ("aov.xml", RGB), ("spectral_spiky.xml", SPECTRAL), ("medium_homogeneous.xml", RGB)]


def _loaded(name: str, variant: str):
    return load(SceneSpec(SCENES / name, {}, ()), variant, threads=2)


def _window(loaded) -> tuple[int, int]:
    w, h = (int(v) for v in loaded.sensors()[0].film().crop_size())
    return h, w


@pytest.mark.slow
@pytest.mark.parametrize(("name", "variant"), KINDS)
def test_uniform_counts_are_mitsubas_render(name, variant):
    """Every channel the film writes (alpha, AOVs, spectral to RGB, a medium), means and variance."""
    ref, names = reference_renders(SCENES / name, variant, SPP)
    loaded = _loaded(name, variant)
    out = render_counts(loaded, np.full(_window(loaded), SPP), seed=555)
    assert out.channels == names
    verdict = compare(by_name(out.pixels, out.channels, names), ref)
    assert verdict.passed, f"{name}: {verdict}"


@pytest.mark.slow
@pytest.mark.parametrize(("name", "variant"), [KINDS[0], KINDS[2]])
def test_varying_counts_keep_the_means_and_cut_the_variance_as_counted(name, variant):
    """Blocks of 8 px at SPP/2 .. 4 SPP: the means are Mitsuba's at every pixel (several renders against
    32 of Mitsuba's), and inside the blocks (away from the filter's reach into a neighbour) each pixel's
    squared deviation scaled by count / SPP has the median an independent render at SPP has."""
    ref, names = reference_renders(SCENES / name, variant, SPP)
    loaded = _loaded(name, variant)
    h, w = _window(loaded)
    rng = np.random.default_rng(7)
    blocks = rng.choice([SPP // 2, SPP, 2 * SPP, 4 * SPP], size=(-(-h // 8), -(-w // 8)))
    counts = np.kron(blocks, np.ones((8, 8), dtype=np.int64))[:h, :w]
    images = [by_name(render_counts(loaded, counts, seed=900 + k).pixels, names, names) for k in range(6)]
    means = compare(images, ref)
    assert means.failing <= 2, f"{name}: {means}"
    m, v = ref.mean(axis=0), ref.var(axis=0, ddof=1)
    inner = np.zeros((h, w), dtype=bool)
    for y in range(0, h, 8):
        for x in range(0, w, 8):
            inner[y + 2:y + 6, x + 2:x + 6] = True
    real = inner[..., None] & (v > 1e-8)
    scaled = ((images[0] - m) ** 2 * (counts / SPP)[..., None])[real] / (v[real] * (1 + 1 / ref.shape[0]))
    ratio = np.median(scaled) / stats.f.median(1, ref.shape[0] - 1)
    assert VARIANCE_BOUNDS[0] <= ratio <= VARIANCE_BOUNDS[1], f"{name}: variance ratio {ratio:.3f}"


@pytest.mark.slow
def test_two_pass_render_keeps_mitsubas_means_with_less_noise():
    """The adaptive render at SPP on average against 32 of Mitsuba's renders at SPP: the same means (4
    renders), and its median squared deviation below an SPP render's (samples went where the noise is)."""
    ref, names = reference_renders(SCENES / "rgba.xml", RGB, SPP)
    loaded = _loaded("rgba.xml", RGB)
    runs = [render_adaptive(loaded, SPP, seed=40 + 2 * k) for k in range(4)]
    assert all(r.channels == names for r in runs)
    assert abs(runs[0].counts.mean() - SPP) < 0.05 * SPP
    verdict = compare([r.pixels for r in runs], ref)
    assert verdict.failing <= 2, str(verdict)
    m = ref.mean(axis=0)
    ours = np.mean([((r.pixels - m) ** 2).mean() for r in runs])
    theirs = np.mean([((img - m) ** 2).mean() for img in ref[:4]])
    assert ours < theirs, f"adaptive mean squared deviation {ours:.3g} not below uniform's {theirs:.3g}"


def test_counts_must_match_the_window_and_be_whole():
    loaded = _loaded("rgba.xml", RGB)
    h, w = _window(loaded)
    with pytest.raises(RenderError, match="do not match the film window"):
        render_counts(loaded, np.ones((h + 1, w), dtype=np.int64), seed=0)
    with pytest.raises(RenderError, match="non-negative integers"):
        render_counts(loaded, np.full((h, w), 1.5), seed=0)
    with pytest.raises(RenderError, match="non-negative integers"):
        render_counts(loaded, np.full((h, w), -1), seed=0)


def test_zero_counts_give_an_empty_window():
    loaded = _loaded("rgba.xml", RGB)
    out = render_counts(loaded, np.zeros(_window(loaded), dtype=np.int64), seed=0)
    assert not out.pixels.any() and not out.sum.any()
    assert not out.relative_variance().any()


@pytest.mark.parametrize(("xml", "reason"), [
    ('<sampler type="stratified"><integer name="sample_count" value="4"/></sampler>', "independent sampler"),
    ('<sampler type="independent"/><film type="hdrfilm"><integer name="width" value="8"/>'
     '<integer name="height" value="8"/><boolean name="sample_border" value="true"/></film>', "sample_border"),
])
def test_refused_with_the_reason(tmp_path, xml, reason):
    scene = tmp_path / "scene.xml"
    scene.write_text(f'<scene version="3.0.0"><integrator type="path"/><sensor type="perspective">{xml}'
                     '</sensor><shape type="sphere"/><emitter type="constant"/></scene>')
    loaded = load(SceneSpec(scene, {}, ()), RGB, threads=1)
    with pytest.raises(RenderError, match=reason):
        render_counts(loaded, np.ones(_window(loaded), dtype=np.int64), seed=0)


def test_a_particle_tracer_is_refused():
    loaded = _loaded("ptracer.xml", RGB)
    with pytest.raises(RenderError, match="not a sampling integrator"):
        render_counts(loaded, np.ones(_window(loaded), dtype=np.int64), seed=0)


def test_neyman_counts_spend_the_budget_where_the_noise_is():
    rng = np.random.default_rng(0)
    variance = np.array([[0.0, 1.0], [4.0, 16.0]])
    extra = np.mean([neyman_counts(variance, 2, 4 * 40, rng) for _ in range(400)], axis=0)
    totals = 2 + extra
    assert abs(totals.sum() - 160) < 1.0  # the expectation of the stochastic rounding keeps the budget
    assert totals[0, 0] == pytest.approx(2.0)  # a pixel without noise keeps its first pass only
    # the rest in proportion to sqrt(variance): 1 : 2 : 4 over the budget left, 160 - 2
    assert totals[0, 1] / totals[1, 1] == pytest.approx(0.25, rel=0.05)
    assert totals[1, 0] / totals[1, 1] == pytest.approx(0.5, rel=0.05)


def test_neyman_counts_edges():
    rng = np.random.default_rng(1)
    flat = np.zeros((3, 3))
    assert (neyman_counts(flat, 4, 4 * 9, rng) == 0).all()  # the first pass spent the budget
    assert (neyman_counts(flat, 1, 4 * 9, rng) == 3).all()  # no noise anywhere: the rest uniformly
    cost = np.array([[1.0, 4.0]])
    extra = np.mean([neyman_counts(np.ones((1, 2)), 1, 2 * 10, rng, cost) for _ in range(400)], axis=0)
    spent = ((1 + extra) * cost).sum()
    assert spent == pytest.approx(10 * cost.sum(), rel=0.02)  # totals cost what uniform 10 spp would
    assert (1 + extra[0, 0]) / (1 + extra[0, 1]) == pytest.approx(2.0, rel=0.05)  # sqrt(1 / cost)
    with pytest.raises(RenderError, match="cost map"):
        neyman_counts(np.ones((2, 2)), 1, 40, rng, np.ones((1, 2)))


@pytest.mark.parametrize("case", range(12))
def test_neyman_scale_solves_the_budget(case):
    # Against the definition, sum(max(first, lam base) cost) = budget, and a bisection of it: heavy tails,
    # zeros, a single pixel, ties, costs spanning 1e4, budgets just above the first pass and far above it.
    rng = np.random.default_rng(case)
    shape = [(1, 1), (1, 7), (40, 30), (256, 256)][case % 4]
    base = rng.pareto(1.0, size=shape) * (rng.random(shape) < [1.0, 0.5, 0.05][case % 3])
    if not base.any():
        base.flat[0] = 1.0
    if case == 5:
        base = np.round(base)  # many equal values
    cost = 10 ** rng.uniform(-2, 2, size=shape) if case % 2 else np.ones(shape)
    first = int(rng.integers(1, 9))
    budget = first * cost.sum() * [1.0 + 1e-9, 1.5, 40.0][case % 3]
    lam = neyman_scale(base, cost, first, budget)
    spent = lambda s: float((np.maximum(first, s * base) * cost).sum())  # noqa: E731
    assert spent(lam) == pytest.approx(budget, rel=1e-12)
    lo, hi = 0.0, budget / float((base * cost)[base > 0].min())
    while hi - lo > 1e-13 * hi:
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if spent(mid) > budget else (mid, hi)
    assert lam == pytest.approx(lo, rel=1e-9)


@pytest.mark.parametrize("shape", [(64, 48), (1, 1), (3, 40), (40, 2), (17, 1)])
@pytest.mark.parametrize("sigma", [4.0, 0.7, 2.5])
def test_the_blur_is_scipys_gaussian_filter(shape, sigma):
    # Images smaller than the kernel's reach, one pixel, heavy-tailed noise: scipy's result to 1e-12.
    noise = np.random.default_rng(len(shape) + shape[0]).pareto(1.5, size=shape)
    assert np.allclose(blurred(noise, sigma), ndimage.gaussian_filter(noise, sigma, mode="nearest"),
                       rtol=1e-12, atol=0.0)
    weights = np.array([0.0, 0.2, 0.5, 0.3, 0.0])  # not symmetric: correlation, not convolution
    expected = ndimage.correlate1d(ndimage.correlate1d(noise, weights, 0, mode="nearest"), weights, 1,
                                   mode="nearest")
    assert np.allclose(separable(noise, weights), expected, rtol=1e-12, atol=0.0)


def test_the_blur_leaves_the_filters_reach_out():
    # A single noisy pixel: with its filter's reach (2 px) left out, its own square gets nothing of it.
    noise = np.zeros((21, 21))
    noise[10, 10] = 1.0
    out = blurred(noise, 4.0, exclude_px=2)
    assert (out[8:13, 8:13] == 0.0).all() and out[10, 14] > 0 and out[5, 10] > 0
    assert blurred(noise, 0.0) is noise


def test_second_pass_adapts_only_where_the_first_predicts_a_gain():
    rng = np.random.default_rng(2)
    flat = np.full((8, 8), 0.3)
    extra, predicted = second_pass(flat, 8, 16, rng)
    assert predicted == pytest.approx(1.0) and (extra == 8).all()  # nothing to gain: uniform
    spot = np.full((8, 8), 0.01)
    spot[:2, :2] = 10.0
    extra, predicted = second_pass(spot, 8, 16, rng)
    assert predicted < PAYS_BELOW
    assert extra[:2, :2].min() > 8 > extra[4:, 4:].max()  # the noisy corner takes the samples
    assert abs(extra.sum() - 8 * 64) < 0.05 * 8 * 64


CBOX = Path(__file__).resolve().parents[1].parent / "shared" / "scenes" / "mitsuba-data" / "cbox" / "cbox.xml"
# A child that renders cbox at 128 px with 2^19 - 7 samples: 32 a pixel, one pixel none, the difference
# spread one sample each over the pixels from index 1000. Unpadded, this wavefront faulted Dr.Jit's kernel.
_FAULTING_TOTAL = f"""
import numpy as np
from core.model.job import SceneSpec
from core.render.per_pixel import render_counts
from core.scene.scene import load
counts = np.full(128 * 128, 32, dtype=np.int64)
counts[100] = 0
diff = 2**19 - 7 - int(counts.sum())
counts[1000:1000 + abs(diff)] += int(np.sign(diff))
loaded = load(SceneSpec({str(CBOX)!r}, {{"res": "128"}}), "llvm_ad_spectral", threads=2)
out = render_counts(loaded, counts.reshape(128, 128), seed=2001, moments=False)
print("rendered", int(out.counts.sum()), float(out.pixels[..., :3].mean()))
"""


def test_a_sample_total_that_faulted_the_kernel_renders():
    """The wavefront is padded (core.render.per_pixel.LANE_MULTIPLE): a total that crashed the render process
    now renders, in a process of its own so that a fault fails this test, not the run."""
    done = subprocess.run([sys.executable, "-c", _FAULTING_TOTAL], capture_output=True, text=True, timeout=300,
                          cwd=Path(__file__).resolve().parents[1])
    assert done.returncode == 0, f"exit {done.returncode}: {done.stderr[-1500:]}"
    assert f"rendered {2**19 - 7} " in done.stdout


def test_padding_lanes_add_nothing(tmp_path):
    """One sample in the last pixel of a film that sees a constant emitter (radiance 1 everywhere): the
    wavefront's 1023 padding lanes sit on that pixel, and neither its moments nor its value count them."""
    scene = tmp_path / "scene.xml"
    scene.write_text('<scene version="3.0.0"><integrator type="path"/><sensor type="perspective">'
                     '<sampler type="independent"/><film type="hdrfilm"><integer name="width" value="8"/>'
                     '<integer name="height" value="8"/><rfilter type="box"/></film></sensor>'
                     '<emitter type="constant"/></scene>')
    loaded = load(SceneSpec(scene, {}, ()), RGB, threads=1)
    counts = np.zeros((8, 8), dtype=np.int64)
    counts[-1, -1] = 1
    out = render_counts(loaded, counts, seed=3)
    assert out.sum[-1, -1] == pytest.approx([1.0, 1.0, 1.0], rel=1e-5)
    assert out.sum_sq[-1, -1] == pytest.approx([1.0, 1.0, 1.0], rel=1e-5)
    assert not out.sum[:-1].any() and not out.sum[-1, :-1].any()
    assert out.pixels[-1, -1, :3] == pytest.approx([1.0, 1.0, 1.0], rel=1e-5)
