"""The command line a Mitsuba user expects: every `--help` names itself `quekaro ...`; `render` takes
several scenes, -o as a file or a folder, -t, and shows a progress bar; `agents` and `logs` read a real
local farm."""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from disk_support import fill, small_tmpfs

from core.errors import QuekaroError
from core.home import AGENTS_ALLOW, FARM_FILE
from core.model.job import RenderOptions, SceneSpec
from farm.local import LocalFarm
from planning.jobplan import plan_job
from planning.pipeline import Composed, write_outputs
from quekaro.cli import OWNERS, build_parser
from quekaro.cmd_farm import follow_log
from quekaro.cmd_render import outputs

REPO = Path(__file__).resolve().parent.parent
SCENES = REPO / "scenes"


def quekaro(*args: str, cwd: Path | None = None, timeout: float = 300,
            env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "quekaro", *args], capture_output=True, text=True, cwd=cwd,
                          timeout=timeout, env=env)


def subcommands(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    found = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                found.append((*path, name))
                found += subcommands(sub, (*path, name))
    return found


def test_every_help_names_itself_quekaro() -> None:
    commands = subcommands(build_parser())
    assert ("agent",) in commands and ("ca", "issue") in commands and ("rules", "check") in commands
    for command in [*commands, ("bench", "fuzzy")]:
        done = quekaro(*command, "--help", timeout=60)
        assert done.returncode == 0, (command, done.stderr)
        usage = done.stdout.split("\n", 1)[0]
        assert usage.startswith(f"usage: quekaro {' '.join(command)}"), (command, usage)


def test_each_command_imports_the_module_that_registers_it() -> None:
    """OWNERS names, for each built-in command, the one module a run of it imports: it must register that
    command, and no built-in command may be missing from it."""
    everything = {c[0] for c in subcommands(build_parser())}
    assert set(OWNERS) == everything - {"bench"}  # bench comes through the entry point
    for name in OWNERS:
        assert (name,) in subcommands(build_parser(name)), name
    done = subprocess.run([sys.executable, "-c", "import sys; from quekaro.cli import build_parser; "
                           "build_parser('render'); print('farm.local' in sys.modules)"],
                          capture_output=True, text=True, cwd=REPO, timeout=60)
    assert done.stdout.strip() == "False", done.stderr  # `quekaro render` leaves the farm unloaded


@pytest.mark.slow
def test_a_render_plans_and_renders_in_its_render_process_and_never_imports_mitsuba(tmp_path: Path) -> None:
    # The command's own process composes and writes; Mitsuba's import, variant and shutdown are the child's.
    code = ("import sys; from quekaro.cli import main; "
            f"code = main(['render', {str(SCENES / 'cbox.xml')!r}, '-D', 'res=48', '--opt', 'S', '--adaptive', "
            "'--spp', '8', '-t', '1', '--no-progress', '-o', 'out.exr']); "
            "print(code, 'mitsuba' in sys.modules, 'drjit' in sys.modules)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert done.stdout.split()[-3:] == ["0", "False", "False"], done.stderr
    report = json.loads((tmp_path / "out.json").read_text())
    assert report["totals"]["prepass_seconds"] > 0 and report["adaptive"]  # it was planned, pre-pass and all
    assert {u["agent"] for u in report["units"]} == {None}


def test_outputs_for_one_scene_a_folder_and_several() -> None:
    a, b = Path("s/a.xml"), Path("t/b.xml")
    assert outputs([a], Path("x/one.exr")) == [Path("x/one.exr")]
    assert outputs([a, b], Path("renders")) == [Path("renders/a.exr"), Path("renders/b.exr")]
    with pytest.raises(QuekaroError, match="need a folder"):
        outputs([a, b], Path("x/one.exr"))
    with pytest.raises(QuekaroError, match=r"a\.exr"):
        outputs([a, Path("u/a.xml")], Path("renders"))
    assert outputs([a], Path("renders.v2")) == [Path("renders.v2/a.exr")]  # a dotted folder name stays a folder
    for other in ("x/one.png", "x/one.JPG", "x/one.hdr", "x/one.json"):  # .json made a folder named one.json
        with pytest.raises(QuekaroError, match=r"film's file_format asks \(EXR, PFM or RGBE\).*give -o x/one\.exr"):
            outputs([a], Path(other))
    for film_file in ("x/one.pfm", "x/one.rgbe"):  # a film's own suffixes name the file (the film sets the suffix)
        assert outputs([a], Path(film_file)) == [Path(film_file)]


def test_render_refuses_an_output_it_cannot_write_before_rendering(tmp_path: Path) -> None:
    (tmp_path / "a-file").write_text("not a folder")
    out = tmp_path / "a-file" / "renders"
    done = quekaro("render", str(SCENES / "cbox.xml"), str(SCENES / "glass-corner.xml"), "-D", "res=16",
                   "--no-progress", "-o", str(out), cwd=tmp_path)
    assert done.returncode == 2 and f"-o {out}: cannot write in {out}" in done.stderr, done.stderr
    assert "report:" not in done.stdout  # refused before the first scene rendered
    done = quekaro("render", str(SCENES / "cbox.xml"), str(SCENES / "glass-corner.xml"), "-D", "res=16",
                   "--no-progress", "-o", str(tmp_path / "a-file"), cwd=tmp_path)
    assert done.returncode == 2 and f"{tmp_path / 'a-file'} is a file, not a folder" in done.stderr, done.stderr


@pytest.mark.slow
@pytest.mark.parametrize("free", [16 << 10, 36 << 10])
def test_a_render_onto_a_full_disk_says_so_and_leaves_no_part_of_its_outputs(tmp_path: Path, free: int) -> None:
    """The PNG is written beside the image: with room for it and not for the EXR (16 KiB), or for both and
    not the report (36 KiB), a full disk left an image without a report or a PNG without its image."""
    with small_tmpfs(tmp_path / "small", "128k", free=free) as disk:
        done = quekaro("render", str(SCENES / "cbox.xml"), "-D", "res=64", "-D", "spp=4", "-t", "1", "--no-progress",
                       "-o", str(disk / "x.exr"))
        left = sorted(p.name for p in disk.iterdir())
    assert done.returncode == 2 and "x." in done.stderr and "Traceback" not in done.stderr, done.stderr[-2000:]
    assert left == ["filler"], left


@pytest.mark.slow
def test_a_render_again_to_the_same_output_on_a_full_disk_leaves_the_earlier_files_as_they_were(
        tmp_path: Path) -> None:
    """The new image, PNG and report are written beside the earlier render's three and replace them only
    together: with 36 KiB free, less than the new three need beside the old, whichever write fails, the
    earlier three stay as they were (tests/test_cli.py's in-process test fails the report itself)."""
    with small_tmpfs(tmp_path / "small", "256k") as disk:
        args = ["render", str(SCENES / "cbox.xml"), "-D", "res=64", "-D", "spp=4", "-t", "1", "--no-progress",
                "-o", str(disk / "x.exr")]
        assert quekaro(*args).returncode == 0
        before = {p.name: p.read_bytes() for p in disk.iterdir()}
        fill(disk, 36 << 10)
        done = quekaro(*args)
        after = {p.name: p.read_bytes() for p in disk.iterdir() if p.name != "filler"}
    assert sorted(before) == ["x.exr", "x.json", "x.png"], sorted(before)
    assert done.returncode == 2 and "x." in done.stderr and "Traceback" not in done.stderr, done.stderr[-2000:]
    assert after == before


def test_outputs_that_fail_at_the_report_leave_an_earlier_renders_three_files(tmp_path: Path) -> None:
    """All three or none, whichever write fails: here the report (a value JSON cannot hold), after the
    image and the PNG were written. The earlier image and PNG were replaced and then removed, leaving
    its report about an image that was gone."""
    plan = plan_job(SceneSpec(SCENES / "cbox.xml", {"res": "16"}), RenderOptions(spp=1, threads=1), seed=1)
    out = tmp_path / "x.exr"
    first = Composed(np.full((3, 16, 16), 0.5, np.float32), ("R", "G", "B"), {}, [])
    write_outputs(plan, first, out, time.perf_counter())
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    second = Composed(np.full((3, 16, 16), 0.25, np.float32), ("R", "G", "B"), {}, [])
    with pytest.raises(TypeError):
        write_outputs(plan, second, out, time.perf_counter(), {"unserialisable": object()})
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
    write_outputs(plan, second, out, time.perf_counter())
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(before) and out.read_bytes() != before["x.exr"]


def test_render_several_scenes_into_a_folder_with_progress(tmp_path: Path) -> None:
    done = quekaro("render", str(SCENES / "cbox.xml"), str(SCENES / "glass-corner.xml"), "-D", "res=32",
                   "--spp", "4", "-t", "1", "--units", "4", "-o", str(tmp_path / "out"), cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    for stem in ("cbox", "glass-corner"):
        report = json.loads((tmp_path / "out" / f"{stem}.json").read_text())
        assert report["image"]["width"] == 32 and (tmp_path / "out" / f"{stem}.exr").is_file()
    assert "4/4 units" in done.stdout and "spp" in done.stdout


@pytest.mark.slow
def test_a_farm_leaves_no_folder_of_pyjabber_in_the_temporary_folder(tmp_path: Path) -> None:
    """pyjabber makes a folder at import in every process that imports spade (the master and agents) and
    never removes it itself."""
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    done = quekaro("demo", "--home", str(tmp_path / "farm"), "--agents", "2", "--threads", "1",
                   "-o", str(tmp_path / "demo.exr"), cwd=tmp_path, env={**os.environ, "TMPDIR": str(scratch)})
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "demo.exr").is_file()
    assert not list(scratch.glob("pyjabber_xep0363_*"))
    # The summary's seconds are the report's whole job, not its composition alone (they were labelled so)
    totals = json.loads((tmp_path / "demo.json").read_text())["totals"]
    assert f"{totals['units']} units, {totals['seconds']:.1f} s for the job (upload to image)" in done.stdout


@pytest.mark.slow
def test_one_bad_scene_of_several_does_not_stop_the_others(tmp_path: Path) -> None:
    (tmp_path / "broken.xml").write_text('<scene version="3.0.0"><default name="res" value="8"/><shape '
                                         'type="no_such_plugin_here"><integer name="n" value="$res"/></shape></scene>')
    done = quekaro("render", str(SCENES / "cbox.xml"), str(tmp_path / "broken.xml"), str(SCENES / "glass-corner.xml"),
                   "-D", "res=16", "--spp", "2", "-t", "1", "--no-progress", "-o", str(tmp_path / "out"), cwd=tmp_path)
    assert done.returncode == 2, done.stderr
    assert "broken.xml" in done.stderr and "no_such_plugin_here" in done.stderr
    assert f"1 of 3 scenes failed: {tmp_path / 'broken.xml'}" in done.stderr and "Traceback" not in done.stderr
    assert {p.name for p in (tmp_path / "out").glob("*.exr")} == {"cbox.exr", "glass-corner.exr"}


NO_SENSOR = '<scene version="3.0.0"><integrator type="path"/><shape type="sphere"/></scene>'
NO_INTEGRATOR = ('<scene version="3.0.0"><sensor type="perspective"><film type="hdrfilm"><integer name="width" '
                 'value="16"/><integer name="height" value="12"/></film></sensor><shape type="sphere"/></scene>')


@pytest.mark.parametrize(("text", "args", "said"), [
    (NO_SENSOR, ["--opt", "off"], "the scene has no sensor"),
    (NO_SENSOR, ["--opt", "S"], "the scene has no sensor"),
    (NO_INTEGRATOR, ["--opt", "off"], "the scene names no integrator"),
    (NO_INTEGRATOR, ["--opt", "S", "--adaptive"], "the scene names no integrator"),
])
def test_a_scene_mitsuba_cannot_render_is_refused_naming_it(tmp_path: Path, text: str, args: list[str],
                                                            said: str) -> None:
    """Mitsuba loads a scene without a sensor, or without an integrator, and renders nothing ("No integrator
    specified for scene"): the job failed at its first unit, planning raised an IndexError or an
    AttributeError, or a path integrator rendered what plain Mitsuba refuses."""
    (tmp_path / "odd.xml").write_text(text)
    done = quekaro("render", str(tmp_path / "odd.xml"), *args, "--spp", "2", "-t", "1", "--no-progress",
                   "-o", str(tmp_path / "out.exr"), cwd=tmp_path)
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
    assert f"odd.xml: {said}" in done.stderr and "unit 0" not in done.stderr, done.stderr


def test_a_scene_without_an_integrator_renders_with_the_one_the_user_gives(tmp_path: Path) -> None:
    (tmp_path / "odd.xml").write_text(NO_INTEGRATOR)
    done = quekaro("render", str(tmp_path / "odd.xml"), "--integrator", "path", "--spp", "2", "-t", "1",
                   "--no-progress", "-o", str(tmp_path / "out.exr"), cwd=tmp_path)
    assert done.returncode == 0 and (tmp_path / "out.exr").is_file(), done.stderr


@pytest.mark.parametrize("name", ["no-such-scene.xml", "a-folder"])
def test_render_of_a_scene_that_cannot_be_read_names_it(tmp_path: Path, name: str) -> None:
    (tmp_path / "a-folder").mkdir()
    done = quekaro("render", str(tmp_path / name), "--no-progress", "-o", str(tmp_path / "out.exr"), cwd=tmp_path)
    assert done.returncode == 2, done.stderr
    assert f"quekaro: error: {tmp_path / name}: " in done.stderr and "Traceback" not in done.stderr
    assert not (tmp_path / "out.exr").exists()


def test_logs_lists_tails_and_follows(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    logs = tmp_path / "logs"
    logs.mkdir()
    (logs / "master.log").write_text("".join(f"line {i}\n" for i in range(100)))
    (logs / "agent-0.log").write_text("agent\n")
    listed = quekaro("logs", "--home", str(tmp_path))
    assert listed.returncode == 0 and "master" in listed.stdout and "agent-0" in listed.stdout
    tail = quekaro("logs", "master", "-n", "3", "--home", str(tmp_path))
    assert tail.stdout.split() == ["line", "97", "line", "98", "line", "99"]
    missing = quekaro("logs", "agent-9", "--home", str(tmp_path))
    assert missing.returncode == 2 and "agent-0" in missing.stderr
    follow = subprocess.Popen([sys.executable, "-m", "quekaro", "logs", "agent-0", "-f", "--home", str(tmp_path)],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert follow.stdout.readline() == "agent\n"
        with (logs / "agent-0.log").open("a") as log:
            log.write("appended later\n")
        assert follow.stdout.readline() == "appended later\n"
    finally:
        follow.kill()
        follow.wait()


@pytest.mark.slow
def test_a_farm_short_of_space_says_so_at_start_and_while_a_job_waits(tmp_path: Path) -> None:
    """A home under the master's 64 MiB started without a word, and `--wait` showed a job 'running' while
    it sat paused for ever; only `quekaro status` said why."""
    with small_tmpfs(tmp_path / "small", "48m") as disk:
        up = subprocess.Popen([sys.executable, "-m", "quekaro", "up", "--agents", "1", "--threads", "1", "--home",
                               str(disk / "home")], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            assert "farm up" in up.stdout.readline()
            assert "MiB free; the master pauses every job below 64 MiB" in up.stderr.readline()
            sent = quekaro("submit", str(SCENES / "cbox.xml"), "-D", "res=32", "--spp", "4", "--home",
                           str(disk / "home"))
            assert sent.returncode == 0, sent.stderr
            job_id = sent.stdout.split()[0]
            with pytest.raises(subprocess.TimeoutExpired) as watching:
                subprocess.run([sys.executable, "-m", "quekaro", "watch", job_id, "--home", str(disk / "home")],
                               capture_output=True, text=True, timeout=8)
            shown = (watching.value.stdout or b"").decode(errors="replace")
            assert "paused: disk full on the master" in shown, shown[-2000:]
        finally:
            up.terminate()
            up.wait(60)


@pytest.mark.slow
def test_agents_lists_a_real_farms_agents(tmp_path: Path) -> None:
    with LocalFarm(tmp_path / "farm", agents=2, threads=1) as farm:
        farm.wait_for_agents()
        done = quekaro("submit", str(SCENES / "cbox.xml"), "-D", "res=32", "--spp", "4", "--units", "4", "--wait",
                       "--home", str(farm.home))
        assert done.returncode == 0, done.stderr
        job_id = done.stdout.split()[0]
        unit = quekaro("status", job_id, "--unit", "0", "--home", str(farm.home))
        assert unit.returncode == 0, unit.stderr
        lines = unit.stdout.splitlines()
        assert lines[0] == f"unit 0 of job {job_id}: done" and "attempt by agent-" in lines[1], lines
        moves = [line.split("  ")[2] for line in lines if " -> " in line]  # its story, oldest first
        assert moves[0] == "pending -> announced" and moves[-1] == "awarded -> done", lines
        assert lines[-1].endswith(")") and f"(tile-{job_id}-0-" in lines[-1], lines
        missing = quekaro("status", job_id, "--unit", "99", "--home", str(farm.home))
        assert missing.returncode != 0 and f"job {job_id} has no unit 99" in missing.stderr, missing.stderr
        time.sleep(0.5)
        listed = quekaro("agents", "--json", "--home", str(farm.home))
        assert listed.returncode == 0, listed.stderr
        agents = json.loads(listed.stdout)
        assert len(agents) == 2 and sum(a["units_done"] for a in agents) == 4
        assert {a["state"] for a in agents} == {"idle"} and all(a["last_seen_s"] < 15 for a in agents)
        table = quekaro("agents", "--home", str(farm.home))
        assert table.stdout.count("idle") == 2
        master = quekaro("logs", "master", "-n", "1000", "--home", str(farm.home))
        assert master.returncode == 0 and "up: HTTP" in master.stdout and ": every unit done" in master.stdout
        assert quekaro("logs", "master", "-n", "0", "--home", str(farm.home)).stdout == ""
        assert "xmpp" in quekaro("logs", "--home", str(farm.home)).stdout  # the help offers it
        assert quekaro("logs", "xmpp", "--home", str(farm.home)).returncode == 0

        # A second farm on this home would delete its farm.json and accounts and empty its allow-list.
        allowed = (farm.home / AGENTS_ALLOW).read_text()
        second = quekaro("up", "--agents", "1", "--threads", "1", "--home", str(farm.home), timeout=60)
        assert second.returncode != 0 and f"a farm is already running in {farm.home}" in second.stderr
        assert (farm.home / AGENTS_ALLOW).read_text() == allowed and (farm.home / FARM_FILE).is_file()
        assert len(farm.client().agents()) == 2


def test_a_reader_that_leaves_the_pipe_gets_no_traceback(tmp_path: Path) -> None:
    (tmp_path / "logs").mkdir()
    (tmp_path / "logs" / "master.log").write_text("".join(f"line {i}\n" for i in range(100_000)))
    cmd = f"{sys.executable} -m quekaro logs master -n 100000 --home {tmp_path} | head -1"
    done = subprocess.run(["bash", "-c", cmd], capture_output=True, text=True, cwd=REPO, timeout=60)
    assert done.stdout == "line 0\n" and "Traceback" not in done.stderr and "BrokenPipe" not in done.stderr


@pytest.mark.parametrize(("args", "said"), [
    (["--url", "notaurl", "--token-file", "TOKEN"], "--url 'notaurl': the master's URL starts with http://"),
    (["--url", "http://127.0.0.1:9", "--token-file", "."], "admin token file . is not a file"),
    (["--url", "http://127.0.0.1:9", "--token-file", "TOKEN", "--ca-file", "/no/ca.pem"],
     "--ca-file /no/ca.pem: the master at http://127.0.0.1:9 speaks plain HTTP"),
])
def test_a_farm_location_that_cannot_work_is_refused_naming_it(tmp_path: Path, args: list[str], said: str) -> None:
    (tmp_path / "TOKEN").write_text("x")
    done = quekaro("status", *args, cwd=tmp_path)
    assert done.returncode == 2 and said in done.stderr and "Traceback" not in done.stderr, done.stderr


def test_follow_log_prints_the_last_lines(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    path = tmp_path / "x.log"
    path.write_text("a\nb\nc\n")
    follow_log(path, 2, follow=False)
    assert capsys.readouterr().out == "b\nc\n"


def test_a_film_file_that_cannot_hold_the_integrators_channels_is_refused_before_rendering(tmp_path: Path) -> None:
    """A PFM film with the aov integrator: plain Mitsuba renders it and fails writing the file; quekaro
    refuses at planning, naming the file, the film's format and the channels, and writes nothing."""
    import mitsuba as mi

    from core.model.job import SceneSpec
    from core.scene.scene import load

    compat = REPO / "tests" / "compat" / "scenes"
    scene = tmp_path / "aov_pfm.xml"
    scene.write_text((compat / "film_pfm.xml").read_text()
                     .replace('<integrator type="path"><integer name="max_depth" value="4"/></integrator>',
                              '<integrator type="aov"><string name="aovs" value="dd.y:depth"/>'
                              '<integrator type="path"/></integrator>')
                     .replace('_room.xml', str(compat / "_room.xml")))
    loaded = load(SceneSpec(scene, {"spp": "1"}), "llvm_ad_rgb", threads=2)
    mi.render(loaded)
    with pytest.raises(RuntimeError, match="write_pfm"):  # the real thing fails at its very end
        loaded.sensors()[0].film().write(str(tmp_path / "mitsuba"))
    done = quekaro("render", str(scene), "-o", str(tmp_path / "out.exr"), "--no-progress")
    assert done.returncode != 0
    assert "aov_pfm.xml: the film's file_format pfm holds colour only" in done.stderr
    assert "'dd.y.T'" in done.stderr and "file_format openexr" in done.stderr
    assert not list(tmp_path.glob("out.*"))
    # The user's --integrator renders instead, and adds no channel: the same film takes its image.
    done = quekaro("render", str(scene), "-D", "spp=2", "--integrator", "path", "-o", str(tmp_path / "out.pfm"),
                   "--no-progress")
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "out.pfm").stat().st_size > 0


def test_an_integrator_override_that_mitsuba_cannot_build_is_refused_before_rendering(tmp_path: Path) -> None:
    """`--integrator aov` needs its `aovs` parameter, which the option cannot give: refused at planning,
    naming the option and Mitsuba's reason, for any film, before a unit renders."""
    scene = REPO / "tests" / "compat" / "scenes" / "crop.xml"
    done = quekaro("render", str(scene), "-D", "spp=2", "--integrator", "aov", "-o", str(tmp_path / "out.exr"),
                   "--no-progress")
    assert done.returncode != 0
    assert "--integrator aov: cannot build integrator aov: " in done.stderr and '"aovs"' in done.stderr
    assert "unit 0" not in done.stderr
    assert not list(tmp_path.glob("out.*"))


def test_a_reference_spp_without_report_accuracy_is_refused(tmp_path: Path) -> None:
    """--ref-spp only sets the spp of --report-accuracy's reference: given alone it would be ignored."""
    scene = REPO / "tests" / "compat" / "scenes" / "crop.xml"
    done = quekaro("render", str(scene), "-D", "spp=2", "--ref-spp", "64", "-o", str(tmp_path / "out.exr"),
                   "--no-progress")
    assert done.returncode != 0
    assert "--ref-spp 64: the reference is rendered only with --report-accuracy" in done.stderr
    assert not list(tmp_path.glob("out.*"))


@pytest.mark.parametrize(("args", "said"), [
    (["--threads", "0"], "--threads 0: each agent needs at least one thread"),
    (["--threads", "-1"], "--threads -1"),
    (["--http-port", "70000"], "--http-port 70000: not a TCP port"),
    (["--rules", "/no/such/rules.xml"], "--rules: /no/such/rules.xml: cannot read"),
    (["--home", "/proc/no-farm"], "--home /proc/no-farm: cannot make the farm's folder there"),
])
def test_up_refuses_options_its_agents_or_master_would_die_of(tmp_path: Path, args: list[str], said: str) -> None:
    """Each of these started a farm whose agents crash-looped (a farm without agents) or whose master never
    came up (120 s of silence), or meant the default (--threads 0)."""
    done = quekaro("up", "--agents", "1", "--home", str(tmp_path / "f"), *args, timeout=60)
    assert done.returncode != 0 and said in done.stderr and "Traceback" not in done.stderr, done.stderr
    assert not (tmp_path / "f").exists()


def test_a_master_that_cannot_start_fails_the_farm_at_once(tmp_path: Path) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        start = time.monotonic()
        with pytest.raises(QuekaroError, match=r"the master exited with status \d+ as it started: .*in use"):
            LocalFarm(tmp_path / "farm", agents=1, threads=1, http_port=taken.getsockname()[1]).__enter__()
        assert time.monotonic() - start < 60  # it waited START_TIMEOUT_S (120 s) in silence


def test_more_rule_files_than_agents_are_refused_before_the_farm_starts(tmp_path: Path) -> None:
    """Agent i takes rule file i (mod their count): with more files than agents some would never be used."""
    rules = REPO / "rules" / "pathtracing.xml"
    done = quekaro("up", "--agents", "1", "--rules", str(rules), "--rules", str(rules), "--home", str(tmp_path / "f"))
    assert done.returncode != 0
    assert "--rules: 2 rule files for 1 agents" in done.stderr and "--agents 2 or more" in done.stderr
    assert not (tmp_path / "f").exists()
