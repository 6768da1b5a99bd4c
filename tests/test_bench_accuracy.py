"""The accuracy benchmark at its smallest size (in-process pipeline), its grid parsing and CPU timing."""

from __future__ import annotations

import argparse
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from PIL import Image

from bench import accuracy as bench_accuracy
from core.errors import QuekaroError
from core.image.imageio import read_image
from core.model.job import SceneSpec
from fuzzy import load_rulebase


def args_for(tmp_path, *extra: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    bench_accuracy.add_arguments(parser)
    args = parser.parse_args(["--res", "32", "--spp", "4", "--ref-spp", "32", "--threads", "1",
                              "--levels", "off,S", "--agents", "1", "--out", str(tmp_path / "out"),
                              "--cache", str(tmp_path / "cache"), *extra])
    args.json = True
    return args


@pytest.mark.slow
def test_inprocess_grid_json_has_cells_and_baseline(tmp_path):
    """A suite name and a user's scene file (the volumetric one, by path, with its -D), in one run."""
    volume = Path(bench_accuracy.__file__).parent / "scenes" / "volume.xml"
    result = bench_accuracy.run(args_for(tmp_path, "--inprocess", "caustic-corner", str(volume), "-D", "spp=4"))
    cells = [c for c in result["cells"] if c["scene"] == "caustic-corner"]
    assert [c["scene"] for c in result["cells"]][2:] == ["volume", "volume"]
    assert result["scenes"]["volume"]["defines"] == {"res": "32", "spp": "4"}
    assert [(c["agents"], c["level"]) for c in cells] == [(1, "off"), (1, "S")]
    for c in cells:
        assert c["seconds"] > 0 and c["cpu_seconds"] > 0 and c["first_seconds"] > 0  # the warm-up's time
        assert len(c["seconds_runs"]) == 2 and len(c["relmse_runs"]) == 3  # two timed runs and the warm-up
        assert 0 < c["mean_pixel_diff_percent"] < 50 and 0 < c["relmse"] < 10 and 0 <= c["flip"] <= 1
        assert c["uniform_spp"] >= 1 and 0 < c["uniform_relmse"] < 10
        assert c["spp_min"] >= 1 and c["units"] >= 1
        assert c["seam_border_strips"] > 0 or c["units"] == 1, c
        assert isinstance(c["seam_seam"], bool)
        assert c["units"] == 1 or c["uniform_seam_border_strips"] > 0  # plain Mitsuba measured at its borders
    off = cells[0]
    assert off["spp_min"] == off["spp_max"] == 4  # level off applies no rules
    assert list((tmp_path / "cache" / "references").glob("caustic-corner-*.exr"))  # cached for next time
    diff = Image.open(tmp_path / "out" / "accuracy-diff" / "caustic-corner-S.png")
    assert diff.mode == "L" and diff.size[0] == diff.size[1] > 0  # 8-bit grey, the scene's square image
    table = (tmp_path / "out" / "accuracy.md").read_text()
    s_row = f"| caustic-corner | 1 | S | {cells[1]['seconds']:.1f} | {cells[1]['first_seconds']:.1f} |"
    assert "| 1 |" in table and s_row in table
    again = bench_accuracy.run(args_for(tmp_path, "--inprocess", "--resume", "caustic-corner", str(volume),
                                        "-D", "spp=4"))
    assert again["cells"] == result["cells"]  # both scenes were kept, none measured again
    assert again["resumed"] == ["caustic-corner", "volume"]
    assert "--resume" in (tmp_path / "out" / "accuracy.md").read_text()


COMPAT = Path(__file__).parent / "compat" / "scenes"
REPO = Path(__file__).resolve().parent.parent


def one_cell(tmp_path: Path, mode: str, scene: Path, spp: int, ref_spp: int, threads: int,
             *extra: str) -> dict:
    """`bench accuracy` at level off, one agent, one timed run: its result."""
    parser = argparse.ArgumentParser()
    bench_accuracy.add_arguments(parser)
    args = parser.parse_args(["--spp", str(spp), "--ref-spp", str(ref_spp), "--threads", str(threads), "--levels",
                              "off", "--agents", "1", "--runs", "1", "--out", str(tmp_path / "out"), "--cache",
                              str(tmp_path / "cache"), *([mode] if mode != "farm" else []), *extra, str(scene)])
    args.json = True
    return bench_accuracy.run(args)


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["--inprocess", "farm"])
def test_a_scene_whose_film_writes_pfm_is_measured_from_the_file_the_job_wrote(tmp_path, mode):
    """The job's image is the film's file (.pfm here, as Mitsuba names it), in one process and fetched
    from a farm; the benchmark read OUT.exr, which no job had written."""
    [cell] = one_cell(tmp_path, mode, COMPAT / "film_pfm.xml", 4, 32, 1)["cells"]
    assert cell["level"] == "off" and 0 < cell["relmse"] < 10 and cell["uniform_spp"] >= 1


