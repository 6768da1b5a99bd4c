"""`quekaro up | down | demo | master | agent | submit | status | watch | result | cancel | requeue`: running a
farm, and using one. The processes themselves live in `farm.local` (up, demo), `master.service` and
`agents.render_agent`; this module is argument parsing and printing."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import re
import secrets
import shutil
import sys
import tempfile
import time
from pathlib import Path

from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

from core.data import DEMO_SCENE
from core.errors import QuekaroError, without_locations
from core.home import ADMIN_TOKEN, MIN_FREE_BYTES, default_home, read_processes
from core.logs import FORMATS, farm_logs
from core.model.frames import SEQUENCE_ID, FrameRange, frame_name
from core.model.job import IMAGE_SUFFIXES, JobSpec, SceneSpec
from core.model.units import SLOTS
from core.scene.bundle import make_bundle
from core.scene.scene import check_parameters, parse_defines, referenced_files
from core.wording import count
from farm.client import FarmClient
from farm.local import LocalFarm, stop_farm
from planning import budgets, progressive
from quekaro.cmd_render import (
    add_job_arguments,
    check_writable,
    options_from_args,
    outputs,
    search_paths,
    split_range,
    writable_outputs,
)


def register(sub: argparse._SubParsersAction) -> None:
    _register_up(sub)
    down = sub.add_parser("down", help="stop the local farm of a home (the one `quekaro up` started there)",
                          description="Stop the local farm that `quekaro up` (or `demo`) runs in HOME: its master, "
                                      "agents and XMPP server, as Ctrl-C in its terminal would. Waits until they "
                                      "are gone and names them. Exit status 0 also where no farm runs there "
                                      "(it says so); 2 where the farm did not stop.")
    down.add_argument("--home", type=Path, help="farm directory (default: $QUEKARO_HOME or ~/.quekaro/farm)")
    down.set_defaults(func=run_down)
    _register_master(sub)
    # `quekaro agent ...` is dispatched to agents.render_agent before parsing (see quekaro.cli.main);
    # this entry is for `quekaro --help`.
    sub.add_parser("agent", help="run one render agent against an XMPP server (quekaro agent --help)")
    _register_client(sub)


def _add_farm_location(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--home", type=Path, help="farm directory (default: $QUEKARO_HOME or ~/.quekaro/farm)")
    parser.add_argument("--url", help="master URL (default: from HOME/farm.json)")
    parser.add_argument("--token-file", type=Path, help="admin token file (default: HOME/admin.token)")
    parser.add_argument("--ca-file", type=Path, help="the farm's CA certificate, to verify an https master")


def _register_up(sub: argparse._SubParsersAction) -> None:
    for name, text in (("up", "a whole local farm: embedded XMPP server, master and N agents"),
                       ("demo", "start a local farm, render a sample scene on it, print where the outputs are")):
        parser = sub.add_parser(name, help=text)
        parser.add_argument("--agents", type=int, default=2, help="render agents (default 2)")
        parser.add_argument("--home", type=Path, help="farm directory (default: $QUEKARO_HOME or ~/.quekaro/farm)")
        parser.add_argument("--http-port", type=int, default=0, help="master HTTP port (default: a free one)")
        parser.add_argument("--threads", type=int, help="Dr.Jit threads per agent (default: cores / agents)")
        parser.add_argument("--rules", type=Path, action="append", default=[],
                            help="rule file for the agents; repeat to give agents different rules")
        _add_log_format(parser)
        if name == "demo":
            parser.add_argument("-o", "--out", type=Path, default=Path("out/demo.exr"),
                                help="output EXR file, or a folder (the PNG and the report go beside it)")
            parser.add_argument("--opt", dest="level", default="S", help="optimisation level (default S)")
        parser.set_defaults(func=run_up if name == "up" else run_demo)


def _register_master(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser("master", help="run the master against an XMPP server")
    parser.add_argument("--home", type=Path, help="state directory (default: $QUEKARO_HOME or ~/.quekaro/farm)")
    parser.add_argument("--jid", default="master@localhost")
    parser.add_argument("--password", help="XMPP password (better: --password-file or $QUEKARO_XMPP_PASSWORD)")
    parser.add_argument("--password-file", type=Path)
    parser.add_argument("--server", help="XMPP server host (default: the JID's domain)")
    parser.add_argument("--port", type=int, default=5222, help="XMPP client port")
    parser.add_argument("--ca-file", help="CA certificate to verify the XMPP server's TLS certificate")
    parser.add_argument("--http-host", default="127.0.0.1", help="address the HTTP API binds to")
    parser.add_argument("--http-port", type=int, default=8765,
                        help="HTTP API port (0: a free one, named in HOME/farm.json)")
    parser.add_argument("--public-url", help="URL agents use to reach the HTTP API (default http(s)://HOST:PORT)")
    parser.add_argument("--tls-cert", type=Path, help="HTTPS certificate of the data plane (quekaro ca issue)")
    parser.add_argument("--tls-key", type=Path, help="its private key")
    parser.add_argument("--insecure-http", action="store_true",
                        help="serve plain HTTP although agents reach it over a network (logged and shown by status)")
    parser.add_argument("--threads", type=int,
                        help="Dr.Jit threads of the pre-pass (default: one per core; a job naming its own keeps them)")
    parser.add_argument("--slots", type=int,
                        help=f"units an agent may hold at once (default {SLOTS}: it wins up to half of them a round "
                             "and renders them in one call, the next half awarded while it renders; 2: one unit a "
                             "call; 1: one at a time). An agent started with fewer says so when it registers, "
                             "and is awarded no more")
    parser.add_argument("--pass-samples", type=int,
                        help="a --progressive job's pass holds at least this many samples (its unit's pixels x "
                             "spp) where the unit has them (default 262144: a smaller pass costs more in its "
                             "award, render call and upload than it renders; 1: five passes a unit, however small)")
    parser.add_argument("--agents-allow", type=Path,
                        help="file of agent JIDs (one a line, read again when it changes): only these may bid; "
                             "default: any JID matching agent*@DOMAIN that the XMPP server authenticated")
    parser.add_argument("--log-level", default="INFO")
    _add_log_format(parser)
    parser.set_defaults(func=run_master)


def _add_log_format(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--log-format", choices=FORMATS, default=os.environ.get("QUEKARO_LOG_FORMAT", "text"),
                        help="the farm's logs: text, a sentence a line (default), or json, one object a line "
                             "($QUEKARO_LOG_FORMAT)")


def _register_client(sub: argparse._SubParsersAction) -> None:
    submit = sub.add_parser("submit", help="submit a scene to the farm")
    add_job_arguments(submit)
    _add_farm_location(submit)
    submit.add_argument("--wait", action="store_true",
                        help="watch the job until it ends; exit status 1 (and the reason) if it fails")
    submit.add_argument("-o", "--output", "--out", dest="out", type=Path,
                        help="with --wait: write the image there when done, as quekaro result -o does (a file for "
                             "one job, else a folder: SCENE.exr, a frame's SCENE_0001.exr)")
    submit.add_argument("--name", help="a label for the job, shown by status, watch and the page")
    submit.add_argument("--sequence", action="store_true",
                        help="the scene files are the frames of one sequence, numbered 1..N in the order given")
    submit.add_argument("-t", "--threads", type=int,
                        help="Dr.Jit threads each agent renders the job on (Mitsuba's -t), at most its own "
                             "--threads; also the master's pre-pass (default: each agent's own)")
    submit.set_defaults(func=run_submit)
    status = sub.add_parser("status", help="jobs and their progress (one job or sequence if given)")
    status.add_argument("job", nargs="?", help="a job id, a sequence id (seq-...) for its frames, or a submit --name")
    status.add_argument("--unit", type=int, metavar="N",
                        help="one unit of JOB: its attempts and its story (what moved it, and when)")
    status.add_argument("--json", action="store_true")
    _add_farm_location(status)
    status.set_defaults(func=run_status)
    watch = sub.add_parser("watch", help="a live progress bar for a job or sequence: units done, agents busy, ETA "
                                         "(a plain line a change when not on a terminal)")
    watch.add_argument("job", help="a job id, a sequence id (seq-...), or a submit --name")
    _add_farm_location(watch)
    watch.set_defaults(func=run_watch)
    result = sub.add_parser("result", help="download a finished job's image (and its report), or a sequence's")
    result.add_argument("job", help="a job id, a sequence id (seq-...) for every frame, or a submit --name")
    result.add_argument("-o", "--output", "--out", dest="out", type=Path,
                        help="output image file (its suffix is the film's file_format's: .exr, .pfm, .rgbe), or "
                             "a folder (default: this one) for SCENE.exr, a frame's SCENE_0001.exr; the PNG and "
                             "the report go beside it, replacing earlier ones as quekaro render does")
    result.add_argument("--partial", action="store_true",
                        help="a job (or frame) running, failed or cancelled: the image of its tiles so far, "
                             "the units without one black, as SCENE.partial.exr; a done job's is its whole image")
    _add_farm_location(result)
    result.set_defaults(func=run_result)
    cancel = sub.add_parser("cancel", help="cancel a job, or every frame of a sequence")
    cancel.add_argument("job", help="a job id, a sequence id (seq-...), or a submit --name")
    _add_farm_location(cancel)
    cancel.set_defaults(func=run_cancel)
    requeue = sub.add_parser("requeue", help="run a failed or cancelled job again, its done units kept; or every "
                                             "failed or cancelled frame of a sequence",
                             description="A failed or cancelled job runs again: the units it had done keep their "
                                         "tiles, the others are rendered. A sequence id requeues each of its failed "
                                         "or cancelled frames (one frame alone: its job id). A running or done job "
                                         "is refused.")
    requeue.add_argument("job", help="a job id, a sequence id (seq-...), or a submit --name")
    _add_farm_location(requeue)
    requeue.set_defaults(func=run_requeue)
    agents = sub.add_parser("agents", help="the agents the master knows: state, speed, units done, last heard")
    agents.add_argument("--json", action="store_true")
    _add_farm_location(agents)
    agents.set_defaults(func=run_agents)
    logs = sub.add_parser("logs", help="a local farm's process logs (HOME/logs): one process, or the list")
    logs.add_argument("process", nargs="?", help="master, xmpp or agent-N (default: list the logs)")
    logs.add_argument("-f", "--follow", action="store_true", help="keep printing what is written (Ctrl-C stops)")
    logs.add_argument("-n", "--lines", type=_lines, default=40, help="lines from the end to start with (default 40)")
    logs.add_argument("--home", type=Path, help="farm directory (default: $QUEKARO_HOME or ~/.quekaro/farm)")
    logs.set_defaults(func=run_logs)


# ---- running processes ---------------------------------------------------------------------------------


def run_up(args: argparse.Namespace) -> int:
    os.environ["QUEKARO_LOG_FORMAT"] = args.log_format  # the farm's processes inherit it
    with LocalFarm(args.home, args.agents, args.threads, args.rules, args.http_port, supervise=True) as farm:
        print(f"farm up: master {farm.url}, {_agents(farm.n_agents)}")
        _print_page(farm)
        home = f" --home {farm.home}" if args.home else ""
        print(f"home:     {farm.home} (logs: quekaro logs{home})")
        print(f"stop:     quekaro down{home}, or Ctrl-C here", flush=True)
        _warn_if_short_of_space(farm.home)
        farm.wait()
    return 0


def _print_page(farm: LocalFarm, while_: str = "") -> None:
    """Where the farm's web page is and how to log in to it."""
    print(f"web page: {farm.url}/ui/ (log in with the admin token in {farm.home / ADMIN_TOKEN}{while_})", flush=True)


