"""The allocation benchmark: its arithmetic on hand-made maps, and a small real run through its JSON."""

from __future__ import annotations

import argparse
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from bench import allocation as ba
from bench.scaling import TimeMap, cache_file, measured_spec
from core.errors import QuekaroError, SceneError
from core.model.geometry import Rect
from core.model.job import SceneSpec
from planning.accuracy import content_key


def _plan(rects: list[Rect]) -> SimpleNamespace:
    return SimpleNamespace(units=[SimpleNamespace(rect=r) for r in rects], width=8, height=8, reach=0)


def _params(spps: list[int], band: int = 0) -> list[SimpleNamespace]:
    return [SimpleNamespace(spp=s, band=band) for s in spps]


HALVES = [Rect(0, 0, 4, 8), Rect(4, 0, 4, 8)]


def test_uniform_allocation_matches_the_uniform_baseline() -> None:
    tmap = TimeMap(np.full((8, 8), 1e-3), 0.0, {})
    weight = np.random.default_rng(1).uniform(0.1, 2.0, size=(8, 8, 3))
    row = ba.level_row("S", _plan(HALVES), _params([16, 16]), weight, tmap)
    spp, relmse = ba.uniform(row["render_seconds"], weight, tmap)
    assert spp == pytest.approx(16.0)
    assert row["relmse"] == pytest.approx(relmse)  # same samples everywhere: same expected error


def test_samples_moved_to_the_noisy_half_beat_uniform_and_neyman_is_best() -> None:
    tmap = TimeMap(np.full((8, 8), 1e-3), 0.0, {})
    weight = np.ones((8, 8, 3))
    weight[:, 4:] = 16.0  # the right half is 16x as noisy per sample: Neyman gives it 4x the samples
    row = ba.level_row("S", _plan(HALVES), _params([8, 24]), weight, tmap)
    _, uniform_relmse = ba.uniform(row["render_seconds"], weight, tmap)
    assert row["relmse"] < uniform_relmse
    bound = ba.neyman_ratio(_plan(HALVES), _params([8, 24]), weight, tmap)
    assert bound <= row["relmse"] / uniform_relmse
    # Neyman: spp in proportion to sqrt(16) = 4, so 6.4 and 25.6 for the same 32 spp-units of time;
    # uniform spends it as 16 spp everywhere. Errors: weight sums 96 and 1536 over 192 values.
    assert bound == pytest.approx(((96 / 6.4 + 1536 / 25.6) / 192) / (8.5 / 16), rel=1e-9)


def test_fixed_costs_and_bands_are_charged_to_the_units() -> None:
    tmap = TimeMap(np.full((8, 8), 1e-3), 0.05, {})
    weight = np.ones((8, 8, 3))
    row = ba.level_row("S", _plan(HALVES), _params([10, 10], band=1), weight, tmap)
    assert row["relmse"] < 0.1  # the overlapping bands average two estimates: below one tile's 1 / 10
    # each half's window is its 4 px and a 1 px band a side, shifted inside at the image's edge (both
    # bands on the inner side): 6x8 pixels; two render calls
    assert row["render_seconds"] == pytest.approx(2 * 0.05 + 2 * 10 * 48 * 1e-3)
    spp, _ = ba.uniform(row["render_seconds"], weight, tmap)
    # the same time buys uniform more than the units' 10 spp: one call, no band rendered twice
    assert spp == pytest.approx((row["render_seconds"] - 0.05) / (64 * 1e-3)) and spp > 10


def test_band_overlap_averages_two_estimates_and_lowers_the_variance() -> None:
    factor = ba.composed_inverse_spp(_plan(HALVES), [10, 10], [1, 1])
    # Band 1 at the image's edge: each window is shifted inside, so its inner side has 2 px of band.
    # Left half's core at x = 3 has weight 1; the right tile's 2 px band reaches it at distance 1 with
    # weight 1 - 1/3. Normalised 0.6 and 0.4: variance (0.36 + 0.16) / 10. At x = 2: 1 and 1/3, so
    # (0.75^2 + 0.25^2) / 10. Beyond the band (x = 0, 1) one tile: 1 / 10.
    assert factor[:, 0] == pytest.approx(0.1) and factor[:, 1] == pytest.approx(0.1)
    assert factor[:, 3] == pytest.approx(0.052) and factor[:, 2] == pytest.approx(0.0625)
    assert np.allclose(factor[:, ::-1], factor)  # symmetric
    no_band = ba.composed_inverse_spp(_plan(HALVES), [10, 40], [0, 0])
    assert np.allclose(no_band[:, :4], 0.1) and np.allclose(no_band[:, 4:], 0.025)