@pytest.mark.slow
@pytest.mark.parametrize(("mode", "scene", "asked"), [
    ("--inprocess", "two_sensors.xml", ["-s", "1", "--depth", "2"]),
    ("farm", "searchpath/scene/needs_a.xml", ["-a", "searchpath/common", "--integrator", "direct"]),
])
def test_the_benchmark_computes_what_the_jobs_were_asked_to(tmp_path, mode, scene, asked):
    """-s, -a, --integrator and --depth reach the jobs, the reference and the uniform baseline alike, as
    they do for `quekaro render --report-accuracy`: the benchmark refused them as unknown arguments, so a
    scene that needs a search folder could not be measured at all."""
    asked = [str(COMPAT / a) if a.startswith("searchpath") else a for a in asked]
    result = one_cell(tmp_path, mode, COMPAT / scene, 64, 256, 2, *asked)
    [cell] = result["cells"]
    assert 0 < cell["relmse"] < 0.05 and cell["uniform_spp"] >= 1
    assert cell["mean_pixel_diff_percent"] < 5 and cell["uniform_mean_pixel_diff_percent"] < 8  # depth 2: -13 %
    [ref] = (tmp_path / "cache" / "references").glob("*.exr")
    if "-s" in asked:  # the second sensor's film is 40x48, the first's 48x40
        assert read_image(ref).shape[:2] == (48, 40)
    assert result["asked"] == {k: v for k, v in (("sensor", 1), ("depth", 2), ("integrator", "direct"))
                               if f"--{k}" in asked or (k == "sensor" and "-s" in asked)}


def test_resume_refuses_other_settings_and_missing_files(tmp_path):
    with pytest.raises(QuekaroError, match="does not exist"):
        bench_accuracy.run(args_for(tmp_path, "--resume"))
    args = args_for(tmp_path)
    settings = bench_accuracy.run_settings(args, [1], ["off", "S"])
    cell = {"scene": "caustic-corner", "level": "off", "seconds": 1.0}
    bench_accuracy.write_partial(settings, [cell], args.out)
    assert bench_accuracy.resumed_cells(args.out, settings) == [cell]
    with pytest.raises(QuekaroError, match="spp=4, this run asks for 8"):
        bench_accuracy.resumed_cells(args.out, {**settings, "spp": 8})


def test_a_damaged_or_empty_partial_run_is_refused_naming_the_file_and_line(tmp_path):
    """The progress file is written whole or not at all; one cut short by hand, or empty, is refused with
    the way out (run without --resume), not a JSONDecodeError."""
    args = args_for(tmp_path)
    settings = bench_accuracy.run_settings(args, [1], ["off", "S"])
    bench_accuracy.write_partial(settings, [{"scene": "cbox", "level": "off"}] * 3, args.out)
    path = args.out / "accuracy.partial.jsonl"
    assert [p.name for p in args.out.iterdir()] == [path.name]  # no temporary file left beside it
    path.write_text(path.read_text()[:-20])
    with pytest.raises(QuekaroError, match=rf"{path} line 4 is not JSON .*run without --resume"):
        bench_accuracy.resumed_cells(args.out, settings)
    path.write_text("")
    with pytest.raises(QuekaroError, match=r"has no settings line \(empty, or written by an older version\)"):
        bench_accuracy.resumed_cells(args.out, settings)