def run_down(args: argparse.Namespace) -> int:
    home = Path(args.home or default_home()).resolve()
    stopped = stop_farm(home)
    if stopped is None:
        print(f"no farm is running in {home}")
        return 0
    print(f"stopped the farm in {home}: {', '.join(stopped) or 'its processes'}")
    return 0


def _warn_if_short_of_space(home: Path) -> None:
    """The master pauses every job below MIN_FREE_BYTES free in its home: say so at once, not only when a
    job sits paused."""
    free = shutil.disk_usage(home).free
    if free < MIN_FREE_BYTES:
        print(f"warning: {home} has {free >> 20} MiB free; the master pauses every job below "
              f"{MIN_FREE_BYTES >> 20} MiB (quekaro status says so) until space is freed", file=sys.stderr)


def run_demo(args: argparse.Namespace) -> int:
    """Start a farm, render the demo scene on it, fetch the image, and say where everything is."""
    (target,) = writable_outputs([DEMO_SCENE], args.out)  # before a farm starts, not after its render
    os.environ["QUEKARO_LOG_FORMAT"] = args.log_format  # the farm's processes inherit it
    with LocalFarm(args.home, args.agents, args.threads, args.rules, args.http_port, supervise=True) as farm:
        print(f"farm up: master {farm.url}, {_agents(farm.n_agents)}, home {farm.home}")
        _print_page(farm, "; up while the demo runs")
        farm.wait_for_agents()
        with tempfile.TemporaryDirectory() as tmp:
            bundle = make_bundle(DEMO_SCENE, {}, Path(tmp) / "bundle.tar").path.read_bytes()
        client = farm.client()
        job_id = client.submit(bundle, {}, {"level": args.level})
        print(f"submitted {DEMO_SCENE.name} as job {job_id} (optimisation {args.level})")
        status = watch(client, job_id)
        if status != 0:
            return status
        out = client.result(job_id, target)
        report = json.loads(out.with_suffix(".json").read_text())
    totals = report["totals"]
    print(f"image:  {out.resolve()}\npng:    {out.with_suffix('.png').resolve()}\n"
          f"report: {out.with_suffix('.json').resolve()}")
    # totals.seconds is the whole job, upload to composed image (as `quekaro render`'s is the whole run)
    print(f"{count(totals['units'], 'unit')}, {totals['seconds']:.1f} s for the job (upload to image), render "
          f"seconds on agents {totals['render_seconds']:.1f}, pre-pass {totals['prepass_seconds']:.2f} s")
    return 0


