"""The statistical comparison with plain Mitsuba (tests/render_check.py) has power: it refuses renders
that compute something else, with fewer samples, or from tiles of an integrator that cannot be tiled."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import time

import pytest
from compat_cases import CASES, SCENES, compare_files, job_args, problems, reference
from render_check import by_name, compare, reference_renders

import core.model.integrators as integrators
from core.image.imageio import read_image_channels
from core.model.job import RenderOptions, SceneSpec
from core.render.process import RenderProcess
from planning.jobplan import plan_job
from planning.pipeline import render_plan

pytestmark = pytest.mark.slow


def _case(name: str):
    return next(c for c in CASES if c.name == name)


def test_another_seed_passes_and_fewer_samples_or_another_integrator_fail():
    scene = SCENES / "default_integrator.xml"
    refs, _ = reference_renders(scene, "llvm_ad_rgb", 64, defines={"integrator": "direct"})
    same, _ = reference_renders(scene, "llvm_ad_rgb", 64, defines={"integrator": "direct"}, renders=1, seed0=7)
    assert compare(same[0], refs).passed
    fewer, _ = reference_renders(scene, "llvm_ad_rgb", 16, defines={"integrator": "direct"}, renders=1, seed0=7)
    verdict = compare(fewer[0], refs)
    assert not verdict.passed and verdict.variance_ratio > 2
    path, _ = reference_renders(scene, "llvm_ad_rgb", 64, defines={"integrator": "path"}, renders=1, seed0=7)
    assert compare(path[0], refs).failing > 1000


def test_a_tiled_particle_tracer_is_refused_by_the_comparison(tmp_path, monkeypatch):
    """Why ptracer renders whole: forced into 6 tiles, its image fails (light paths splat across tiles)."""
    forced = dataclasses.replace(integrators.CATALOGUE["ptracer"], splittable=True)
    monkeypatch.setitem(integrators.CATALOGUE, "ptracer", forced)
    case = _case("ptracer")
    plan = plan_job(SceneSpec(case.scene), RenderOptions(units=6, threads=2))  # here, where the patch is
    with RenderProcess() as worker:
        render_plan(plan, tmp_path / "tiled.exr", worker, time.perf_counter())
    found = problems(case, tmp_path / "tiled.exr")
    assert any("DIFFERENT" in p for p in found), found


@pytest.mark.parametrize(("name", "rgb_is_the_same"), [("spectral_flat.xml", True), ("spectral_spiky.xml", False)])
def test_the_variant_criterion_on_both_sides_against_real_renders(name, rgb_is_the_same):
    """effects.py renders per-wavelength data in rgb only where rgb computes the same image: checked here
    by plain Mitsuba in both variants. Flat data: an rgb render's means agree with spectral renders' (its
    variance is lower: no colour noise from sampling wavelengths). A narrow line lighting a narrow band:
    rgb's channel-wise product lights a sphere that spectral light leaves dark."""
    from core.scene.effects import analyse

    spectral, _ = reference_renders(SCENES / name, "llvm_ad_spectral", 64)
    rgb, _ = reference_renders(SCENES / name, "llvm_ad_rgb", 64, renders=1, seed0=5)
    verdict = compare(rgb[0], spectral)
    if rgb_is_the_same:
        assert verdict.failing == 0, verdict  # every mean agrees (the variance is lower, see above)
    else:
        assert not verdict.passed and verdict.failing > 100, verdict
    chosen = analyse(SceneSpec(SCENES / name)).variant
    assert chosen == ("llvm_ad_rgb" if rgb_is_the_same else "llvm_ad_spectral")


def test_a_scalar_variant_renders_level_off_as_mitsuba_and_refuses_what_needs_wavefronts(tmp_path):
    """scalar_rgb is the fallback where Dr.Jit finds no LLVM (and a user may ask for it with -m): level off
    renders there, in tiles, the image plain Mitsuba makes; the pre-pass and adaptive sampling trace
    Dr.Jit wavefronts, so the levels that need them are refused with the reason, not a traceback."""
    case = _case("direct")
    out = tmp_path / "scalar.exr"
    done = subprocess.run([sys.executable, "-m", "quekaro", "render", *job_args(case), "-m", "scalar_rgb",
                           "--spp", str(case.spp), "--no-progress", "-o", str(out)],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads(out.with_suffix(".json").read_text())
    assert report["effects"]["variant"] == "scalar_rgb" and len(report["units"]) == case.units
    ref_names = reference(case)[1]
    image, names = read_image_channels(out)
    verdict = compare_files(case, by_name(image, names, ref_names))
    assert verdict.passed, verdict
    for extra in (["--opt", "S"], ["--opt", "S", "--adaptive"]):
        refused = subprocess.run([sys.executable, "-m", "quekaro", "render", str(case.scene), "-m", "scalar_rgb",
                                  *extra, "--spp", "8", "--no-progress", "-o", str(tmp_path / "S.exr")],
                                 capture_output=True, text=True, timeout=600)
        assert refused.returncode == 2, refused.stderr[-2000:]
        assert "needs an llvm_* or cuda_* Mitsuba variant" in refused.stderr and "Traceback" not in refused.stderr