def test_the_pixel_bound_by_hand() -> None:
    tmap = TimeMap(np.array([[1.0, 1.0]]), 0.0, {})
    # all the error in one pixel of two equally costly ones: give it all the samples, half uniform's error
    assert ba.pixel_bound(np.array([[[1.0], [0.0]]]), tmap) == pytest.approx(0.5)
    # error in proportion to time: uniform spp is already the best allocation
    tmap = TimeMap(np.array([[1.0, 4.0], [2.0, 0.5]]), 0.0, {})
    assert ba.pixel_bound(np.array([[[3.0], [12.0]], [[6.0], [1.5]]]), tmap) == pytest.approx(1.0)


@pytest.mark.parametrize("seed", range(8))
def test_no_allocation_over_units_beats_the_pixel_bound(seed: int) -> None:
    rng = np.random.default_rng(seed)
    tmap = TimeMap(rng.uniform(1e-4, 5e-3, size=(8, 8)), 0.0, {})
    weight = rng.lognormal(0.0, 1.5, size=(8, 8, 3))
    bound = ba.pixel_bound(weight, tmap)
    assert 0.0 < bound <= 1.0 + 1e-12
    # Neyman over two units, no bands and no fixed cost, is one of the allocations the bound ranges over
    assert bound <= ba.neyman_ratio(_plan(HALVES), _params([16, 16]), weight, tmap) + 1e-12


@pytest.mark.parametrize("seed", range(4))
def test_a_first_pass_that_knew_the_true_noise_reaches_the_pixel_bound_where_time_is_even(seed: int) -> None:
    rng = np.random.default_rng(seed)
    weight = rng.lognormal(0.0, 1.5, size=(8, 8, 3))
    truth = weight.mean(axis=-1)
    even = TimeMap(np.full((8, 8), 2e-3), 0.0, {})
    assert ba.first_pass_ratio(weight, even, truth, 16, 0) == pytest.approx(ba.pixel_bound(weight, even), rel=1e-9)
    # the bound also prices time per pixel, and a first pass spent uniformly or a wrong estimate only lose
    tmap = TimeMap(rng.uniform(1e-4, 5e-3, size=(8, 8)), 0.0, {})
    guess = truth * rng.lognormal(0.0, 1.0, size=truth.shape)
    assert ba.pixel_bound(weight, tmap) - 1e-12 <= ba.first_pass_ratio(weight, tmap, truth, 16, 0)
    assert ba.first_pass_ratio(weight, even, truth, 16, 0) - 1e-12 <= ba.first_pass_ratio(weight, even, truth, 16, 8) \
        <= ba.first_pass_ratio(weight, even, guess, 16, 8) + 1e-12


def test_the_first_pass_ratio_by_hand() -> None:
    tmap = TimeMap(np.full((8, 8), 1e-3), 0.0, {})
    weight = np.ones((8, 8, 1))
    weight[:, 4:] = 16.0  # Neyman wants 1:4, 6.4 and 25.6 spp of 16; the first pass holds the left at 8
    truth = weight[..., 0]
    assert ba.first_pass_ratio(weight, tmap, truth, 16, 8) == pytest.approx((1 / 8 + 16 / 24) / (17 / 16))
    # the estimate swapped: the quiet half gets the samples, and the image is worse than uniform's
    assert ba.first_pass_ratio(weight, tmap, truth[:, ::-1], 16, 8) == pytest.approx((1 / 24 + 16 / 8) / (17 / 16))
    assert ba.first_pass_ratio(weight, tmap, np.ones((8, 8)), 16, 8) == pytest.approx(1.0)  # nothing known
    assert ba.first_pass_ratio(weight, tmap, truth, 16, 16) == 1.0  # the first pass spent the budget
    with pytest.raises(ValueError, match="differ in shape"):
        ba.first_pass_ratio(weight, tmap, np.ones((4, 4)), 16, 8)