def run_master(args: argparse.Namespace) -> int:
    # Lazy: the master's SPADE and aiohttp take ~0.4 s to import, which `quekaro --help`, `status` and
    # `watch` should not pay.
    from master.run import main

    return main(args)


# ---- using a farm ----------------------------------------------------------------------------------------


def _client(args: argparse.Namespace):
    return FarmClient.from_home(args.home, args.url, args.token_file, args.ca_file)


JOB_ID = re.compile(r"[0-9a-f]{12}")  # as the master makes them (master.service)


def _job_ref(client: FarmClient, text: str) -> str:
    """A job or sequence id as given, or the id of the one job (a sequence's frames: the sequence) named
    `text` by `submit --name`. Several named so are refused, naming their ids."""
    if JOB_ID.fullmatch(text) or SEQUENCE_ID.fullmatch(text):
        return text
    named = sorted({j.get("sequence") or j["job_id"] for j in client.jobs() if j.get("name") == text})
    if len(named) > 1:
        raise QuekaroError(f"{len(named)} jobs are named {text!r}; give one's id: {', '.join(named)}")
    return named[0] if named else text  # neither: the master says there is no such job


def run_submit(args: argparse.Namespace) -> int:
    """One job per scene (its bundle carries the files it reads and the rule file), a frame range's one a
    frame (the master makes them), or with --sequence the scenes as one sequence's frames; with --wait,
    watch each, and with -o write the images."""
    defines, frames = split_range(parse_defines(args.defines))
    _refuse_unusable(args, frames)
    options = options_from_args(args)
    JobSpec(defines, options, args.name, frames).header()  # a -D list too long to carry: refused before packing
    spec = JobSpec(defines, dataclasses.replace(options, rules=None), args.name, frames)  # rules: in the bundle
    if args.out is not None:
        _result_folder(args.out, len(args.scenes) > 1 or frames is not None or args.sequence)
    bundles = [_bundle_bytes(scene, defines, frames, args) for scene in args.scenes]  # every input checked first
    client = _client(args)
    sequence = f"seq-{secrets.token_hex(6)}" if args.sequence else None
    ids, refused = [], []
    for n, (scene, bundle) in enumerate(zip(args.scenes, bundles, strict=True), start=1):
        job = dataclasses.replace(spec, sequence=sequence, frame=n) if sequence else spec
        try:
            answer = client.submit_spec(bundle, job)
        except QuekaroError as exc:
            if len(args.scenes) == 1:
                raise
            print(f"quekaro: error: {scene}: {exc}", file=sys.stderr)  # the others are still submitted
            refused.append(str(scene))
            continue
        ids.append(answer["job_id"])
        _print_submitted(answer, scene, len(args.scenes), n if sequence else None)
    if sequence and ids:
        ids = [sequence]
        print(f"{sequence}  {len(args.scenes) - len(refused)} frames")
    statuses = [_wait_and_fetch(client, job_id, args.out) for job_id in ids] if args.wait else [0]
    if refused:
        print(f"quekaro: error: {len(refused)} of {len(args.scenes)} scenes refused: {', '.join(refused)}",
              file=sys.stderr)
        return 2
    return max(statuses)


