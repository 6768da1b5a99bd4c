"""What a person typing `quekaro` reads, without a farm: Mitsuba's flags (--define, --output, --mode, -a "a;b",
-v), levels in any case, "did you mean" for variants, integrators and plugins, errors without C++ locations or
transport prefixes, an unknown -D refused before upload, a stale farm.json named as such, a bad flag answered
with its sub-command's usage, and `quekaro render` of a frame range."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest

from core.errors import QuekaroError, did_you_mean, without_locations
from core.home import ADMIN_TOKEN, FARM_FILE
from core.logs import verbosity
from farm.client import FarmClient, FarmRefusal
from quekaro.cli import build_parser
from quekaro.cmd_farm import parameters_text, sequence_status
from quekaro.cmd_render import search_paths, split_range

REPO = Path(__file__).resolve().parent.parent
CBOX = REPO / "scenes" / "cbox.xml"
NOWHERE = ["--url", "http://127.0.0.1:9", "--token-file", str(REPO / "README.md")]  # a closed port


def quekaro(*args: str, cwd: Path | None = None, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "quekaro", *args], capture_output=True, text=True, cwd=cwd,
                          timeout=timeout)


def parse(*argv: str):
    return build_parser(argv[0]).parse_args(list(argv))


@pytest.mark.parametrize("command", ["render", "submit"])
def test_mitsubas_flags_and_levels_in_any_case(command: str, tmp_path: Path) -> None:
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    args = parse(command, "x.xml", "--define", "res=8", "-D", "spp=2", "--mode", "scalar_rgb", "--opt", "s",
                 "-a", f"{tmp_path / 'a'};{tmp_path / 'b'}", "-a", str(tmp_path / "a"), "-vv")
    assert args.defines == ["res=8", "spp=2"] and args.variant == "scalar_rgb" and args.level == "S"
    assert search_paths(args) == (tmp_path / "a", tmp_path / "b", tmp_path / "a") and args.verbose == 2
    assert parse(command, "x.xml", "--opt", "OFF").level == "off" and parse(command, "x.xml", "-m", "v").variant == "v"
    assert parse(command, "x.xml", "--output", "o.exr").out == Path("o.exr")


def test_a_missing_search_folder_in_a_list_is_named(tmp_path: Path) -> None:
    args = parse("render", "x.xml", "-a", f"{tmp_path};{tmp_path / 'gone'}")
    with pytest.raises(Exception, match=f"-a {tmp_path / 'gone'}: not a folder"):
        search_paths(args)


def test_verbosity_follows_mitsubas_v() -> None:
    assert [verbosity(n) for n in range(4)] == ["WARNING", "INFO", "DEBUG", "DEBUG"]


def test_v_logs_what_the_planning_and_mitsuba_do(tmp_path: Path) -> None:
    """-v: the command's INFO lines and Mitsuba's own, from its render process, as Mitsuba's -v shows them."""
    args = ["render", str(CBOX), "-D", "res=8", "--spp", "1", "-t", "1", "--no-progress", "-o", "x.exr"]
    quiet, told = quekaro(*args, cwd=tmp_path), quekaro(*args, "-v", cwd=tmp_path)
    assert quiet.returncode == told.returncode == 0, told.stderr
    assert " INFO planning.pipeline: " in told.stderr and " INFO " not in quiet.stderr
    assert "Loading XML file" in told.stderr and "[SamplingIntegrator] Starting render job" in told.stderr
    assert "Loading XML file" not in quiet.stderr


def test_split_range_takes_one_range_and_refuses_two() -> None:
    defines, frames = split_range({"res": "8", "frame": "1:9:4"})
    assert defines == {"res": "8"} and frames.frames() == [1, 5, 9]
    assert split_range({"res": "8"}) == ({"res": "8"}, None)
    with pytest.raises(Exception, match="-D a and -D b: both are frame ranges"):
        split_range({"a": "1:2", "b": "3:4"})


