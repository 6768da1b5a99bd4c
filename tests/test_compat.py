"""The compatibility suite: scenes of the kinds users bring (tests/compat_cases.py), each rendered through
`quekaro render --opt off` and through a real 2-agent farm, and compared with plain Mitsuba rendering the
same file in the same variant by the per-pixel statistical test of tests/render_check.py."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from compat_cases import (
    CASES,
    REPO,
    SCENES,
    adaptive_args,
    check_adaptive_report,
    compare_files,
    job_args,
    problems,
    quekaro,
    reference,
    wait_done,
)
from render_check import by_name

from core.errors import QuekaroError
from core.image.imageio import read_image_channels
from core.scene.bundle import make_bundle
from farm.local import LocalFarm

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_quekaro_render_renders_as_mitsuba(case, tmp_path):
    out = tmp_path / "out.exr"
    done = quekaro("render", *job_args(case), "-o", str(out), "--threads", "2")
    assert done.returncode == 0, done.stderr[-3000:]
    assert "effects:" in done.stdout and "  - variant" in done.stdout  # the reasons are printed
    assert problems(case, out) == []


PASS_CASES = ("spectral-spiky", "spectral-grey-box", "polarized-stokes", "second-sensor", "nested-depths", "moment",
               "aov", "medium-grid")


@pytest.mark.parametrize("name", PASS_CASES)
def test_a_job_in_passes_renders_as_mitsuba(name, tmp_path):
    """`--progressive` (each unit's samples in halving passes, merged on their film weights) on the inputs
    passes had not met: spectral and polarized variants, a second sensor, nested integrators, moments, AOVs
    and a medium; merged, the image is Mitsuba's at the job's spp."""
    case = next(c for c in CASES if c.name == name)
    out = tmp_path / "passes.exr"
    done = quekaro("render", *job_args(case), "--progressive", "-o", str(out), "--threads", "2", "--no-progress")
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads(out.with_suffix(".json").read_text())
    assert report["render_calls"]["progressive"]["goal"] == "budget"
    assert all(u["passes"] >= 2 and u["spp"] == case.unit_spp for u in report["units"]), report["units"]
    assert problems(case, out) == []


@pytest.mark.parametrize("name,kind", [("radiancemeter", "radiancemeter"), ("irradiancemeter", "irradiancemeter")])
def test_a_rule_level_plans_a_meter_as_one_unit(name, kind, tmp_path):
    """Level S on a radiance meter and on a shape's irradiance meter (sensors that render whole: one unit
    at the user's spp, saying why; the radiance meter's pre-pass had made Dr.Jit abort, the irradiance
    meter's had failed in Mitsuba, which cannot sample a camera ray from it)."""
    meter = next(c for c in CASES if c.name == name)
    out = tmp_path / "meter.exr"
    done = quekaro("render", *job_args(meter), "--opt", "S", "-o", str(out), "--threads", "2", "--no-progress")
    assert done.returncode == 0, done.stderr[-3000:]
    assert "level S not applied" in done.stdout and f"sensor {kind} renders as one unit" in done.stdout
    assert problems(meter, out) == []


def test_a_rule_level_plans_a_polarized_scene(tmp_path):
    """Level S on a stokes scene (the pre-pass traces Mueller-matrix weights)."""
    stokes = next(c for c in CASES if c.name == "polarized-stokes")
    out = tmp_path / "stokes.exr"
    done = quekaro("render", *job_args(stokes), "--opt", "S", "-o", str(out), "--threads", "2", "--no-progress")
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads(out.with_suffix(".json").read_text())
    assert report["options"]["level"] == "S" and report["effects"]["variant"] == stokes.variant
    assert report["prepass"]["downscale"] >= 1  # the pre-pass ran (its ray count had failed on a Mueller weight)


AVERAGED_JOBS = 8  # one image lacks the power to see a bias of a few band pixels; eight averaged see it


@pytest.mark.parametrize("name", ["aov", "lanczos"])
def test_averaged_jobs_keep_mitsubas_means_at_unit_borders(name, tmp_path):
    """AVERAGED_JOBS level-off jobs of 6 units (each its own job id, so its own seeds) against plain
    Mitsuba's 32 renders. A tile's outer band pixels miss the samples beyond its window that their filter
    reaches: blended in, they moved the depth AOV and the colour at unit borders by ~2 reference standard
    deviations (aov, gaussian filter); with Lanczos' wider filter a band of 2 px also left core pixels
    short (issue 15)."""
    case = next(c for c in CASES if c.name == name)
    ref_names = reference(case)[1]
    images = []
    for k in range(AVERAGED_JOBS):
        out = tmp_path / f"job{k}.exr"
        done = quekaro("render", *job_args(case), "-o", str(out), "--threads", "2", "--no-progress")
        assert done.returncode == 0, done.stderr[-3000:]
        image, names = read_image_channels(out)
        images.append(by_name(image, names, ref_names))
    verdict = compare_files(case, images)
    print(f"{name}, {AVERAGED_JOBS} jobs averaged: {verdict}")
    assert verdict.only_fireflies, f"{name}: {verdict}"


@pytest.fixture(scope="module")
def farm_jobs(tmp_path_factory):
    """A real 2-agent farm with every case submitted through `quekaro submit`; yields {case: job id}."""
    home = tmp_path_factory.mktemp("farm")
    with LocalFarm(home, agents=2, threads=1) as farm:
        farm.wait_for_agents()
        jobs = {}
        for case in CASES:
            done = quekaro("submit", *job_args(case), "--home", str(home))
            assert done.returncode == 0, f"{case.name}: {done.stderr[-2000:]}"
            jobs[case.name] = done.stdout.strip().splitlines()[-1]
        yield farm, home, jobs


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_farm_renders_as_mitsuba(case, farm_jobs, tmp_path):
    farm, home, jobs = farm_jobs
    job = wait_done(farm.client(), jobs[case.name])
    assert job["status"] == "done", job
    shown = quekaro("status", jobs[case.name], "--home", str(home))
    assert "effects:" in shown.stdout and "  - integrator" in shown.stdout  # reasons where people look
    out = tmp_path / "farm.exr"
    fetched = quekaro("result", jobs[case.name], "-o", str(out), "--home", str(home))
    assert fetched.returncode == 0, fetched.stderr[-2000:]
    assert problems(case, out) == []


def test_a_jobs_rule_file_reaches_the_agents(farm_jobs, tmp_path):
    """`quekaro submit --rules` carries the file in the job's bundle; the agents plan with it (MASYRO's own
    file here: its factors keep every unit between half and all of the user's 64 spp)."""
    farm, home, _ = farm_jobs
    rules = REPO / "tests" / "data" / "rules" / "masyro_fixed.xml"
    case = next(c for c in CASES if c.name == "moment")
    done = quekaro("submit", str(case.scene), "--opt", "S", "--units", "6", "--rules", str(rules),
                   "--home", str(home))
    assert done.returncode == 0, done.stderr[-2000:]
    job_id = done.stdout.strip().splitlines()[-1]
    assert wait_done(farm.client(), job_id)["status"] == "done"
    out = tmp_path / "rules.exr"
    assert quekaro("result", job_id, "-o", str(out), "--home", str(home)).returncode == 0
    units = json.loads(out.with_suffix(".json").read_text())["units"]
    assert {u["rules"] for u in units} == {"QUEKARO-RULES.xml"}
    assert all(32 <= u["spp"] <= 64 for u in units), [u["spp"] for u in units]
    # The same bundle sent at level off through the API (no CLI to check it first): the master refuses it,
    # since level off would ignore the rule file.
    bundle = make_bundle(case.scene, {}, tmp_path / "rules.tar", rules=rules).path.read_bytes()
    with pytest.raises(QuekaroError, match="--rules: level off applies no rules"):
        farm.client().submit(bundle, {}, {"level": "off"})


def test_result_writes_the_films_file_or_into_a_folder_and_refuses_other_formats(farm_jobs, tmp_path):
    farm, home, jobs = farm_jobs
    job_id = jobs["moment"]
    assert wait_done(farm.client(), job_id)["status"] == "done"
    folder = quekaro("result", job_id, "-o", str(tmp_path / "renders"), "--home", str(home))
    assert folder.returncode == 0, folder.stderr[-2000:]
    stem = Path(farm.client().status(job_id)["scene"]).stem  # named after its scene, as `quekaro render` names it
    assert all((tmp_path / "renders" / f"{stem}{suffix}").is_file() for suffix in (".exr", ".png", ".json"))
    png = quekaro("result", job_id, "-o", str(tmp_path / "picture.png"), "--home", str(home))
    assert png.returncode == 2 and "film's file_format asks (EXR, PFM or RGBE)" in png.stderr
    assert not (tmp_path / "picture.png").exists()
    pfm = jobs["film-pfm"]  # a film writing PFM: the file takes the film's suffix, as Mitsuba names it
    assert wait_done(farm.client(), pfm)["status"] == "done"
    fetched = quekaro("result", pfm, "-o", str(tmp_path / "asked.exr"), "--home", str(home))
    assert fetched.returncode == 0 and fetched.stdout.startswith(str(tmp_path / "asked.pfm")), fetched.stdout
    assert (tmp_path / "asked.pfm").is_file() and not (tmp_path / "asked.exr").exists()
    (tmp_path / "a-file").write_text("not a folder")
    blocked = quekaro("result", job_id, "-o", str(tmp_path / "a-file" / "x.exr"), "--home", str(home))
    assert blocked.returncode == 2 and f"{tmp_path / 'a-file'} is a file, not a folder" in blocked.stderr


FARM_ADAPTIVE_JOBS = 8  # as tests/test_adaptive_jobs.py's RUNS: the jobs' own variance enters the test


@pytest.mark.parametrize("name", ["aov", "medium-homogeneous"])
def test_an_adaptive_farm_job_keeps_mitsubas_means(name, farm_jobs, tmp_path):
    """`quekaro submit --adaptive`: the agents render each unit's planned share in two passes; eight jobs
    (each its own job id, so its own seeds) keep plain Mitsuba's means in every channel, and the report
    says each unit rendered its share."""
    farm, home, _ = farm_jobs
    case = next(c for c in CASES if c.name == name)
    ref_names = reference(case)[1]
    jobs = []
    for _ in range(FARM_ADAPTIVE_JOBS):
        done = quekaro("submit", *adaptive_args(case, 4), "--home", str(home))
        assert done.returncode == 0, done.stderr[-2000:]
        jobs.append(done.stdout.strip().splitlines()[-1])
    images = []
    for k, job_id in enumerate(jobs):
        assert wait_done(farm.client(), job_id)["status"] == "done"
        out = tmp_path / f"farm{k}.exr"
        assert quekaro("result", job_id, "-o", str(out), "--home", str(home)).returncode == 0
        image, names = read_image_channels(out)
        images.append(by_name(image, names, ref_names))
        check_adaptive_report(json.loads(out.with_suffix(".json").read_text()), units=4)
    verdict = compare_files(case, images)
    assert verdict.only_fireflies, f"{name}: {verdict}"
    shown = quekaro("status", jobs[0], "--home", str(home)).stdout
    assert "adaptive: " in shown and "spp per pixel from the rules" in shown, shown


def test_a_bad_rule_file_is_refused_at_submit_naming_its_fault(tmp_path):
    bad = REPO / "tests" / "data" / "rules" / "masyro_original.xml"  # MASYRO's published typo
    done = quekaro("submit", str(CASES[0].scene), "--opt", "S", "--rules", str(bad), "--home", str(tmp_path))
    assert done.returncode == 2
    assert "masyro_original.xml:41, variable 'Ls', label 'B'" in done.stderr and "c=9 > d=1" in done.stderr


def test_a_scene_name_no_message_can_carry_is_refused_at_submit(farm_jobs, tmp_path):
    """A file name with a line break is a valid Linux name that the job message cannot carry: refused when
    submitted, naming the field, not accepted and failed at its auction; the farm goes on."""
    farm, home, jobs = farm_jobs
    odd = tmp_path / "two\nlines.xml"
    odd.write_text((SCENES / "direct.xml").read_text().replace("_room.xml", str(SCENES / "_room.xml"))
                   .replace("_camera.xml", str(SCENES / "_camera.xml")))
    done = quekaro("submit", str(odd), "--home", str(home))
    assert done.returncode == 2 and "job.scene_name" in done.stderr and "cannot travel" in done.stderr, done.stderr
    assert wait_done(farm.client(), jobs["direct"])["status"] == "done"