def _refuse_unusable(args: argparse.Namespace, frames: FrameRange | None) -> None:
    """Options of submit that cannot work together, refused before anything is packed."""
    if args.sequence and frames is not None:
        raise QuekaroError(f"--sequence and -D {frames.define}={frames.first}:{frames.last}: a sequence is either "
                           "several scene files or one file's frame range, not both")
    if args.out is not None and not args.wait:
        raise QuekaroError(f"-o {args.out}: the image is written when the job ends: add --wait, or fetch it "
                           "later with quekaro result JOB -o ...")


def _print_submitted(answer: dict, scene: Path, scenes: int, frame: int | None) -> None:
    """The new job's id (with its scene when several were submitted), or a range's sequence and frames."""
    if answer.get("jobs") is not None:
        print(f"{answer['sequence']}  {scene.name}  {len(answer['jobs'])} frames")
    elif frame is not None:
        print(f"{answer['job_id']}  {scene.name}  frame {frame}")
    else:
        print(answer["job_id"] if scenes == 1 else f"{answer['job_id']}  {scene.name}")


def _wait_and_fetch(client: FarmClient, job_id: str, out: Path | None) -> int:
    """Watch the job (or sequence) to its end, then write its images to `out` if given."""
    status = watch(client, job_id)
    if status == 0 and out is not None:
        _fetch(client, job_id, out)
    return status


def _bundle_bytes(scene: Path, defines: dict[str, str], frames: FrameRange | None,
                  args: argparse.Namespace) -> bytes:
    """The scene's bundle, its -D checked against its parameters first; for a range, one bundle serves every
    frame, so the frame number may not change which files the scene reads."""
    paths = search_paths(args)
    first = defines if frames is None else {**defines, frames.define: str(frames.first)}
    check_parameters(SceneSpec(scene, first, paths))
    if frames is not None and len(frames) > 1:
        second = {**defines, frames.define: str(frames.frames()[1])}
        if referenced_files(SceneSpec(scene, first, paths)) != referenced_files(SceneSpec(scene, second, paths)):
            raise QuekaroError(f"{scene}: -D {frames.define} changes which files the scene reads, and a range is "
                               "uploaded once; submit each frame's file with --sequence")
    with tempfile.TemporaryDirectory() as tmp:
        return Path(make_bundle(scene, first, Path(tmp) / "bundle.tar", search_paths=paths,
                                rules=args.rules).path).read_bytes()