def test_scenes_of_one_file_name_are_told_apart_by_their_folders(tmp_path):
    """Two `scene.xml` in two folders were one section, one set of image files, and one plot panel; now
    each is named by its folder. One file given twice is refused."""
    for folder in ("sc", "sc2"):
        (tmp_path / folder).mkdir()
        (tmp_path / folder / "a.xml").write_text("<scene version='3.0.0'/>")
    scenes, _, _ = bench_accuracy.parse_grid(args_for(tmp_path, str(tmp_path / "sc" / "a.xml"),
                                                      str(tmp_path / "sc2" / "a.xml"), "caustic-corner"))
    assert [s.name for s in scenes] == ["sc-a", "sc2-a", "caustic-corner"]
    with pytest.raises(QuekaroError, match=r"a\.xml given twice"):
        bench_accuracy.parse_grid(args_for(tmp_path, str(tmp_path / "sc" / "a.xml"),
                                           str(tmp_path / "sc" / ".." / "sc" / "a.xml")))


@pytest.mark.slow
def test_an_interrupted_run_says_what_it_kept_and_how_to_go_on(tmp_path):
    """Ctrl-C (SIGINT) after the first scene: the exit is 130 as before, and the output names the scenes
    kept and --resume (it printed nothing)."""
    scenes = []
    for name in ("one", "two"):
        scenes.append(tmp_path / f"{name}.xml")
        scenes[-1].write_text(BALL.replace("'R'", "'1.0'"))
    partial = tmp_path / "out" / "accuracy.partial.jsonl"
    cmd = [sys.executable, "-m", "quekaro", "bench", "accuracy", "--inprocess", "--levels", "off", "--spp", "4",
           "--ref-spp", "16", "--threads", "1", "--runs", "1", "--out", str(tmp_path / "out"), "--cache",
           str(tmp_path / "cache"), *map(str, scenes)]
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 240
    while not partial.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.2)
    assert proc.poll() is None, proc.communicate()
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert f"interrupted in two; the finished scenes (one) are kept in {partial}" in err and "--resume" in err, err


# 64 px a side: at 24 a sample of this scene (most rays miss the ball) cost too little to time against a
# process's start, and the uniform baseline's spp fit was refused now and then (planning.accuracy.fit_spp_line).
BALL = ("<scene version='3.0.0'><integrator type='path'/><sensor type='perspective'><film type='hdrfilm'>"
        "<integer name='width' value='64'/><integer name='height' value='64'/></film>"
        "<sampler type='independent'/></sensor><emitter type='constant'/>"
        "<shape type='sphere'><point name='center' x='0' y='0' z='4'/><float name='radius' value='R'/>"
        "</shape></scene>")


@pytest.mark.slow
def test_resume_measures_again_a_scene_whose_files_changed(tmp_path):
    """--resume kept a scene's figures after its file was edited (the cached reference follows the files,
    the kept cells did not); now that scene is measured again and the output says so."""
    scene, text = tmp_path / "ball.xml", BALL
    scene.write_text(text.replace("'R'", "'0.8'"))
    first = one_cell(tmp_path, "--inprocess", scene, 4, 16, 1)
    scene.write_text(text.replace("'R'", "'1.2'"))
    again = one_cell(tmp_path, "--inprocess", scene, 4, 16, 1, "--resume")
    assert again["resumed"] == [] and again["changed"] == ["ball"]
    assert again["cells"][0]["relmse"] != first["cells"][0]["relmse"]
    assert "measured again, their files changed since the partial run: ball" in \
        (tmp_path / "out" / "accuracy.md").read_text()
    kept = one_cell(tmp_path, "--inprocess", scene, 4, 16, 1, "--resume")
    assert kept["resumed"] == ["ball"] and kept["cells"] == again["cells"]


def test_resume_refuses_a_partial_run_of_other_rules(tmp_path):
    """A key only one side has differs too: a run with --rules does not resume one with the default rules,
    nor the other way round."""
    args = args_for(tmp_path)
    default = bench_accuracy.run_settings(args, [1], ["off", "S"])
    retuned = {**default, "rules_digest": "ab" * 32}
    bench_accuracy.write_partial(default, [{"scene": "cbox"}], args.out)
    with pytest.raises(QuekaroError, match="rules_digest=None, this run asks for 'abab"):
        bench_accuracy.resumed_cells(args.out, retuned)
    bench_accuracy.write_partial(retuned, [{"scene": "cbox"}], args.out)
    with pytest.raises(QuekaroError, match=r"rules_digest='abab.*this run asks for None"):
        bench_accuracy.resumed_cells(args.out, default)