def test_a_scene_the_two_pass_render_refuses_gets_its_reason_not_a_ratio() -> None:
    """The first pass renders by per-pixel counts, which need the independent sampler: the line names that."""
    spec = measured_spec(COMPAT / "sampler_stratified.xml", 16)
    args = SimpleNamespace(spp=8, seeds=2, threads=1)
    tmap = TimeMap(np.full((1, 1), 1e-3), 0.0, {})  # not reached: the pass is refused before any scoring
    first = ba.first_pass_bound(spec, "llvm_ad_rgb", np.ones((1, 1, 3)), tmap, args)
    assert first["ratio"] is None and first["ratio_runs"] == [] and first["first_spp"] == 4
    assert first["refused"].startswith("sampler StratifiedSampler: per-pixel sample counts need the independent")
    line = ba.format_report({"scene": "s.xml", "size": [1, 1], "spp": 8, "rules": "r.xml", "off_render_seconds": 1.0,
                             "rows": [], "seeds": 2, "neyman_ratio_S": 1.0, "pixel_bound": 1.0,
                             "first_pass": first}).splitlines()[-1]
    assert line.startswith("the same with the noise a two-pass render knows (its first pass of 4 spp): none, "
                           "the two-pass render refuses this scene: sampler StratifiedSampler")


def test_the_pixel_bound_refuses_maps_of_other_shapes() -> None:
    with pytest.raises(ValueError, match="differ in shape"):
        ba.pixel_bound(np.ones((4, 4, 3)), TimeMap(np.ones((8, 8)), 0.0, {}))


@pytest.mark.slow  # six small real renders, a reference, a time map and 5 levels x 1 plan
def test_small_real_run(tmp_path) -> None:
    parser = argparse.ArgumentParser()
    ba.add_arguments(parser)
    args = parser.parse_args(["--res", "64", "--spp", "16", "--renders", "3", "--ref-spp", "128", "--seeds", "1",
                              "--threads", "1", "--cell", "32", "--measure-spp", "64",
                              "--cache-dir", str(tmp_path), "--out", str(tmp_path)])
    args.json = True
    result = ba.run(args)
    assert [r["level"] for r in result["rows"]] == list(ba.LEVELS)
    for r in result["rows"]:
        assert 0.0 < r["time_vs_off"] < 3.0 and np.isfinite(r["ratio"]) and r["ratio"] > 0, r
        assert 1 <= r["spp_min"] <= r["spp_max"] <= 3 * 16
    assert 0.0 < result["neyman_ratio_S"] <= 1.0 + 1e-6  # float sums of per-pixel seconds
    assert 0.0 < result["pixel_bound"] <= min(1.0, result["neyman_ratio_S"]) + 1e-9
    first = result["first_pass"]
    assert first["first_spp"] == 8 and len(first["ratio_runs"]) == 1
    assert result["pixel_bound"] < first["ratio"] < 10  # not knowing the noise costs something
    assert list(tmp_path.glob("allocation-noise-*.npy"))  # the noise map is cached
    text = (tmp_path / "allocation.md").read_text()
    assert "| S |" in text and "its first pass of 8 spp, blurred as it blurs it" in text
    assert f"that pass uniform): ratio {first['ratio']:.3f}" in text


@pytest.mark.slow  # small real renders, a reference and a time map of a 40x24 scene
def test_any_scene_with_its_parameters(tmp_path) -> None:
    """-D takes the scene at its own film size: a scene whose size comes from width and height, not res."""
    parser = argparse.ArgumentParser()
    ba.add_arguments(parser)
    scene = Path(__file__).resolve().parent / "data" / "scenes" / "tiny.xml"
    args = parser.parse_args(["--scene", str(scene), "-D", "width=40", "-D", "height=24", "--spp", "8",
                              "--renders", "2", "--ref-spp", "64", "--seeds", "1", "--threads", "1",
                              "--cell", "20", "--measure-spp", "256", "--cache-dir", str(tmp_path),
                              "--out", str(tmp_path)])
    args.json = True
    result = ba.run(args)
    assert result["size"] == [40, 24] and result["defines"] == {"width": "40", "height": "24"}
    assert (tmp_path / "allocation.md").read_text().splitlines()[2].startswith("tiny.xml 40x24, user spp 8")
    names = [p.name for p in tmp_path.glob("scaling-*.npz")]
    key = content_key(SceneSpec(scene, {"width": "40", "height": "24"}))  # every file read, and the -D
    assert len(names) == 1 and names[0].startswith(f"scaling-{key}-"), names