def run_status(args: argparse.Namespace) -> int:
    client = _client(args)
    args.job = args.job and _job_ref(client, args.job)
    if args.unit is not None:
        return _print_unit(client, args)
    answer = client.status(args.job) if args.job else None
    if args.json:
        print(json.dumps(answer if answer is not None else client.jobs(), indent=2))
        return 0
    plane = client.farm()["data_plane"]  # first: a farm not running is said alone
    _print_processes(Path(args.home or default_home()))
    if "insecure" in plane:
        print(f"WARNING: data plane {plane}")
    if answer is not None and "frames" in answer:  # a sequence: its line, then each frame's
        print(_sequence_line(answer))
        for job in answer["frames"]:
            _print_job(job, f"frame {job.get('frame')}  ")
        return 0
    if answer is not None:
        _print_job(answer)
        print(f"job: {parameters_text(answer)}")
        print_effects(answer.get("effects") or {})
        if answer.get("adaptive"):
            print(f"adaptive: {budgets.describe(answer['adaptive'])}")
        return 0
    jobs = client.jobs()
    if not jobs:
        print("no jobs (quekaro submit SCENE adds one)")
    for group in _by_sequence(jobs):
        if group[0].get("sequence"):
            print(_sequence_line({"sequence": group[0]["sequence"], "name": group[0].get("name"),
                                  "scene": group[0].get("scene"), "status": sequence_status(group), "frames": group}))
        else:
            _print_job(group[0])
    return 0


def _print_job(job: dict, lead: str = "") -> None:
    """A job's line: id, status, progress, ETA, scene and name; its retries below it."""
    running = job["status"] == "running" and job.get("eta_s") is not None
    eta = _eta_text(job, " s") if running else "-"  # an ended job has none (it read "0 s")
    print(f"{lead}{job['job_id']}  {job['status']:<9} {job['units_done']}/{job['units_total']} units"
          f"{_passes_text(job)}  agents busy {job['agents_busy']}  ETA {eta}  {job['scene']}{_name_text(job)}"
          + (f"  error: {without_locations(job['error'])}" if job.get("error") else "")
          + (f"  PAUSED: {job['paused']}" if job.get("paused") else ""))
    if (job.get("passes") or {}).get("stopped"):
        print(f"  stopped: {job['passes']['stopped']}")
    if job.get("attempts_retried"):
        print(f"  {job['attempts_retried']} attempt(s) ended without a tile, their units auctioned again; "
              f"latest: {job['last_retry']}")


def _name_text(job: dict) -> str:
    return f"  \"{job['name']}\"" if job.get("name") else ""


def parameters_text(job: dict) -> str:
    """What a job renders, from its summary: scene, level, spp, resolution, -D values and name."""
    parts = [str(job.get("scene"))]
    if job.get("level") is not None:
        parts.append(f"level {job['level']}")
    if job.get("spp") is not None:
        parts.append(f"{job['spp']} spp")
    if job.get("resolution"):
        parts.append("x".join(map(str, job["resolution"])))
    parts += [f"-D {name}={value}" for name, value in (job.get("defines") or {}).items()]
    if job.get("frame") is not None:
        parts.append(f"frame {job['frame']} of {job.get('sequence')}")
    return ", ".join(parts) + _name_text(job)


def sequence_status(frames: list[dict]) -> str:
    """A sequence's status from its frames': running while any runs; failed if any failed; done when all are."""
    states = {job["status"] for job in frames}
    for state in ("running", "failed", "cancelled"):
        if state in states:
            return state
    return "done" if states <= {"done"} else sorted(states)[0]


def _sequence_line(sequence: dict) -> str:
    """A sequence's line: id, status, frames done/total, units over all frames, scene and name."""
    frames = sequence["frames"]
    done = sum(job["status"] == "done" for job in frames)
    units = sum(job["units_done"] for job in frames), sum(job["units_total"] for job in frames)
    return (f"{sequence['sequence']}  {sequence['status']:<9} {done}/{len(frames)} frames  "
            f"{units[0]}/{units[1]} units  {sequence.get('scene')}{_name_text(sequence)}")


def _by_sequence(jobs: list[dict]) -> list[list[dict]]:
    """The jobs in order, a sequence's frames together where its first frame is (each plain job alone)."""
    groups: dict[str, list[dict]] = {}
    for job in jobs:
        groups.setdefault(job.get("sequence") or job["job_id"], []).append(job)
    return list(groups.values())


