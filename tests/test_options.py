"""Job options are a schema: known keys, integer types, finite ranges, refused with the field named, at
the CLI, at the master's API and when a stored job is resumed."""

from __future__ import annotations

from pathlib import Path

import pytest

from core.errors import QuekaroError
from core.model.job import RenderOptions
from planning.jobplan import default_unit_count, scene_spp


@pytest.mark.parametrize(("options", "match"), [
    ({"spp": float("inf")}, r"option spp \(--spp inf\): not an integer"),
    ({"spp": 1e400}, r"option spp \(--spp inf\): not an integer"),
    ({"spp": 0}, r"option spp \(--spp 0\): outside 1\.\.1048576"),
    ({"spp": True}, r"option spp \(--spp True\): not an integer"),
    ({"units": "4"}, r"option units \(--units '4'\): not an integer"),
    ({"depth": 0}, r"option depth \(--depth 0\): outside 1\.\.1024 \(or -1 for unbounded\)"),
    ({"colour": "red"}, "option 'colour' is not known"),
    ({"integrator": "raytracer"}, "not one of Mitsuba's integrators"),
    ({"defuzzifier": "mean"}, "option defuzzifier"),
    ({"variant": "cuda; rm -rf"}, "not a Mitsuba variant name"),
    ({"level": "XL"}, "--opt 'XL'"),
    ({"noise": 0}, r"option noise \(--noise 0\): not a positive number"),
    ({"noise": float("nan")}, r"option noise \(--noise nan\): not a positive number"),
    ({"time": "10"}, r"option time \(--time '10'\): not a positive number"),
    ({"time": True}, r"option time \(--time True\): not a positive number"),
    ({"noise": 0.1, "time": 10}, "--noise and --time: give one goal"),
    ({"noise": 0.1, "level": "S", "adaptive": True}, "--adaptive with --noise, --time or --progressive"),
    ({"time": 5, "progressive": True}, "--time and --progressive: give one goal"),
    ({"progressive": 1}, "option progressive: 1 is not true or false"),
])
def test_bad_options_are_refused_naming_the_field(options, match):
    with pytest.raises(QuekaroError, match=match):
        RenderOptions.from_dict(options)


@pytest.mark.parametrize(("options", "match"), [
    ({"level": "off", "rules": "rules/pathtracing.xml"}, r"--rules: level off applies no rules.*--opt VS/S/N/B/VB"),
    ({"defuzzifier": "centroid"}, "--defuzzifier: level off applies no rules"),
    ({"rules": "r.xml", "defuzzifier": "centroid"}, "--rules and --defuzzifier: level off"),
])
def test_a_new_job_at_level_off_refuses_what_it_would_ignore(options, match):
    """Level off applies no rules: a rule file or a defuzzifier with it would be ignored, so a new job is
    refused (RenderOptions.check_used, at the CLI and the master's submit). A job stored before this
    check still reads back, so an older farm's list of jobs keeps working."""
    stored = RenderOptions.from_dict(options)
    assert RenderOptions.from_dict(stored.to_dict()) == stored
    with pytest.raises(QuekaroError, match=match):
        stored.check_used()
    RenderOptions.from_dict({**options, "level": "S"}).check_used()  # at a rule level they are used


@pytest.mark.parametrize("tau", [1, 2, 5.0])
def test_a_noise_goal_of_a_whole_relative_error_or_more_is_refused_as_a_likely_percentage(tau):
    """--noise 2 (meaning 2 %?) asks for an error of 200 %, which the first pass meets: a new job is refused."""
    with pytest.raises(QuekaroError, match=rf"--noise {tau:g}: a relative error of {tau * 100:g} %.*0.02 for 2 %"):
        RenderOptions(noise=tau).check_used()
    RenderOptions(noise=0.999).check_used()


def test_good_options_round_trip():
    options = RenderOptions.from_dict({"level": "S", "spp": 16, "depth": -1, "units": 6, "sensor": 1})
    assert RenderOptions.from_dict(options.to_dict()) == options
    for goal in ({"noise": 0.05}, {"time": 12.5}):
        progressive = RenderOptions.from_dict(goal)
        assert progressive.in_passes and RenderOptions.from_dict(progressive.to_dict()) == progressive
    assert "noise" not in options.to_dict() and not options.in_passes  # a job without a goal reads as before


def test_a_zero_sample_count_from_a_define_is_refused(tmp_path):
    from core.model.job import SceneSpec

    scene = tmp_path / "s.xml"
    scene.write_text('<scene version="3.0.0"><default name="spp" value="8"/><sensor type="perspective">'
                     '<sampler type="independent"><integer name="sample_count" value="$spp"/></sampler>'
                     '</sensor></scene>')
    assert scene_spp(SceneSpec(scene)) == 8
    with pytest.raises(QuekaroError, match="sample_count 0"):
        scene_spp(SceneSpec(scene, {"spp": "0"}))


def test_a_level_off_job_is_one_unit_as_mitsuba_renders_it():
    """Level off: one unit once the spp is known (Mitsuba's own render call), never fewer than the farm's
    `min_units`; by size (256 px tiles) without the spp; the rule levels' count does not depend on the spp."""
    assert default_unit_count(512, 512, "off") == 4  # spp unknown: tiles by size only
    assert default_unit_count(512, 512, "off", spp=64) == default_unit_count(4096, 4096, "off", spp=4096) == 1
    assert default_unit_count(512, 512, "off", min_units=8, spp=64) == 8  # a farm's agents each get some
    assert default_unit_count(512, 512, "S", spp=1) == default_unit_count(512, 512, "S", spp=4096) == 84


def test_a_farms_units_are_larger_where_the_rules_run_and_still_several_per_agent():
    """A farm's unit pays an award and an upload besides its render call (default_unit_count): 90 px units
    where the rules run, never fewer than the farm's minimum, and level off as in one process."""
    assert default_unit_count(512, 512, "S", farm=True) == 32 < default_unit_count(512, 512, "S")
    assert default_unit_count(512, 512, "VB", min_units=56, farm=True) == 56  # 16 agents: 3 each + 8
    assert default_unit_count(512, 512, "off", spp=64, farm=True) == default_unit_count(512, 512, "off", spp=64)
    assert default_unit_count(64, 64, "S", farm=True) == 1


def test_a_job_whose_defines_an_http_header_cannot_carry_is_refused_naming_the_longest(tmp_path) -> None:
    """The job travels in a header (aiohttp reads 8190 bytes of one): past JOB_HEADER_MAX it is refused by
    `quekaro submit` before anything is packed or sent, naming -D and its longest value."""
    import subprocess
    import sys

    from core.model.job import JOB_HEADER_MAX, JobSpec

    fits = JobSpec({"a": "x" * (JOB_HEADER_MAX - 200)})
    assert len(fits.header()) <= JOB_HEADER_MAX
    with pytest.raises(QuekaroError, match=r"-D: the job's parameters and options take \d+ bytes, over the 8000 .*"
                                           r"-D long=\.\.\., 9000 characters"):
        JobSpec({"a": "1", "long": "y" * 9000}).header()
    repo = Path(__file__).resolve().parent.parent
    done = subprocess.run([sys.executable, "-m", "quekaro", "submit", str(repo / "scenes" / "cbox.xml"), "-D",
                           "res=" + "9" * 9000, "--home", str(tmp_path / "nofarm")], capture_output=True, text=True,
                          cwd=repo, timeout=120)
    assert done.returncode == 2 and "-D: the job's parameters and options take" in done.stderr, done.stderr
    assert "not running" not in done.stderr and "Traceback" not in done.stderr