def test_a_rule_file_the_planner_cannot_use_is_refused_before_anything_renders(tmp_path):
    bad = tmp_path / "bad.xml"
    bad.write_text(RULES.read_text().replace('<fset label="VB" a="0.9" b="1.6" c="1.6" d="3.0"/>', ""))
    with pytest.raises(QuekaroError, match=r"--rules: .*bad\.xml.*VB"):
        bench_accuracy.run(args_for(tmp_path, "--inprocess", "--rules", str(bad)))
    assert not (tmp_path / "cache").exists() and not (tmp_path / "out").exists()


RULES = Path(bench_accuracy.__file__).parent.parent / "rules" / "pathtracing.xml"


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["--inprocess", "farm"])
def test_the_rule_levels_run_the_rule_file_given(tmp_path, mode):
    """A retune tried on the suite: every Ls consequent raised to VB (about 1.8x the user's spp, where the
    shipped rules spend less than it at level S) reaches the jobs in one process and through a farm's
    bundles, and the output names the file and its rules' digest."""
    raised = tmp_path / "raised.xml"
    raised.write_text(re.sub(r'<consequent name="Ls" label="[^"]+"/>', '<consequent name="Ls" label="VB"/>',
                             RULES.read_text()))
    shipped = one_cell(tmp_path / "shipped", mode, COMPAT / "film_pfm.xml", 4, 32, 1, "--levels", "S")
    retuned = one_cell(tmp_path / "retuned", mode, COMPAT / "film_pfm.xml", 4, 32, 1, "--levels", "S",
                       "--rules", str(raised))
    [s], [r] = shipped["cells"], retuned["cells"]
    assert s["spp_mean"] < 4 < r["spp_mean"]
    header = (tmp_path / "retuned" / "out" / "accuracy.md").read_text().splitlines()[2]
    assert f"rules {raised} (digest {load_rulebase(raised).digest()[:12]})" in header
    assert "rules" not in (tmp_path / "shipped" / "out" / "accuracy.md").read_text().splitlines()[2]


def test_grid_arguments_are_checked(tmp_path):
    with pytest.raises(QuekaroError, match="unknown level 'XL'"):
        bench_accuracy.parse_grid(args_for(tmp_path, "--levels", "off,XL"))
    with pytest.raises(QuekaroError, match="--agents"):
        bench_accuracy.parse_grid(args_for(tmp_path, "--agents", "1,x"))
    with pytest.raises(QuekaroError, match="neither a suite scene"):
        bench_accuracy.parse_grid(args_for(tmp_path, "nope"))
    with pytest.raises(QuekaroError, match="-D 'res'"):
        bench_accuracy.parse_grid(args_for(tmp_path, "-D", "res"))
    with pytest.raises(QuekaroError, match="--runs 0"):
        bench_accuracy.parse_grid(args_for(tmp_path, "--runs", "0"))
    with pytest.raises(QuekaroError, match=r"-D '=3': '' is not a parameter name"):
        bench_accuracy.parse_grid(args_for(tmp_path, "-D", "=3"))
    with pytest.raises(QuekaroError, match=r"--spp 0, --ref-spp 32: at least one sample"):
        bench_accuracy.parse_grid(args_for(tmp_path, "--spp", "0"))
    with pytest.raises(QuekaroError, match=r"--levels 'off,S,off': off given twice"):
        bench_accuracy.parse_grid(args_for(tmp_path, "--levels", "off,S,off"))
    with pytest.raises(QuekaroError, match=r"--rules .*: level off plans with no rules"):
        bench_accuracy.parse_grid(args_for(tmp_path, "--levels", "off", "--rules", str(RULES)))
    # One process is no farm: agent counts other than 1 would be ignored, so they are refused.
    with pytest.raises(QuekaroError, match=r"--agents 2,1,2: --inprocess times one `quekaro render` process"):
        bench_accuracy.parse_grid(args_for(tmp_path, "--agents", "2,1,2", "--inprocess"))
    scenes, agents, levels = bench_accuracy.parse_grid(args_for(tmp_path, "--agents", "1", "--inprocess"))
    assert ([s.name for s in scenes], agents, levels) == (["caustic-corner"], [1], ["off", "S"])
    parser = argparse.ArgumentParser()
    bench_accuracy.add_arguments(parser)
    assert bench_accuracy.parse_grid(parser.parse_args([]))[1] == [1, 2]  # a farm of one agent and of two
    assert bench_accuracy.parse_grid(parser.parse_args(["--inprocess"]))[1] == [1]
    suite, _, _ = bench_accuracy.parse_grid(args_for(tmp_path, "--suite"))
    assert len(suite) >= 6 and {s.role for s in suite} == {"tune", "report"}