def _passes_text(job: dict) -> str:
    """A progressive job's passes beside its units: done/ordered and the mean spp so far (else nothing)."""
    passes = job.get("passes")
    if not passes:
        return ""
    return f", {passes['done']}/{passes['ordered']} passes, {_spp_text(passes)} spp"


def _spp_text(passes: dict) -> str:
    """The mean spp so far as the page writes it: 287.5, 288, 1048576."""
    return str(passes["spp_mean"]).removesuffix(".0")


def _eta_text(job: dict, unit: str) -> str:
    """The ETA in whole seconds; "at least" where it counts only the passes ordered so far (a noise goal),
    and "unknown" once those are rendered: the noise decides what comes next."""
    if job.get("eta_at_least"):
        return f"at least {job['eta_s']:.0f}{unit}" if job["eta_s"] >= 0.5 else "unknown"
    return f"{job['eta_s']:.0f}{unit}"


def _print_unit(client, args: argparse.Namespace) -> int:
    """`quekaro status JOB --unit N`: the unit's attempts, then its story, a line each."""
    if not args.job:
        raise QuekaroError("--unit needs a JOB: quekaro status JOB --unit N")
    unit = client.unit(args.job, args.unit)
    if args.json:
        print(json.dumps(unit, indent=2))
        return 0
    print(f"unit {unit['index']} of job {unit['job_id']}: {unit['status']}"
          + (f", held by {unit['agent']}" if unit.get("agent") else ""))
    for a in unit["attempts"]:
        took = f" in {a['seconds']:.2f} s" if a.get("seconds") is not None else ""
        print(f"  attempt by {a['agent']}: {a['outcome']}{took}" + (f" ({a['reason']})" if a.get("reason") else ""))
    if not unit["story"]:
        print("  no change of state since the master started")
    for s in unit["story"]:
        clock = time.strftime("%H:%M:%S", time.localtime(s["at"])) + f".{int(s['at'] % 1 * 1000):03d}"
        print(f"  {clock}  {s['start']} -> {s['finish']}  ({s['stimulus_id']})")
    return 0


def _agents(n: int) -> str:
    return f"{n} agent{'' if n == 1 else 's'}"


def _not_running(home: Path) -> dict[str, str]:
    """A local farm's processes that are not running: name -> state (restarting, or failed)."""
    return {p["name"]: f"{p['state']} ({p.get('restarts', 0)} restarts)" for p in read_processes(home)
            if p.get("state") != "running"}


def _print_processes(home: Path) -> None:
    """Processes down, and those restarted since the farm started (a job went on without them a while)."""
    for p in read_processes(home):
        if p.get("state") != "running" or p.get("restarts"):
            print(f"process {p['name']}: {p['state']} ({p.get('restarts', 0)} restarts)")


def print_effects(effects: dict) -> None:
    """What the job simulates and why, one reason a line (as `quekaro render` prints them)."""
    if not effects:
        return
    print(f"effects: {effects.get('variant')} / {effects.get('integrator')} / max_depth {effects.get('max_depth')}")
    for reason in effects.get("reasons", []):
        print(f"  - {reason}")


def run_watch(args: argparse.Namespace) -> int:
    client = _client(args)
    return watch(client, _job_ref(client, args.job))


def progress_of(client, job_id: str) -> dict:
    """A job's summary as watch shows it; a sequence's frames' units summed, with its frames done/total and
    the errors of its failed frames (its agents busy are the master's count: an agent on two frames is one)."""
    job = client.status(job_id)
    if "frames" not in job:
        return job
    frames = job["frames"]
    return {**job, "job_id": job_id, "units_done": sum(f["units_done"] for f in frames),
            "units_total": sum(f["units_total"] for f in frames),
            "eta_s": None, "passes": None, "paused": next((f["paused"] for f in frames if f.get("paused")), None),
            "frames_text": f"{sum(f['status'] == 'done' for f in frames)}/{len(frames)} frames ",
            "error": "; ".join(f"frame {f.get('frame')}: {f['error']}" for f in frames if f.get("error"))}


def watch(client, job_id: str, poll_s: float = 0.5) -> int:
    """Progress until the job (or sequence) ends: a live bar on a terminal, else a plain line a change (at
    most one every PLAIN_EVERY_S seconds, and the last); exit status 0 only if it is done. Ctrl-C stops the
    watching, not the job, and says so."""
    first = progress_of(client, job_id)
    frames = first.get("frames")
    print(f"sequence of {len(frames)} frames, the first: {parameters_text(frames[0])}" if frames
          else f"job: {parameters_text(first)}")
    print_effects(first.get("effects") or {})
    try:
        job = (_watch_bar if sys.stdout.isatty() else _watch_lines)(client, job_id, first, poll_s)
    except KeyboardInterrupt:
        print(f"\nstopped watching; {job_id} goes on on the farm: quekaro cancel {job_id} stops it, "
              f"quekaro result {job_id} fetches it", file=sys.stderr)
        raise
    if job["status"] != "done":
        print(f"job {job_id} {job['status']}: {without_locations(job.get('error') or '')}", file=sys.stderr)
        return 1
    return 0