def test_did_you_mean_and_locations() -> None:
    assert did_you_mean("paht", ["path", "volpath"]) == " (did you mean path?)"
    assert did_you_mean("zzzz", ["path"]) == ""
    assert without_locations("[parser.cpp:111] Found unused parameters") == "Found unused parameters"


@pytest.mark.parametrize(("args", "said"), [
    (["--integrator", "paht"], "argument --integrator: 'paht' is not one of Mitsuba's integrators (did you mean "
                               "path?)"),
    (["--bogus"], "unrecognized arguments: --bogus"),
    (["--opt", "huge"], "argument --opt: invalid choice: 'huge'"),
])
@pytest.mark.parametrize("command", ["render", "submit"])
def test_a_bad_flag_prints_the_subcommands_usage(command: str, args: list[str], said: str) -> None:
    done = quekaro(command, str(CBOX), *args)
    assert done.returncode == 2 and said in done.stderr, done.stderr
    assert done.stderr.startswith(f"usage: quekaro {command} "), done.stderr


@pytest.mark.parametrize(("args", "said"), [
    (["-D", "nosuch=1"], "-D nosuch: cbox.xml has no parameter nosuch; its parameters: max_depth, res, spp"),
    (["-D", "rez=1"], "-D rez: cbox.xml has no parameter rez (did you mean res?); its parameters"),
    (["-D", "frame=1:3"], "-D frame: cbox.xml has no parameter frame"),
    (["--opt", "s", "--rules", "nosuch.xml"], "--rules nosuch.xml: file not found"),
    (["--rules", "nosuch.xml"], "--rules nosuch.xml: file not found"),
    (["-t", "0"], "option threads (--threads 0): outside 1..4096"),
    (["-D", "res=1:2", "-D", "spp=1:2"], "-D res and -D spp: both are frame ranges"),
    (["-D", "res=1:2", "--sequence"], "--sequence and -D res=1:2: a sequence is either"),
    (["-o", "x.exr"], "-o x.exr: the image is written when the job ends: add --wait"),
    (["--wait", "-o", "x.png"], "-o x.png: the image is written as its film's file_format asks"),
])
def test_submit_refuses_before_anything_is_uploaded(args: list[str], said: str, tmp_path: Path) -> None:
    """The farm's address is a closed port: an upload would say it cannot reach the master."""
    done = quekaro("submit", str(CBOX), *args, *NOWHERE, cwd=tmp_path)
    assert done.returncode == 2 and f"quekaro: error: {said}" in done.stderr, done.stderr
    assert "Traceback" not in done.stderr and "reach" not in done.stderr


@pytest.mark.parametrize("command", ["render", "submit"])
def test_a_folder_given_as_scene_is_named_a_folder(command: str, tmp_path: Path) -> None:
    done = quekaro(command, str(tmp_path), *(NOWHERE if command == "submit" else []), cwd=tmp_path)
    assert done.returncode == 2, done.stderr
    assert f"{tmp_path}: a folder, not a scene file" in done.stderr and "Traceback" not in done.stderr


def test_an_unknown_plugin_is_named_with_the_closest_and_no_source_location(tmp_path: Path) -> None:
    (tmp_path / "odd.xml").write_text(CBOX.read_text().replace('<shape type="rectangle"', '<shape type="rectangel"', 1))
    done = quekaro("render", str(tmp_path / "odd.xml"), "-D", "res=8", "--spp", "1", "-t", "1", "--no-progress",
                   "-o", str(tmp_path / "x.exr"))
    assert done.returncode == 2, done.stderr
    assert 'Plugin "rectangel" not found! (did you mean rectangle?)' in done.stderr, done.stderr
    assert ".cpp:" not in done.stderr


def test_an_unknown_variant_is_named_with_the_closest(tmp_path: Path) -> None:
    done = quekaro("render", str(CBOX), "-D", "res=8", "--spp", "1", "--mode", "llvm_rgb", "--no-progress",
                   "-o", str(tmp_path / "x.exr"))
    assert done.returncode == 2 and "variant 'llvm_rgb' is not available (did you mean llvm_ad_rgb?)" in done.stderr