def test_tree_cpu_seconds_counts_a_busy_child():
    pid = os.fork()
    if pid == 0:  # the child burns CPU for a moment, then leaves without cleanup
        end = time.process_time() + 0.4
        while time.process_time() < end:
            pass
        os._exit(0)
    try:
        time.sleep(0.35)
        child = bench_accuracy.tree_cpu_seconds([pid])
        assert 0.1 <= child <= 1.0
        assert bench_accuracy.tree_cpu_seconds([os.getpid()]) >= child + 0.05  # the tree includes the child
    finally:
        os.waitpid(pid, 0)


def test_the_render_time_baseline_matches_render_seconds_by_the_slope_alone():
    """A job's render seconds hold no process start, load or writing: the uniform spp at equal render time
    is render seconds / k, not (render seconds - t0) / k, which gave plain Mitsuba about half its samples
    at a cheap level (cbox at level B: 8 spp for 1.24 s of render at 0.08 s a sample). A farm's render
    seconds are its agents' added up, each on threads // agents threads."""
    assert bench_accuracy.render_time_spp(1.24, 0.0795, agents=1, threads=2) == 16
    assert bench_accuracy.render_time_spp(4.0, 0.1, agents=2, threads=2) == 20  # two agents of one thread
    assert bench_accuracy.render_time_spp(4.0, 0.1, agents=4, threads=8) == 10  # four agents of two threads
    assert bench_accuracy.render_time_spp(0.0, 0.1, agents=1, threads=2) == 1


def test_a_scene_path_is_shown_relative_to_the_checkouts_parent_even_through_a_link(tmp_path):
    repo, shown = bench_accuracy.REPO, bench_accuracy._shown
    # ../shared is a link in a CI clone: the name as given counts, not where the link leads.
    assert shown(repo / ".." / "shared" / "scenes" / "x.xml") == "shared/scenes/x.xml"
    assert shown(repo / "bench" / "scenes" / "volume.xml") == f"{repo.name}/bench/scenes/volume.xml"
    link = tmp_path / "link"
    link.symlink_to(repo)
    assert shown(link / "bench" / "x.xml") == f"{repo.name}/bench/x.xml"  # outside, but resolves inside
    assert shown(tmp_path / "other.xml") == str(tmp_path / "other.xml")


def test_an_unbounded_depth_reads_as_words_in_the_table():
    """Mitsuba's max_depth -1 showed as "-1--1"."""
    assert bench_accuracy._depths({"depth_min": -1, "depth_max": -1}) == "unbounded"
    assert bench_accuracy._depths({"depth_min": 3, "depth_max": 6}) == "3-6"
    assert bench_accuracy._depths({"depth_min": 6, "depth_max": 6}) == "6-6"


def test_a_cell_faster_than_plain_mitsubas_least_render_is_not_scored_against_it(tmp_path):
    """A 0.3 s cell against plain Mitsuba whose start-up alone takes 0.37 s: the equal-wall-time baseline
    was clamped to 1 spp, which took longer than the cell, and the median target read PASS. Now the
    baseline says it takes longer, and the target is not measured (neither PASS nor MISS)."""
    args = args_for(tmp_path, "--runs", "1", "--no-warmup")
    spec = SceneSpec(COMPAT / "film_pfm.xml", {})
    cells = [{"agents": 1, "level": "S", "seconds": 0.30, "render_seconds": 0.1, "scene": "a"},
             {"agents": 1, "level": "N", "seconds": 1.00, "render_seconds": 0.1, "scene": "a"}]
    variant = bench_accuracy.job_variant(spec)
    ref = bench_accuracy.reference(spec, 4, 1, tmp_path / "cache", variant)
    uniform = bench_accuracy.uniform_baseline(spec, cells, 1, args, (0.37, 0.01), ref, variant, {})
    assert uniform["S"]["uniform_fits"] is False and uniform["S"]["uniform_spp"] == 1
    assert uniform["N"]["uniform_fits"] is True and uniform["N"]["uniform_spp"] == 63
    for cell in cells:
        cell.update(uniform[cell["level"]], relmse=0.01, mean_pixel_diff_percent=1.0, seam_seam=False)
    [s_target, n_target] = [t for t in bench_accuracy.targets(cells, 1) if t["name"].startswith("level")]
    assert s_target["value"] is None and not s_target["pass"] and "on a the cell took less" in s_target["name"]
    assert n_target["value"] is not None
    table = "\n".join(bench_accuracy.paper_table(cells, "a", ["S", "N"]))
    assert "1 spp (the least; takes longer than the cell)" in table and "63 spp," in table