PLAIN_EVERY_S = 2.0  # the fewest seconds between two plain progress lines


def _progress_line(job: dict) -> str:
    paused = f" (paused: {job['paused']})" if job.get("paused") else ""
    return (f"{job['job_id']} {job['status']}{paused}: {job.get('frames_text', '')}{job['units_done']}/"
            f"{job['units_total']} units{_passes_text(job)}, agents busy {job['agents_busy']}")


def _watch_lines(client, job_id: str, job: dict, poll_s: float) -> dict:
    """A plain line whenever the progress changes, rate-limited: logs and pipes show it as it goes."""
    said, said_at = None, -math.inf
    while True:
        line = _progress_line(job)
        ended = job["status"] != "running"
        if line != said and (ended or time.monotonic() - said_at >= PLAIN_EVERY_S):
            eta = f", ETA {_eta_text(job, ' s')}" if job.get("eta_s") is not None and not ended else ""
            print(line + eta, flush=True)
            said, said_at = line, time.monotonic()
        if ended:
            return job
        time.sleep(poll_s)
        job = progress_of(client, job_id)


def _watch_bar(client, job_id: str, job: dict, poll_s: float, console: Console | None = None) -> dict:
    """A rich progress bar, a paused job's reason on a line of its own. It fits 80 columns: a job's units,
    or a progressive job's share of its work (`_bar_state`)."""
    columns = (TextColumn("{task.description}"), BarColumn(bar_width=None), TextColumn("{task.percentage:>3.0f}%"),
               TextColumn("{task.fields[count]}"), TextColumn("{task.fields[busy]} busy"),
               TextColumn("ETA {task.fields[eta]}"), TimeElapsedColumn())
    with Progress(*columns, transient=False, console=console) as progress:
        task = progress.add_task(job_id, total=1, count="", busy=0, eta="-")
        said = None
        while True:
            eta = _eta_text(job, "s") if job.get("eta_s") is not None else "-"
            if (job.get("paused") or None) != said:
                said = job.get("paused") or None
                progress.console.print(f"{job_id} paused: {said}" if said else f"{job_id} goes on")
            paused = " (paused)" if said else ""
            completed, total, count = _bar_state(job)
            progress.update(task, total=total, completed=completed, count=count, busy=job["agents_busy"], eta=eta,
                            description=f"{job_id} {job['status']}{paused}")
            if job["status"] != "running":
                return job
            time.sleep(poll_s)
            job = progress_of(client, job_id)


def _bar_state(job: dict) -> tuple[float, float, str]:
    """(completed, total, the count beside the bar): a job's units done of its units (a sequence's frames
    beside); a progressive job's share of its work (its passes' cost x spp, or a time goal's seconds), its
    units met and spp so far beside."""
    units = job.get("frames_text", "").strip() or f"{job['units_done']}/{job['units_total']} units"
    passes = job.get("passes")
    if not passes:
        return job["units_done"], max(1, job["units_total"]), units
    return passes.get("share", 0.0), 1.0, f"{units} {_spp_text(passes)} spp"


def run_result(args: argparse.Namespace) -> int:
    client = _client(args)
    return _fetch(client, _job_ref(client, args.job), args.out, args.partial)


def _fetch(client: FarmClient, job_id: str, out: Path | None, partial: bool = False) -> int:
    """Write a job's image (SCENE.exr, a frame's SCENE_0001.exr) to `out` (a file, or a folder: by default
    this one), or every frame of a sequence into the folder `out`; print where each went. `partial`: a job
    running or ended without finishing gives its tiles so far (SCENE.partial.exr). A sequence's frames
    without an image are named and skipped (exit status 1)."""
    answer = client.status(job_id)
    frames = answer.get("frames")
    folder = _result_folder(out or Path("."), frames is not None)
    skipped = []
    for job in frames if frames is not None else [answer]:
        cut = partial and job["status"] != "done"
        if job["status"] != "done" and not cut:
            skipped.append(_no_image(job))
            continue
        name = Path(job["scene"]).stem
        name = name if job.get("frame") is None else frame_name(name, job["frame"])
        target = folder / f"{name}{'.partial' if cut else ''}.exr" if folder is not None else out
        try:
            written = client.result(job["job_id"], target, cut)
        except QuekaroError as exc:  # a frame without a tile yet
            if frames is None:
                raise
            skipped.append(f"frame {job['frame']}: {exc}")
            continue
        report = json.loads(written.with_suffix(".json").read_text())
        print(f"{written}  report: {written.with_suffix('.json')}")
        passes = progressive.report_part(report)
        if passes:
            print(f"  {progressive.describe(passes)}")
        if cut:
            print(f"  {_partial_text(report['partial'], bool(passes))}")
    if frames is None and skipped:
        raise QuekaroError(skipped[0])
    for line in skipped:
        print(line, file=sys.stderr)
    return 1 if skipped else 0