def test_a_bad_define_is_refused_naming_it(tmp_path) -> None:
    parser = argparse.ArgumentParser()
    ba.add_arguments(parser)
    args = parser.parse_args(["-D", "width", "--cache-dir", str(tmp_path), "--out", str(tmp_path)])
    args.json = True
    with pytest.raises(SceneError, match="-D 'width': expected NAME=VALUE"):
        ba.run(args)


COMPAT = Path(__file__).resolve().parent / "compat" / "scenes"
REPO = Path(__file__).resolve().parent.parent


def test_the_caches_follow_every_file_the_scene_reads(tmp_path) -> None:
    """Two scene.xml files alike but for the room they include: the noise and time maps of one were read
    for the other (both keys hashed the top file only)."""
    specs = []
    for name, colour in (("a", "0.2"), ("b", "0.8")):
        folder = tmp_path / name
        folder.mkdir()
        (folder / "room.xml").write_text(f"<scene version='3.0.0'><shape type='sphere'><bsdf type='diffuse'>"
                                         f"<rgb name='reflectance' value='{colour}'/></bsdf></shape></scene>")
        (folder / "scene.xml").write_text("<scene version='3.0.0'><include filename='room.xml'/></scene>")
        specs.append(SceneSpec(folder / "scene.xml"))
    noise = {ba.noise_path(s, 8, 2, tmp_path, "llvm_ad_rgb") for s in specs}
    times = {cache_file(tmp_path, s, 32, 8, 1, "llvm_ad_rgb") for s in specs}
    assert len(noise) == 2 and len(times) == 2


def test_a_scene_without_a_res_parameter_is_measured_at_its_films_size() -> None:
    """--res was passed as -D res to any scene, and Mitsuba refused it where the scene has no such parameter."""
    assert measured_spec(COMPAT / "film_pfm.xml", 320).defines == {}
    assert measured_spec(REPO / "scenes" / "cbox.xml", 320).defines == {"res": "320"}


@pytest.mark.parametrize(("option", "value", "says"), [
    ("--seeds", "0", "--seeds 0: at least 1"), ("--cell", "0", "--cell 0: at least 1"),
    ("--renders", "1", "--renders 1: at least 2"), ("--ref-spp", "0", "--ref-spp 0: at least 1"),
])
def test_counts_it_cannot_run_with_are_refused_before_anything_renders(tmp_path, option, value, says) -> None:
    """They ended in a traceback (min() of nothing, range() step 0) or ran with a reference of 0 spp."""
    parser = argparse.ArgumentParser()
    ba.add_arguments(parser)
    args = parser.parse_args([option, value, "--cache-dir", str(tmp_path / "cache"), "--out", str(tmp_path)])
    with pytest.raises(QuekaroError, match=says):
        ba.run(args)
    assert not (tmp_path / "cache").exists()


@pytest.mark.slow  # a small real run of a scene whose integrator wraps another (aov around path)
def test_a_scene_whose_integrator_wraps_another_is_measured(tmp_path) -> None:
    """Its pre-pass estimates with the wrapped integrator, as a job's does: it crashed on aov's missing
    `aovs` property."""
    parser = argparse.ArgumentParser()
    ba.add_arguments(parser)
    args = parser.parse_args(["--scene", str(COMPAT / "aov.xml"), "--spp", "8", "--renders", "2", "--ref-spp", "32",
                              "--seeds", "1", "--threads", "1", "--measure-spp", "16", "--cache-dir", str(tmp_path),
                              "--out", str(tmp_path)])
    args.json = True
    result = ba.run(args)
    assert result["size"] == [48, 40] and all(np.isfinite(r["ratio"]) for r in result["rows"])