@pytest.mark.slow
def test_denoised_cells_are_scored_against_raw_uniform_at_their_own_wall_time(tmp_path):
    """--denoise: uniform+denoise (level off) and level S denoised beside the raw S cell; each denoised cell
    read from the denoised image (far below its own raw image's error at 4 spp), scored with raw plain
    Mitsuba at the spp its own wall time buys, the targets and the bias printed with figures; a resumed
    run keeps the denoised cells as they were."""
    args = args_for(tmp_path, "--inprocess", "--denoise", "--levels", "S", "--runs", "1", "--bias-spp", "16")
    result = bench_accuracy.run(args)
    cells = result["cells"]
    assert [(c["level"], c["denoise"]) for c in cells] == [("S", False), ("off", True), ("S", True)]
    assert result["mode"] == "inprocess, denoise"
    for c in cells[1:]:
        assert c["aov_pass_seconds"] > 0 and c["denoise_seconds"] > 0 and c["bias_spp"] == 16
        t0, k = c["uniform_t0_s"], c["uniform_s_per_spp"]
        assert c["uniform_spp"] == max(1, round((c["seconds"] - t0) / k))  # the cell's own wall time
        assert "render_uniform_spp" not in c  # no render-time baseline for a denoised job
    off = cells[1]
    assert off["spp_min"] == off["spp_max"] == 4 and off["relmse"] < 0.5 * off["raw_relmse"]
    assert 0 < off["bias_relmse"] < off["bias_raw_relmse"] and 0 < off["bias_flip"] < 1
    table = (tmp_path / "out" / "accuracy.md").read_text()
    ratio = off["relmse"] / off["uniform_relmse"]
    assert f"| 1 | uniform+denoise | {off['seconds']:.1f} |" in table and f"| {ratio:.3f} |" in table
    assert "the scene as written (its own filter) at 32 spp" in table
    assert re.search(r"denoiser's bias: caustic-corner denoised at 16 spp \(level off, one process, [\d.]+ s\) "
                     r"against the reference: relMSE 0\.\d{4}, FLIP 0\.\d{4}", table)
    for name in ("uniform+denoise", "S+denoise"):
        for metric, limit in (("relMSE", 0.2), ("FLIP", 0.5)):
            assert re.search(rf"target: one process, {re.escape(name)}: median {metric} over 1 scene\(s\) <= "
                             rf"{limit} x raw uniform \(equal wall time\): \d+\.\d{{3}} (met|missed) "
                             rf"\(caustic-corner \d+\.\d{{3}}\)", table), (name, metric)
    [relmse_target] = [t for t in result["denoise_targets"] if t["name"].startswith("one process, uniform+denoise: "
                                                                                   "median relMSE")]
    assert relmse_target["value"] == pytest.approx(ratio)
    bias = Image.open(tmp_path / "out" / "accuracy-diff" / "caustic-corner-denoise-bias.png")
    assert bias.mode == "L" and bias.size == (32, 32)
    assert (tmp_path / "out" / "accuracy-diff" / "caustic-corner-uniform-denoise.png").exists()
    again = bench_accuracy.run(args_for(tmp_path, "--inprocess", "--denoise", "--levels", "S", "--runs", "1",
                                        "--bias-spp", "16", "--resume"))
    assert again["cells"] == cells and again["resumed"] == ["caustic-corner"]