def _no_image(job: dict) -> str:
    """Why a job (a frame) has no image to fetch, and what gives one."""
    status, error = job["status"], job.get("error") or ""
    said = error if error.startswith(status) else f"{status}: {error}" if error else status  # "cancelled by the user"
    frame = f"frame {job['frame']} " if job.get("frame") is not None else ""
    return f"{frame}{job['job_id']}: {said}; --partial writes its tiles so far"


def _partial_text(partial: dict, in_passes: bool) -> str:
    """What a partial image lacks, in a line: `partial: cancelled; 3 of 8 units have no tile (black)`."""
    missing = len(partial["units_missing"])
    passes = f", from {count(partial['tiles'], 'pass', 'passes')}" if in_passes else ""
    lack = f"{missing} of {count(partial['units'], 'unit')} have no tile (black)" if missing else \
        f"every unit has a tile{passes}"
    return f"partial: {partial['status']}; {lack}"


def _result_folder(out: Path, several: bool) -> Path | None:
    """The folder images go to (checked writable), or None where `out` names the one image file."""
    one_file = out.suffix.lower() in IMAGE_SUFFIXES and not out.is_dir()
    if one_file and several:
        raise QuekaroError(f"-o {out}: several images (a sequence's frames, or several scenes) need a folder")
    outputs([Path("scene.xml")], out)  # refuses an image format no film writes (-o x.png)
    check_writable(out.parent if one_file else out, out)
    return None if one_file else out


def run_agents(args: argparse.Namespace) -> int:
    rows = _client(args).agents()
    restarting = _not_running(Path(args.home or default_home()))
    for row in rows:
        name = row["jid"].split("@", 1)[0]  # a local farm's agent-0@localhost is its process agent-0
        if name in restarting:
            row["state"] = restarting[name]
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    print(f"{'agent':<28} {'host':<16} {'threads':>7} {'state':<10} {'speed':>7} {'done':>5} {'failed':>6} "
          f"{'heard':>7}  holding")
    for row in rows:
        print(f"{row['jid']:<28} {row.get('host') or '-':<16} {row.get('threads') or '-':>7} {row['state']:<10} "
              f"{row['speed']:>6.2f}x {row['units_done']:>5} {row['units_failed']:>6} {row['last_seen_s']:>6.1f}s  "
              f"{' '.join(row['holding'])}")
    print("speed: renders per second against the reference machine (2.00x: twice as fast)")
    for row in rows:
        if row.get("shared"):
            print(f"warning: {row['shared']}")
    return 0


def _lines(text: str) -> int:
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"{value}: a count of lines, 0 or more")
    return value


def run_logs(args: argparse.Namespace) -> int:
    logs = farm_logs(Path(args.home or default_home()))
    if args.process is None:
        for name, path in logs.items():
            print(f"{name:<12} {path.stat().st_size:>10} bytes  {path}")
        return 0
    if args.process not in logs:
        known = ", ".join(logs) or "none"
        raise QuekaroError(f"no log of {args.process!r} in {Path(args.home or default_home())} (logs: {known})")
    follow_log(logs[args.process], args.lines, args.follow)
    return 0


def follow_log(path: Path, lines: int, follow: bool, poll_s: float = 0.25) -> None:
    """The last `lines` lines of the file, then (with `follow`) what is appended, as `tail -f` does."""
    with path.open("rb") as log:
        written = log.read()  # read to the end even for 0 lines: following starts from there
        tail = written.splitlines()[-lines:] if lines > 0 else []
        for line in tail:
            print(line.decode(errors="replace"), flush=True)
        while follow:
            chunk = log.read()
            if chunk:
                sys.stdout.write(chunk.decode(errors="replace"))
                sys.stdout.flush()
            else:
                time.sleep(poll_s)


def run_requeue(args: argparse.Namespace) -> int:
    client = _client(args)
    answer = client.requeue(_job_ref(client, args.job))
    for job_id in answer["requeued"]:
        print(f"{job_id}: runs again (its done units kept)")
    for job_id, why in answer.get("refused", {}).items():
        print(f"{job_id}: not requeued: {why}")
    return 0


def run_cancel(args: argparse.Namespace) -> int:
    client = _client(args)
    job_id = _job_ref(client, args.job)
    cancelled = client.cancel(job_id)
    what = "every frame still running cancelled" if SEQUENCE_ID.fullmatch(job_id) else "cancelled"
    print(f"{job_id}: {what if cancelled else 'had already ended'}")
    return 0