def test_render_of_a_frame_range_writes_one_image_a_frame(tmp_path: Path) -> None:
    done = quekaro("render", str(CBOX), "-D", "res=8", "-D", "spp=1:5:2", "-t", "1", "--no-progress",
                   "-o", str(tmp_path / "out"))
    assert done.returncode == 0, done.stderr
    assert sorted(p.name for p in (tmp_path / "out").glob("*.exr")) == ["cbox_0001.exr", "cbox_0003.exr",
                                                                       "cbox_0005.exr"]
    spps = [json.loads((tmp_path / "out" / f"cbox_000{n}.json").read_text())["units"][0]["spp"] for n in (1, 3, 5)]
    assert spps == [1, 3, 5]  # each frame rendered with its own value of the range's parameter
    one_file = quekaro("render", str(CBOX), "-D", "spp=1:2", "--no-progress", "-o", str(tmp_path / "x.exr"))
    assert one_file.returncode == 2 and "renders 2 frames, one image each" in one_file.stderr


def test_a_stale_farm_file_is_named_with_its_home(tmp_path: Path) -> None:
    (tmp_path / ADMIN_TOKEN).write_text("secret")
    (tmp_path / FARM_FILE).write_text(json.dumps({"url": "http://127.0.0.1:9"}))
    for command in (["status"], ["watch", "abc"], ["cancel", "abc"], ["result", "abc"]):
        done = quekaro(*command, "--home", str(tmp_path))
        assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
        assert done.stderr == (f"quekaro: error: no farm is running in {tmp_path} (farm.json is stale): start one "
                               "with quekaro up\n"), done.stderr
    missing = quekaro("status", "--home", str(tmp_path / "none"))
    assert f"no farm is running in {tmp_path / 'none'} (no farm.json)" in missing.stderr


def test_down_without_a_farm_says_so_and_succeeds(tmp_path: Path) -> None:
    done = quekaro("down", "--home", str(tmp_path))
    assert done.returncode == 0 and done.stdout == f"no farm is running in {tmp_path}\n", done.stderr


class _Refusing(BaseHTTPRequestHandler):
    def do_GET(self) -> None:
        body = json.dumps({"error": "cbox.xml: [parser.cpp:111] Found unused parameters", "status": 422}).encode()
        self.send_response(422)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args: object) -> None:
        pass


def test_a_refusal_reads_as_the_masters_reason_alone() -> None:
    server = ThreadingHTTPServer(("127.0.0.1", 0), _Refusing)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        with pytest.raises(FarmRefusal) as refused:
            FarmClient(f"http://127.0.0.1:{server.server_port}", "token").status("abc")
    finally:
        server.shutdown()
    assert str(refused.value) == "cbox.xml: Found unused parameters" and refused.value.status == 422


def test_parameters_and_a_sequences_status_from_summaries() -> None:
    job = {"scene": "cbox.xml", "level": "S", "spp": 64, "resolution": [32, 24], "defines": {"res": "32"},
           "name": "hero", "sequence": "seq-0123456789ab", "frame": 3}
    assert parameters_text(job) == 'cbox.xml, level S, 64 spp, 32x24, -D res=32, frame 3 of seq-0123456789ab  "hero"'
    assert parameters_text({"scene": "a.xml"}) == "a.xml"
    frames = [{"status": s} for s in ("done", "failed", "running")]
    assert sequence_status(frames) == "running" and sequence_status(frames[:2]) == "failed"
    assert sequence_status(frames[:1]) == "done"


def test_the_masters_pass_samples_reach_its_auction_and_a_bad_one_is_refused() -> None:
    from master.run import config_from

    base = ("master", "--password", "p")
    assert config_from(parse(*base)).auction.pass_samples == 1 << 18
    assert config_from(parse(*base, "--pass-samples", "1")).auction.pass_samples == 1
    with pytest.raises(QuekaroError, match="--pass-samples 0: must be at least 1"):
        config_from(parse(*base, "--pass-samples", "0"))