def test_a_raw_run_does_not_resume_a_denoised_one(tmp_path):
    """Denoised cells are never taken for raw ones: the settings differ by denoise (and its bias spp)."""
    raw = bench_accuracy.run_settings(args_for(tmp_path), [1], ["off", "S"])
    assert "denoise" not in raw and "bias_spp" not in raw  # partial runs of older versions still match
    args = args_for(tmp_path, "--denoise")
    denoised = bench_accuracy.run_settings(args, [1], ["off", "S"])
    assert denoised["denoise"] is True and denoised["bias_spp"] == 8  # a quarter of --ref-spp 32
    bench_accuracy.write_partial(denoised, [{"scene": "cbox", "level": "off", "denoise": True}], args.out)
    with pytest.raises(QuekaroError, match="denoise=True, this run asks for None"):
        bench_accuracy.resumed_cells(args.out, raw)
    with pytest.raises(QuekaroError, match="bias_spp=8, this run asks for 4"):
        bench_accuracy.resumed_cells(args.out, bench_accuracy.run_settings(
            args_for(tmp_path, "--denoise", "--bias-spp", "4"), [1], ["off", "S"]))


def test_bias_spp_is_refused_without_denoise_or_below_one(tmp_path):
    with pytest.raises(QuekaroError, match="--bias-spp 64: the denoiser's bias is measured with --denoise only"):
        bench_accuracy.parse_grid(args_for(tmp_path, "--bias-spp", "64"))
    with pytest.raises(QuekaroError, match="--bias-spp 0: at least one"):
        bench_accuracy.parse_grid(args_for(tmp_path, "--denoise", "--bias-spp", "0"))
    assert bench_accuracy.grid(["S", "off"], True) == [("S", False), ("off", False), ("off", True), ("S", True)]
    assert bench_accuracy.grid(["S"], False) == [("S", False)]


def test_denoise_targets_are_medians_over_scenes_of_ratios_to_raw_uniform():
    """Per agent count and denoised setting; a cell faster than plain Mitsuba's 1 spp leaves it unmeasured."""
    def cell(scene, level, relmse, flip, agents=2, fits=True):
        return {"scene": scene, "level": level, "denoise": True, "agents": agents, "relmse": relmse, "flip": flip,
                "uniform_relmse": 0.01, "uniform_flip": 0.2, "uniform_fits": fits}

    cells = [cell("a", "off", 0.001, 0.05), cell("b", "off", 0.003, 0.2), cell("c", "off", 0.002, 0.12),
             cell("a", "S", 0.004, 0.1, fits=False), {"scene": "a", "level": "off", "agents": 2, "relmse": 9.0}]
    relmse, flip, s_relmse, _ = bench_accuracy.denoise_targets(cells, inprocess=False)
    assert relmse["name"].startswith("2-agent farm, uniform+denoise: median relMSE over 3 scene(s) <= 0.2 x")
    assert relmse["value"] == pytest.approx(0.2) and relmse["pass"]
    assert flip["value"] == pytest.approx(0.6) and not flip["pass"]
    assert bench_accuracy.denoise_target_line(flip).endswith(": 0.600 missed (a 0.250, b 1.000, c 0.600)")
    assert s_relmse["value"] is None and bench_accuracy.denoise_target_line(s_relmse).endswith("not measured")


@pytest.mark.slow
def test_progressive_cells_render_every_level_in_passes(tmp_path):
    """--progressive: each cell's jobs ran in passes (their reports say so, level off too), each beside its
    uniform baseline, and the run says its mode."""
    result = bench_accuracy.run(args_for(tmp_path, "--inprocess", "--progressive", "--runs", "1", "caustic-corner"))
    assert result["mode"] == "inprocess, progressive"
    assert [(c["level"], c["progressive"]) for c in result["cells"]] == [("off", True), ("S", True)]
    for cell in result["cells"]:
        assert cell["passes"] > cell["units"] >= 1  # several passes of each unit, merged
        assert cell["uniform_spp"] >= 1 and 0 < cell["uniform_relmse"] < 10
    names = [t["name"] for t in result["targets"] if "median relMSE" in t["name"]]
    assert names == [f"level {level} in passes: median relMSE over 1 scene(s) <= 1.0 x uniform (equal wall time)"
                     for level in ("off", "S")]


@pytest.mark.parametrize("other", ["--adaptive", "--denoise"])
def test_progressive_is_refused_beside_adaptive_and_denoise(tmp_path, other):
    with pytest.raises(QuekaroError, match=f"--progressive with {other}"):
        bench_accuracy.parse_grid(args_for(tmp_path, "--progressive", other))
