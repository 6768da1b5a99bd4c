"""Hard-case scenes through the whole render (both routes of conftest.render): every image is finite,
every non-finite sample is counted in the report, awkward sizes and parameters render or are refused."""

from __future__ import annotations

import time

import numpy as np
import pytest

from hard_cases.conftest import RULES, SCENES, Run, pipeline_import_error

LEVELS = ["off", "S"]


def assert_sane(run: Run, width: int, height: int) -> None:
    """Finite, non-negative, the right size, fully covered, every unit rendering something."""
    assert run.image.shape == (height, width, 3)
    assert np.isfinite(run.image).all()
    assert (run.image >= 0).all()
    assert run.compose["uncovered"] == 0
    assert all(u["spp"] >= 1 and u["depth"] >= 1 for u in run.units)
    covered = sum(u["rect"][2] * u["rect"][3] for u in run.units)
    assert covered == width * height  # units tile the image exactly once
    if run.report:
        totals = run.report["totals"]
        assert all(np.isfinite(float(v)) for v in totals.values())


@pytest.mark.parametrize("level", LEVELS)
def test_tiny_very_bright_emitter_beside_glossy_surfaces(render, level):
    run = render("lamp.xml", level, spp=4, radiance="1e7", lamp_radius="0.01", width=24, height=24)
    assert_sane(run, 24, 24)
    assert run.nonfinite == 0  # bright is not infinite: nothing may be zeroed
    assert run.image.max() > 10.0  # the fireflies are there, and finite


@pytest.mark.parametrize("radiance", ["inf", "nan"])
@pytest.mark.parametrize("level", LEVELS)
def test_emitter_with_non_finite_radiance_is_finite_and_counted(render, level, radiance):
    run = render("lamp.xml", level, radiance=radiance)
    assert_sane(run, 16, 16)
    assert run.nonfinite > 0  # never silent
    assert run.nonfinite == sum(u["nonfinite"] for u in run.units)
    assert run.nonfinite <= 16 * 16 + sum(u["band"] for u in run.units) * 64  # counts pixels, not samples
    if run.report:
        assert run.report["totals"]["nonfinite"] == run.nonfinite


@pytest.mark.parametrize("scene", ["black.xml", "empty.xml"])
@pytest.mark.parametrize("level", LEVELS)
def test_all_black_and_nothing_visible_give_exact_zero(render, level, scene):
    run = render(scene, level, units=4)
    assert_sane(run, 16, 16)
    assert run.nonfinite == 0 and not run.image.any()
    # Every unit alike: the dynamic sets get an empty range, and all units get the same parameters.
    assert len({(u["depth"], u["spp"], u["band"]) for u in run.units}) == 1
    assert len({u["C"] for u in run.units}) == 1


@pytest.mark.parametrize(("width", "height"), [(1, 1), (1, 9), (9, 1), (37, 23), (200, 2)])
@pytest.mark.parametrize("level", LEVELS)
def test_awkward_image_sizes(render, level, width, height):
    run = render("lamp.xml", level, units=6, width=width, height=height)
    assert_sane(run, width, height)


def test_huge_spp_on_a_one_pixel_image_finishes_quickly(render):
    start = time.perf_counter()
    run = render("lamp.xml", "off", spp=100_000, units=1, width=1, height=1)
    assert time.perf_counter() - start < 60
    assert_sane(run, 1, 1)
    assert run.units[0]["spp"] == 100_000
    assert run.image.max() > 0  # the pixel sees the lit floor


@pytest.mark.parametrize("level", LEVELS)
def test_depth_one_shows_only_the_emitter(render, level):
    run = render("lamp.xml", level, depth=1, units=4)
    assert_sane(run, 16, 16)
    assert all(u["depth"] == 1 for u in run.units)  # the rules never go below 1, nor above the user
    lit = (run.image > 0).any(axis=-1)
    assert 0 < lit.sum() < 16 * 16 // 2  # the lamp itself, and no bounce light on the floor


def test_depth_zero_from_the_user_is_refused_naming_the_option():
    if reason := pipeline_import_error():
        pytest.skip(reason)
    from core.errors import QuekaroError
    from core.model.job import RenderOptions

    with pytest.raises(QuekaroError, match="--depth 0"):
        RenderOptions(level="S", depth=0)


@pytest.mark.parametrize("level", ["off", "S"])
def test_scene_asking_for_depth_zero_renders_finite_with_depth_at_least_one(level, tmp_path):
    """A scene whose own integrator says max_depth 0 (renders nothing in Mitsuba): the job maps it to
    depth >= 1 at every level, as the rules do, or refuses it naming the depth."""
    if reason := pipeline_import_error():
        pytest.skip(reason)
    from core.errors import QuekaroError
    from core.model.job import RenderOptions, SceneSpec
    from planning.pipeline import render_job

    spec = SceneSpec(SCENES / "lamp.xml", {"depth": "0"})
    options = RenderOptions(level=level, spp=2, threads=1, units=2)
    try:
        report = render_job(spec, options, tmp_path / "out.exr")
    except QuekaroError as exc:
        assert "depth" in str(exc)
        return
    assert all(u["depth"] >= 1 for u in report["units"])


def test_band_wider_than_the_unit_is_clipped_to_the_image(render):
    run = render("lamp.xml", "S", units=16, rules=RULES / "wide_band.xml", width=32, height=32)
    assert_sane(run, 32, 32)
    assert all(u["band"] == 95 for u in run.units)
    assert all(u["window"] in (None, [0, 0, 32, 32]) for u in run.units)
    reference = render("lamp.xml", "off", units=1, width=32, height=32)
    # Every unit covers the whole image, so the blend is a mean of several full renders: close to one.
    assert abs(float(run.image.mean()) - float(reference.image.mean())) < 0.25 * float(reference.image.mean())


def test_one_unit_holding_all_the_cost(render):
    run = render("corner.xml", "S", units=8, width=32, height=32)
    assert_sane(run, 32, 32)
    ys, xs = np.nonzero(run.image.any(axis=-1))
    assert 0 < len(ys) < 32 * 32 // 8  # only the small sphere is visible
    costly = max(run.units, key=lambda u: u["C"])
    x, y, w, h = costly["rect"]
    assert ((xs >= x) & (xs < x + w) & (ys >= y) & (ys < y + h)).any()  # it holds the sphere
    assert sum(u["C"] == 0.0 for u in run.units) >= len(run.units) // 2  # the rest see nothing
