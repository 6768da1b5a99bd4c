"""`quekaro bench accuracy [SCENE ...]`: what accuracy costs in time on any scene, per (agents,
optimisation level), against the obvious alternative of lowering spp everywhere.

SCENE is a Mitsuba scene file (with `-D` parameters) or a name of the suite (bench/suite.py; `--suite` runs
all six). `scene_cells` takes a cached plain-Mitsuba reference, runs one real job per cell (`run_cell`) on a
local farm (`farm_runner`) or as the whole `quekaro render` process (`inprocess_runner`, `--inprocess`), and
plain Mitsuba at the uniform spp that takes the same time (`uniform_baseline`). With `--denoise` each scene
also gets denoised cells (`quekaro render --denoise`: uniform+denoise, which is level off denoised, and each
level denoised), each scored against raw plain Mitsuba at its own wall time (`denoised_baseline`), and the
denoiser's bias: the scene denoised at a high spp against the reference (`denoiser_bias`).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from bench.images import write_difference, write_plot
from bench.provenance import rules_digest, rules_for
from bench.suite import SUITE, SuiteScene, scene_from_argument
from core.errors import QuekaroError
from core.files import written_atomically
from core.image.imageio import read_image
from core.image.metrics import all_metrics, diff_image, flip, relmse
from core.image.seams import seam_measure
from core.model.geometry import Rect
from core.model.job import RenderOptions, SceneSpec
from core.model.levels import LEVELS
from core.scene.bundle import check_rules, make_bundle
from core.scene.scene import parse_defines
from farm.local import LocalFarm
from planning.accuracy import (
    Asked,
    content_key,
    default_cache,
    job_variant,
    plain_render,
    reference,
    reference_warning,
    spp_timing,
)
from quekaro.cmd_render import add_asked_arguments, search_paths

REPO = Path(__file__).resolve().parent.parent
HETEROGENEOUS = "caustic-corner"  # the project's own scene the rules were tuned on
SCENES = {"caustic-corner": REPO / "scenes" / "caustic-corner.xml"}
DEFAULT_OUT = REPO / "docs" / "benchmarks"
JOB_TIMEOUT_S = 900.0
DEFAULT_AGENTS = "1,2"  # a farm of one agent and of two, side by side
S_TIME_RATIO, S_DIFF_PERCENT, RELMSE_RATIO = 0.75, 1.21, 0.8  # the targets (issue 15)
AS_WRITTEN = Asked()  # jobs compute what the scene file says
DIFF_WHITE = 0.10  # a display difference of 10 % is white in the grey difference images
PASSES_RELMSE_RATIO = 1.0  # every level in passes, never worse than lowering spp (issue 61)
RELMSE_DENOISED, FLIP_DENOISED = 0.2, 0.5  # the denoised targets over raw uniform, equal wall time (issue 64)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="folder for table, CSV, plot, images")
    parser.add_argument("--cache", type=Path, default=default_cache(),
                        help="where references are cached (default $XDG_CACHE_HOME/quekaro or ~/.cache/quekaro)")
    parser.add_argument("scenes", nargs="*", metavar="SCENE",
                        help=f"scene files or suite names ({', '.join(s.name for s in SUITE)}); "
                             f"default {HETEROGENEOUS} (the scene the rules were tuned on)")
    parser.add_argument("--suite", action="store_true", help="every scene of the suite (bench/suite.py)")
    parser.add_argument("-D", dest="defines", action="append", default=[], metavar="NAME=VALUE",
                        help="a scene parameter for every scene, as Mitsuba's -D (after --res)")
    add_asked_arguments(parser)
    parser.add_argument("--agents", default=None,
                        help=f"comma list of agent counts (default {DEFAULT_AGENTS}; with --inprocess only 1)")
    parser.add_argument("--levels", default="off,VS,S,N,B,VB", help="comma list of optimisation levels")
    parser.add_argument("--res", type=int, default=None,
                        help="image width (-D res, or width and height at the scene's aspect); default: the "
                             "suite's 512, a file's own, caustic-corner 320")
    parser.add_argument("--spp", type=int, default=128, help="the user's spp (what level off renders)")
    parser.add_argument("--ref-spp", type=int, default=2048, help="spp of the reference")
    parser.add_argument("--threads", type=int, default=2, help="threads in all, shared by the agents")
    parser.add_argument("--units", type=int, default=None,
                        help="target unit count at the optimised levels (default: the planner's choice)")
    parser.add_argument("--runs", type=int, default=2,
                        help="timed runs per cell (median time; errors averaged over these and the warm-up, "
                             "and each uniform baseline over as many seeds)")
    parser.add_argument("--no-warmup", dest="warmup", action="store_false",
                        help="time each cell's first run instead of a second, warm one: it compiles the "
                             "kernels Dr.Jit's on-disk cache (~/.drjit) does not hold yet, so a cell's time "
                             "depends on what ran before it")
    parser.add_argument("--inprocess", action="store_true",
                        help="time the whole `quekaro render` process instead of a farm (smallest agent count)")
    parser.add_argument("--adaptive", action="store_true",
                        help="the optimised levels as adaptive jobs (`--adaptive`), through the farm or in one process")
    parser.add_argument("--progressive", action="store_true",
                        help="every level's jobs in passes (`--progressive`: each unit's own samples, level off's "
                             "the user's), through the farm or in one process")
    parser.add_argument("--rules", type=Path, default=None,
                        help="rule file for the rule levels (default: rules/pathtracing.xml): a retune tried on "
                             "the suite; the output names it and its rules' digest")
    parser.add_argument("--denoise", action="store_true",
                        help="also denoised jobs (`quekaro render --denoise`): uniform+denoise (level off) and each "
                             "level, each against raw plain Mitsuba at equal wall time, and the denoiser's bias")
    parser.add_argument("--bias-spp", type=int, default=None,
                        help="spp of the denoiser's bias render, a denoised job against the reference (with "
                             "--denoise; default: the reference's spp / 4)")
    parser.add_argument("--resume", action="store_true",
                        help="keep the scenes already finished in OUT/accuracy.partial.jsonl by a run with the "
                             "same settings, and measure only the others")


def _csv_list(text: str, what: str) -> list[str]:
    items = [t.strip() for t in text.split(",") if t.strip()]
    if not items:
        raise QuekaroError(f"--{what}: expected a comma-separated list, got {text!r}")
    return items


def parse_levels(text: str) -> list[str]:
    """--levels: a comma list of optimisation levels, each one core.model.levels knows."""
    levels = _csv_list(text, "levels")
    for level in levels:
        if level not in LEVELS:
            raise QuekaroError(f"--levels: unknown level {level!r} (known: {', '.join(LEVELS)})")
    twice = sorted({level for level in levels if levels.count(level) > 1})
    if twice:
        raise QuekaroError(f"--levels {text!r}: {', '.join(twice)} given twice (each level is one cell)")
    return levels


def parse_grid(args: argparse.Namespace) -> tuple[list[SuiteScene], list[int], list[str]]:
    """The scenes, agent counts and levels asked for, checked."""
    names = [s.name for s in SUITE] if args.suite else (args.scenes or [HETEROGENEOUS])
    scenes = distinct([SuiteScene(n, SCENES[n], {"res": "320"}, "tuned") if n in SCENES else scene_from_argument(n)
                       for n in names])
    parse_defines(args.defines)  # refused as `quekaro render -D` refuses it
    if args.spp < 1 or args.ref_spp < 1:
        raise QuekaroError(f"--spp {args.spp}, --ref-spp {args.ref_spp}: at least one sample per pixel each")
    text = args.agents or (DEFAULT_AGENTS if not args.inprocess else "1")
    try:
        agents = sorted({int(a) for a in _csv_list(text, "agents")})
    except ValueError:
        raise QuekaroError(f"--agents {text!r}: expected integers like 1,2") from None
    if agents[0] < 1:
        raise QuekaroError(f"--agents {text!r}: counts must be at least 1")
    levels = parse_levels(args.levels)
    if getattr(args, "rules", None) is not None and set(levels) == {"off"}:
        raise QuekaroError(f"--rules {args.rules}: level off plans with no rules (as `quekaro render --opt off` "
                           "refuses it); add a rule level to --levels")
    if args.runs < 1:
        raise QuekaroError(f"--runs {args.runs}: at least one timed run per cell")
    check_denoise(args)
    check_progressive(args)
    search_paths(args)
    RenderOptions(depth=args.depth, integrator=args.integrator, sensor=args.sensor)  # refuses what a job would
    if args.inprocess and agents != [1]:
        raise QuekaroError(f"--agents {text}: --inprocess times one `quekaro render` process, which is no farm of "
                           "agents; leave --agents out (or give 1)")
    return scenes, agents, levels


def check_denoise(args: argparse.Namespace) -> None:
    """--bias-spp only with --denoise (no option is accepted and ignored), and at least 1."""
    if args.bias_spp is None:
        return
    if not args.denoise:
        raise QuekaroError(f"--bias-spp {args.bias_spp}: the denoiser's bias is measured with --denoise only")
    if args.bias_spp < 1:
        raise QuekaroError(f"--bias-spp {args.bias_spp}: at least one sample per pixel")


def check_progressive(args: argparse.Namespace) -> None:
    """--progressive renders every cell in passes: not with --adaptive (a job in passes places its samples by
    its own noise, RenderOptions refuses both) nor --denoise (its cells would be denoised jobs in passes,
    which this run would not tell apart from whole ones)."""
    if not args.progressive:
        return
    other = "--adaptive" if args.adaptive else "--denoise" if args.denoise else None
    if other:
        raise QuekaroError(f"--progressive with {other}: run them apart (a job in passes "
                           + ("places its samples by its own measured noise)" if other == "--adaptive"
                              else "is compared raw, against raw plain Mitsuba)"))


def bias_spp(args: argparse.Namespace) -> int:
    """The spp of the denoiser's bias render: --bias-spp, else a quarter of the reference's."""
    return args.bias_spp or max(1, args.ref_spp // 4)


def distinct(scenes: list[SuiteScene]) -> list[SuiteScene]:
    """The scenes, each under a name of its own: a name is a scene's section, table rows, image files and
    resumed cells, so files of one name in other folders (two `scene.xml`) are named by their folders as
    far up as tells them apart (`sc-a`, `sc2-a`). One file given twice is refused."""
    seen: dict[Path, str] = {}
    for scene in scenes:
        if scene.path in seen:
            raise QuekaroError(f"scene {scene.path} given twice (as {seen[scene.path]!r} and {scene.name!r})")
        seen[scene.path] = scene.name
    out = []
    for scene in scenes:
        alike = [s.path for s in scenes if s.name == scene.name]
        depth = 1
        while len({_folders(p, depth) for p in alike}) < len(alike) and depth < len(scene.path.parts):
            depth += 1
        out.append(scene if len(alike) == 1 else dataclasses.replace(
            scene, name="-".join([*_folders(scene.path, depth), scene.name])))
    names = [s.name for s in out]
    clash = sorted({n for n in names if names.count(n) > 1})
    if clash:
        raise QuekaroError(f"scenes named alike even by their folders: {', '.join(clash)}; rename a file")
    return out


def _folders(path: Path, depth: int) -> tuple[str, ...]:
    """The last `depth` folder names above `path`, the root left out (fewer near the root)."""
    names = [p for p in path.parent.parts if p != path.anchor]
    return tuple(names[-depth:]) if depth else ()


# ---- CPU time --------------------------------------------------------------------------------------


def proc_stat(pid: int) -> tuple[int, float]:
    """(parent pid, user + system CPU seconds) of a live process, from /proc (psutil is not a dependency)."""
    text = Path(f"/proc/{pid}/stat").read_text()
    fields = text[text.rindex(")") + 2:].split()  # after the command name, which may hold spaces
    return int(fields[1]), (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _proc_table() -> dict[int, tuple[int, float]]:
    """pid -> (parent pid, user + system CPU seconds) of every process readable in /proc."""
    out = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            out[int(entry)] = proc_stat(int(entry))
        except OSError:
            continue
    return out


def tree_cpu_seconds(roots: list[int]) -> float:
    """CPU seconds used so far by these processes and all their live descendants."""
    table = _proc_table()
    children: dict[int, list[int]] = {}
    for pid, (ppid, _) in table.items():
        children.setdefault(ppid, []).append(pid)
    seen, stack, total = set(), list(roots), 0.0
    while stack:
        pid = stack.pop()
        if pid in seen or pid not in table:
            continue
        seen.add(pid)
        total += table[pid][1]
        stack += children.get(pid, [])
    return total


def _self_cpu() -> float:
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


# ---- running the jobs ------------------------------------------------------------------------------


@contextmanager
def farm_runner(agents: int, threads: int, home: Path, units: int | None = None, adaptive: bool = False,
                asked: Asked = AS_WRITTEN, rules: Path | None = None, progressive: bool = False) -> Iterator[Any]:
    """A function (spec, level, spp, out, denoise=False) -> (report, wall s, CPU s) running jobs on a real
    local farm, timed from submit to done (`adaptive`: the optimised levels as adaptive jobs; `asked`: the
    sensor, integrator and depth; `rules`: the rule levels' rule file, carried in each job's bundle as
    `quekaro submit --rules` does; `denoise`: a denoised job; `progressive`: every job in passes)."""

    with LocalFarm(home, agents=agents, threads=max(1, threads // agents)) as farm:
        farm.wait_for_agents()
        client = farm.client()

        def run_job(spec: Any, level: str, spp: int, out: Path, denoise: bool = False) -> tuple[dict, float, float]:
            bundle = make_bundle(spec.path, spec.defines, out.with_suffix(".tar"), search_paths=spec.search_paths,
                                 rules=rules if level != "off" else None).path.read_bytes()
            roots = [p.pid for _, p in farm.procs]  # this process (and the XMPP server in it): _self_cpu
            cpu0, start = tree_cpu_seconds(roots) + _self_cpu(), time.perf_counter()
            options = {"level": level, "spp": spp, **asked.options()}
            options |= {"units": units} if units and level != "off" else {}
            options |= {"adaptive": True} if adaptive and level != "off" else {}
            options |= {"denoise": True} if denoise else {}
            options |= {"progressive": True} if progressive else {}
            job_id = client.submit(bundle, spec.defines, options)
            status = client.wait(job_id, JOB_TIMEOUT_S, while_waiting=farm.check_alive)
            wall = time.perf_counter() - start
            cpu = tree_cpu_seconds(roots) + _self_cpu() - cpu0
            if status["status"] != "done":
                raise QuekaroError(f"farm job {job_id} ({level}) ended {status['status']}: {status.get('error')}")
            client.result(job_id, out)
            return json.loads(out.with_suffix(".json").read_text()), wall, cpu

        yield run_job


@contextmanager
def inprocess_runner(threads: int, units: int | None = None, adaptive: bool = False,
                     asked: Asked = AS_WRITTEN, rules: Path | None = None, progressive: bool = False) -> Iterator[Any]:
    """The same function as `farm_runner`, timing the whole `quekaro render` process a user runs."""

    def run_job(spec: Any, level: str, spp: int, out: Path, denoise: bool = False) -> tuple[dict, float, float]:
        chosen = ["--units", str(units)] if units and level != "off" else []
        chosen += ["--adaptive"] if adaptive and level != "off" else []
        chosen += ["--rules", str(rules)] if rules is not None and level != "off" else []
        chosen += ["--denoise"] if denoise else []
        chosen += ["--progressive"] if progressive else []
        chosen += [*asked.args(), *(arg for folder in spec.search_paths for arg in ("-a", str(folder)))]
        cmd = [sys.executable, "-m", "quekaro", "render", str(spec.path), "--opt", level, "--spp", str(spp),
               "-t", str(threads), "-o", str(out), *chosen, *(f"-D{k}={v}" for k, v in spec.defines.items())]
        cpu0, start = _self_cpu(), time.perf_counter()
        done = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO)
        wall, cpu = time.perf_counter() - start, _self_cpu() - cpu0
        if done.returncode != 0:
            raise QuekaroError(f"quekaro render {spec.path} --opt {level} failed: {done.stderr.strip()[-600:]}")
        return json.loads(out.with_suffix(".json").read_text()), wall, cpu

    yield run_job


def spent(report: dict[str, Any]) -> dict[str, Any]:
    """How the rules spent samples: pixel-weighted mean spp, spp and depth ranges, unit count, and for a job
    in passes the passes of all its units."""
    units = report["units"]
    area = np.array([u["rect"][2] * u["rect"][3] for u in units], dtype=float)
    spp = np.array([u["spp"] for u in units], dtype=float)
    depth = np.array([u["depth"] if u["depth"] is not None else -1 for u in units], dtype=float)
    return {
        "units": len(units), "spp_mean": float((spp * area).sum() / area.sum()),
        "spp_min": int(spp.min()), "spp_max": int(spp.max()), "depth_min": int(depth.min()),
        "depth_max": int(depth.max()), "render_seconds": float(report["totals"]["render_seconds"]),
        "prepass_seconds": float(report["totals"].get("prepass_seconds", 0.0)),
        **({"passes": sum(int(u["passes"]) for u in units)} if all("passes" in u for u in units) else {}),
    }


def scene_spec(scene: SuiteScene, args: argparse.Namespace) -> SceneSpec:
    """The scene with its suite parameters, sized by --res, the -D parameters and the -a folders given."""
    defines = scene.with_size(args.res) if args.res else dict(scene.defines)
    defines.update(parse_defines(args.defines))
    return SceneSpec(scene.path, defines, tuple(args.search_paths))


def asked(args: argparse.Namespace) -> Asked:
    """What every job computes besides its scene file (-s, --integrator, --depth); plain Mitsuba the same."""
    return Asked(args.sensor, args.integrator, args.depth)


def scene_cells(scene: SuiteScene, agents: list[int], levels: list[str], args: argparse.Namespace,
                work: Path) -> list[dict[str, Any]]:
    """Every (agents, level) cell of one scene, raw and (--denoise) denoised, with errors, seams and the
    uniform baseline; with --denoise, the denoiser's bias on each denoised cell."""
    spec = scene_spec(scene, args)
    variant = job_variant(spec)  # the jobs' own: plain Mitsuba renders in it too
    ref = reference(spec, args.ref_spp, args.threads, Path(args.cache), variant, asked(args))
    line = spp_timing(spec, args.spp, args.threads, variant, asked(args))
    cells, diffs, units = [], {}, {}
    for n in agents:
        with runner(n, args, work / f"farm-{scene.name}-{n}") as run_job:
            for level, denoise in grid(levels, args.denoise):
                stem = work / f"{scene.name}-{n}-{level}{'-denoised' if denoise else ''}"
                cell, image, rects = run_cell(run_job, spec, level, args, stem, ref, denoise)
                if cell["variant"] != variant:
                    raise QuekaroError(f"{scene.name} level {level}: the job rendered in {cell['variant']}, "
                                       f"the reference in {variant}")
                cells.append({"scene": scene.name, "role": scene.role, "agents": n, **cell})
                if n == agents[0]:
                    diffs[label(cell)], units[label(cell)] = diff_image(image, ref), rects
    renders: dict[int, Any] = {}  # plain renders by spp, shared by the raw and the denoised baselines
    raw = [c for c in cells if not denoised(c)]
    uniform = uniform_baseline(spec, raw, agents[0], args, line, ref, variant, units, renders)
    for cell in raw:
        cell.update(uniform[cell["level"]])
    if args.denoise:
        bias, diffs["denoise-bias"] = denoiser_bias(spec, args, ref, work / f"{scene.name}-bias.exr")
        for cell in (c for c in cells if denoised(c)):
            cell.update(denoised_baseline(spec, cell, args, line, ref, variant, renders), **bias)
    write_diff_images(scene.name, diffs, Path(args.out))
    return cells


def grid(levels: list[str], denoise: bool) -> list[tuple[str, bool]]:
    """(level, denoised) of a scene's cells: each level raw; with `denoise`, level off (uniform+denoise)
    and each level again, denoised."""
    return [(level, False) for level in levels] + [(level, True) for level in dict.fromkeys(["off", *levels])
                                                   if denoise]


def denoised(cell: dict[str, Any]) -> bool:
    """Whether a cell's jobs were denoised (a cell without the key is raw)."""
    return bool(cell.get("denoise", False))


def label(cell: dict[str, Any]) -> str:
    """A cell's name in tables, plot and files: its level; denoised, uniform+denoise (level off) or
    LEVEL+denoise."""
    if not denoised(cell):
        return cell["level"]
    return ("uniform" if cell["level"] == "off" else cell["level"]) + "+denoise"


def runner(n: int, args: argparse.Namespace, home: Path) -> Any:
    """The job runner of this run: one process (--inprocess) or a farm of n agents at `home`."""
    if args.inprocess:
        return inprocess_runner(args.threads, args.units, args.adaptive, asked(args), args.rules, args.progressive)
    return farm_runner(n, args.threads, home, args.units, args.adaptive, asked(args), args.rules, args.progressive)


def run_cell(run_job: Callable, spec: SceneSpec, level: str, args: argparse.Namespace, stem: Path,
             ref: np.ndarray, denoise: bool = False) -> tuple[dict[str, Any], np.ndarray, list[Rect]]:
    """One level's jobs (warm-up, then the timed runs), denoised with `denoise`: the cell's figures, its
    last image, its units. The warm-up (skipped by `--no-warmup`) compiles the job's kernels and is reported
    as the first run's time; then `--runs` timed runs. The figures: the median wall and CPU seconds, the
    errors against the reference averaged over every run (the warm-up included: seeds follow the job id),
    the seam measure of the last image at the units' borders, how the rules spent samples, and a denoised
    cell's `denoise_account`."""
    images, raws, first = [], [], {}
    if args.warmup:  # compiles this job's kernels (one per window or batch rectangle size) before timing it
        warm, wall, _ = run_job(spec, level, args.spp, stem.with_name(stem.name + "-warm.exr"), denoise=denoise)
        images.append(read_image(warm["image"]["file"])[..., :3])  # the film's file: .pfm, .rgbe or .exr
        raws.append(raw_image(warm))
        first = {"first_seconds": wall}
    timed = []
    for r in range(args.runs):
        out = stem.with_name(f"{stem.name}-{r}.exr")
        timed.append(run_job(spec, level, args.spp, out, denoise=denoise))
        images.append(read_image(timed[-1][0]["image"]["file"])[..., :3])
        raws.append(raw_image(timed[-1][0]))
    report = timed[-1][0]
    used = [spent(rep) for rep, _, _ in timed]
    rects = [Rect.from_list(u["rect"]) for u in report["units"]]
    seams = seam_measure(images[-1], ref, rects)
    account = denoise_account([rep for rep, _, _ in timed], raws, ref) if denoise else {}
    passes = {"progressive": True} if args.progressive else {}  # a run's cells without the key were whole
    return {"level": level, "denoise": denoise, **passes, "variant": report["effects"]["variant"],
            "seconds": float(np.median([wall for _, wall, _ in timed])),
            "cpu_seconds": float(np.median([cpu for _, _, cpu in timed])),
            "seconds_runs": [wall for _, wall, _ in timed], **first, **mean_metrics(images, ref), **used[-1],
            "render_seconds": float(np.median([u["render_seconds"] for u in used])),
            **{f"seam_{k}": v for k, v in seams.to_dict().items()}, **account}, images[-1], rects


def raw_image(report: dict[str, Any]) -> np.ndarray | None:
    """A denoised job's raw colour (its OUT.raw.exr, as the report names it), or None: a raw job, or a
    farm's raw file not where its report says."""
    named = (report.get("denoise") or {}).get("raw")
    return read_image(named)[..., :3] if named and Path(named).is_file() else None


def denoise_account(reports: list[dict[str, Any]], raws: list[np.ndarray | None],
                    ref: np.ndarray) -> dict[str, Any]:
    """A denoised cell's own figures: the medians of the AOV pass's and the denoising's seconds over the
    timed runs (where the reports say them), and the raw images' (box filter) relMSE and FLIP against the
    same reference, averaged over every run (where every raw file was found)."""
    aov = [r["render_calls"]["aov_pass_seconds"] for r in reports
           if "aov_pass_seconds" in (r.get("render_calls") or {})]
    out = {"denoise_seconds": float(np.median([r["denoise"]["seconds"] for r in reports]))}
    out |= {"aov_pass_seconds": float(np.median(aov))} if aov else {}
    if raws and all(r is not None for r in raws):
        out |= {"raw_relmse": float(np.mean([relmse(r, ref) for r in raws])),
                "raw_flip": float(np.mean([flip(r, ref) for r in raws]))}
    return out


def mean_metrics(images: list[np.ndarray], ref: np.ndarray) -> dict[str, float]:
    """Every metric averaged over independent renders of one setting (one render's relMSE swings by tens
    of percent on a caustic, where a few pixels hold most of the error); `relmse_runs` lists them."""
    runs = [all_metrics(image, ref) for image in images]
    mean = {key: float(np.mean([r[key] for r in runs])) for key in runs[0]}
    return {**mean, "relmse_runs": [r["relmse"] for r in runs]}


def wall_spp(seconds: float, line: tuple[float, float]) -> tuple[int, bool]:
    """The uniform spp whose plain-Mitsuba process takes `seconds` by the line (t0, k), at least 1, and
    whether it fits: below half a sample's time beyond plain Mitsuba's start-up, no uniform spp is as fast
    (1 spp, the least, takes longer, and a ratio against it would flatter the cell)."""
    t0, k = line
    return max(1, round((seconds - t0) / k)), (seconds - t0) / k >= 0.5


def uniform_baseline(spec: Any, cells: list[dict[str, Any]], n: int, args: argparse.Namespace,
                     line: tuple[float, float], ref: np.ndarray, variant: str,
                     units: dict[str, list[Rect]], renders: dict[int, Any] | None = None) -> dict[str, dict[str, Any]]:
    """Per level: plain renders at the spp taking the wall time and the render time of its n-agent cell
    (the fewest agents): `uniform_spp` matches the job's wall time (what a user waits for), and
    `render_uniform_spp` its render seconds alone (the allocation without the overheads, by the slope k:
    render_time_spp). Plain Mitsuba runs as a user runs it (`planning.plain`, the whole process timed).
    The seam measure of the first one at the level's unit borders is the measure's control: plain Mitsuba
    has no borders, so what it reads there is the measure's own false alarm on this scene. `renders`:
    plain renders by spp, reused (`plain_at`)."""
    t0, k = line
    out = {}
    for cell in (c for c in cells if c["agents"] == n):
        wall, fits = wall_spp(cell["seconds"], line)
        entry = {"uniform_t0_s": t0, "uniform_s_per_spp": k, "uniform_fits": fits}
        for prefix, spp in (("uniform", wall), ("render_uniform", render_time_spp(cell["render_seconds"], k, n,
                                                                                  args.threads))):
            figures, first = plain_at(spec, spp, args, variant, ref, renders)
            entry.update({f"{prefix}_{m}": v for m, v in figures.items()})
            if prefix == "uniform" and units.get(cell["level"]):
                seams = seam_measure(first, ref, units[cell["level"]]).to_dict()
                entry.update({f"uniform_seam_{m}": v for m, v in seams.items()})
        out[cell["level"]] = entry
    return out


def denoised_baseline(spec: Any, cell: dict[str, Any], args: argparse.Namespace, line: tuple[float, float],
                      ref: np.ndarray, variant: str, renders: dict[int, Any]) -> dict[str, Any]:
    """A denoised cell's baseline: raw plain Mitsuba (the scene's own filter, as the raw cells' baseline) at
    the uniform spp taking the cell's own wall time, whatever its agent count. No render-time baseline: a
    denoised job's AOV pass and denoising are part of what it costs."""
    spp, fits = wall_spp(cell["seconds"], line)
    figures, _ = plain_at(spec, spp, args, variant, ref, renders)
    return {"uniform_t0_s": line[0], "uniform_s_per_spp": line[1], "uniform_fits": fits,
            **{f"uniform_{m}": v for m, v in figures.items()}}


def render_time_spp(render_seconds: float, k: float, agents: int, threads: int) -> int:
    """The uniform spp whose render alone takes the job's render seconds: by the slope k of plain Mitsuba's
    time in spp at `threads` threads, without its intercept t0 (the process's start, load and writing,
    which a job's render seconds do not hold either). A farm's render seconds are its agents' added up,
    each on threads // agents threads (farm_runner), so they are scaled to `threads`."""
    per_renderer = max(1, threads // agents)
    return max(1, round(render_seconds * per_renderer / threads / k))


def plain_at(spec: Any, spp: int, args: argparse.Namespace, variant: str, ref: np.ndarray,
             renders: dict[int, Any] | None = None) -> tuple[dict[str, Any], np.ndarray]:
    """Plain renders at `spp`, as many seeds as a cell's errors average: spp, the fastest one's seconds and
    the mean errors; and the first image. `renders` keeps them by spp: the seeds follow the spp, so a
    second call at one spp would render the same images again."""
    if renders is not None and spp in renders:
        return renders[spp]
    runs = args.runs + int(args.warmup)
    plain = [plain_render(spec, spp, args.threads, variant, seed=4242 + spp + 7919 * i, asked=asked(args))
             for i in range(runs)]
    figures = {"spp": spp, "seconds": min(t for _, t in plain),
               **mean_metrics([pixels for pixels, _ in plain], ref)}
    if renders is not None:
        renders[spp] = (figures, plain[0][0])
    return figures, plain[0][0]


def denoiser_bias(spec: SceneSpec, args: argparse.Namespace, ref: np.ndarray,
                  out: Path) -> tuple[dict[str, Any], np.ndarray]:
    """The denoiser's bias: the scene denoised at `bias_spp` (one `quekaro render --denoise` process, at
    level off) against the reference, where little noise is left for it to remove: its relMSE and FLIP,
    its raw image's (box filter), the reference's warning if too noisy for it, and its difference image."""
    spp = bias_spp(args)
    with inprocess_runner(args.threads, asked=asked(args)) as run_job:
        report, wall, _ = run_job(spec, "off", spp, out, denoise=True)
    image, raw = read_image(report["image"]["file"])[..., :3], raw_image(report)
    return {"bias_spp": spp, "bias_seconds": wall, "bias_relmse": relmse(image, ref), "bias_flip": flip(image, ref),
            "bias_raw_relmse": relmse(raw, ref), "bias_raw_flip": flip(raw, ref),
            "bias_warning": reference_warning(args.ref_spp, spp)}, diff_image(image, ref)


# ---- outputs ---------------------------------------------------------------------------------------


def write_diff_images(name: str, diffs: dict[str, np.ndarray], out: Path) -> None:
    """Grey difference images against the reference, one per cell label (white = DIFF_WHITE or more), at a
    reader's size (bench.images); a label's "+" is "-" in the file name (cbox-S-denoise.png)."""
    for key, diff in diffs.items():
        write_difference(out / "accuracy-diff" / f"{name}-{key.replace('+', '-')}.png", diff / DIFF_WHITE)


def run(args: argparse.Namespace) -> dict[str, Any]:
    scenes, agents, levels = parse_grid(args)
    if args.rules is not None:  # refused (naming file, line and label) before any scene renders
        check_rules(args.rules)
    started, load_before = time.perf_counter(), os.getloadavg()[0]
    settings = run_settings(args, agents, levels)  # digests --rules once; `mode` shows that digest
    cells = resumed_cells(Path(args.out), settings) if args.resume else []
    keys = {s.name: content_key(scene_spec(s, args)) for s in scenes}
    # A scene whose files changed since the partial run is measured again, not kept.
    changed = sorted({c["scene"] for c in cells if c["scene"] in keys and c.get("scene_key") != keys[c["scene"]]})
    cells = [c for c in cells if c["scene"] not in changed]
    done = {c["scene"] for c in cells}
    with tempfile.TemporaryDirectory(prefix="quekaro-bench-") as tmp:
        for scene in (s for s in scenes if s.name not in done):  # each scene's cells are kept as they come
            try:
                cells += [{**c, "scene_key": keys[scene.name]}
                          for c in scene_cells(scene, agents, levels, args, Path(tmp))]
            except KeyboardInterrupt:
                kept = sorted({c["scene"] for c in cells})
                print(f"interrupted in {scene.name}; " + (
                    f"the finished scenes ({', '.join(kept)}) are kept in {Path(args.out) / 'accuracy.partial.jsonl'}"
                    ": the same command with --resume measures only the others" if kept else "no scene finished"),
                    file=sys.stderr)
                raise
            write_partial(settings, cells, Path(args.out))
    names = [s.name for s in scenes]
    cells = [c for c in cells if c["scene"] in names]
    resumed = [n for n in names if n in done]
    result = {
        "scenes": {s.name: {"role": s.role, "path": _shown(s.path), "defines": scene_spec(s, args).defines}
                   for s in scenes}, "spp": args.spp, "ref_spp": args.ref_spp, "threads": args.threads,
        "mode": mode(args, settings.get("rules_digest")), "agents": agents, "levels": levels,
        "asked": asked(args).options(),
        "cells": cells, "targets": targets(cells, agents[0]),
        "denoise_targets": denoise_targets(cells, args.inprocess) if args.denoise else [],
        "seconds": time.perf_counter() - started,
        "load": [load_before, os.getloadavg()[0]], "resumed": resumed, "changed": changed,
    }
    result["outputs"] = [str(p) for p in write_outputs(result, Path(args.out))]
    result["report"] = result["outputs"][0]  # accuracy.md, whose provenance bench.commands keeps
    if not args.json:
        print(format_report(result))
    return result


def rules_file(args: argparse.Namespace) -> Path | None:
    """The rule file the levels planned with (bench.commands records its hash)."""
    return rules_for(args, parse_levels(args.levels))


def run_settings(args: argparse.Namespace, agents: list[int], levels: list[str]) -> dict[str, Any]:
    """What makes two runs' cells comparable (a resumed run must match every one)."""
    return {"spp": args.spp, "ref_spp": args.ref_spp, "threads": args.threads, "res": args.res,
            "defines": sorted(args.defines), "agents": agents, "levels": levels, "runs": args.runs,
            "warmup": args.warmup, "inprocess": args.inprocess, "units": args.units, "adaptive": args.adaptive,
            **asked(args).options(),  # only what differs from the scene as written: older partial runs still match
            **({"rules_digest": rules_digest(args.rules)} if args.rules is not None else {}),
            **({"search_paths": [str(p) for p in args.search_paths]} if args.search_paths else {}),
            **({"denoise": True, "bias_spp": bias_spp(args)} if args.denoise else {}),  # raw runs match as before
            **({"progressive": True} if args.progressive else {})}


def mode(args: argparse.Namespace, digest: str | None = None) -> str:
    """How the jobs ran: through a farm or in one process, whether the optimised levels were adaptive, with
    which rule file (`digest`, what its rules compute: bench.provenance.rules_digest) when not the default,
    whether denoised cells were added (--denoise), and whether every job ran in passes (--progressive)."""
    rules = f", rules {_shown(args.rules)} (digest {digest[:12]})" if digest else ""
    return (("inprocess" if args.inprocess else "farm") + (", adaptive" if args.adaptive else "") + rules
            + (", denoise" if args.denoise else "") + (", progressive" if args.progressive else ""))


def write_partial(settings: dict[str, Any], cells: list[dict[str, Any]], out: Path) -> None:
    """The settings, then the cells so far, as JSON lines beside the outputs (accuracy.partial.jsonl)."""
    out.mkdir(parents=True, exist_ok=True)
    text = "".join(json.dumps(c) + "\n" for c in [{"settings": settings}, *cells])
    # Whole or not at all: a run killed while it writes leaves the previous scenes' file to resume from.
    written_atomically(out / "accuracy.partial.jsonl", lambda tmp: tmp.write_text(text), "a partial run's cells")


def resumed_cells(out: Path, settings: dict[str, Any]) -> list[dict[str, Any]]:
    """The cells of a partial run with these settings; refused, naming the field, when they differ."""
    path = out / "accuracy.partial.jsonl"
    if not path.exists():
        raise QuekaroError(f"--resume: {path} does not exist (no partial run to resume)")
    lines = []
    for number, line in enumerate(path.read_text().splitlines(), 1):
        try:
            lines += [json.loads(line)] if line.strip() else []
        except ValueError as exc:
            raise QuekaroError(f"--resume: {path} line {number} is not JSON ({exc}); run without --resume "
                               "to measure every scene anew") from None
    saved = lines[0].get("settings") if lines and isinstance(lines[0], dict) else None
    if saved is None:
        raise QuekaroError(f"--resume: {path} has no settings line (empty, or written by an older version); "
                           "run without --resume to measure every scene anew")
    for key in dict.fromkeys([*settings, *saved]):  # a key only one side has differs too (e.g. --rules)
        if saved.get(key) != settings.get(key):
            raise QuekaroError(f"--resume: {path} was written with {key}={saved.get(key)!r}, "
                               f"this run asks for {settings.get(key)!r}")
    return lines[1:]


def _shown(path: Path) -> str:
    """A scene's path as the report shows it: relative to the repository's parent where it lies inside,
    as named (../shared may be a link to elsewhere) or once resolved."""
    for candidate in (Path(os.path.abspath(path)), path.resolve()):
        if candidate.is_relative_to(REPO.parent):
            return str(candidate.relative_to(REPO.parent))
    return str(path)


def targets(cells: list[dict[str, Any]], n: int) -> list[dict[str, Any]]:
    """The targets over the scenes run, n-agent cells: per level, the median over scenes of relMSE over
    uniform's at equal wall time (in passes, --progressive: every level, off too, at most PASSES_RELMSE_RATIO,
    never worse than lowering spp); per scene, level S's time over off's and its mean pixel difference. Raw
    cells only: the denoised ones have targets of their own (`denoise_targets`)."""
    mine = [c for c in cells if c["agents"] == n and not denoised(c)]
    in_passes = any(c.get("progressive") for c in mine)
    limit = PASSES_RELMSE_RATIO if in_passes else RELMSE_RATIO
    out = []
    for level in dict.fromkeys(c["level"] for c in mine if in_passes or c["level"] != "off"):
        at_level = [c for c in mine if c["level"] == level]
        name = (f"level {level}{' in passes' if in_passes else ''}: median relMSE over {len(at_level)} scene(s) "
                f"<= {limit} x uniform (equal wall time)")
        unfit = [c["scene"] for c in at_level if not c.get("uniform_fits", True)]
        if unfit:  # not measured, so neither passed nor missed: said as such
            out.append({"name": f"{name}; on {', '.join(unfit)} the cell took less than plain Mitsuba's 1 spp",
                        "value": None, "pass": False})
            continue
        value = float(np.median([c["relmse"] / max(c["uniform_relmse"], 1e-30) for c in at_level]))
        out.append({"name": name, "value": value, "pass": value <= limit})
    for scene in dict.fromkeys(c["scene"] for c in mine):
        by_level = {c["level"]: c for c in mine if c["scene"] == scene}
        if "S" in by_level and "off" in by_level:
            ratio = by_level["S"]["seconds"] / by_level["off"]["seconds"]
            out.append({"name": f"{scene} level S time <= {S_TIME_RATIO} x off", "value": ratio,
                        "pass": ratio <= S_TIME_RATIO})
        if "S" in by_level:
            diff = by_level["S"]["mean_pixel_diff_percent"]
            out.append({"name": f"{scene} level S mean pixel diff <= {S_DIFF_PERCENT} %", "value": diff,
                        "pass": diff <= S_DIFF_PERCENT})
        for level, c in by_level.items():
            if c["seam_seam"]:
                plain = (f"; plain Mitsuba at the same borders: z {c['uniform_seam_z']:.1f}, unit "
                         f"{c['uniform_seam_unit_z']:.1f}{' SEAM' if c['uniform_seam_seam'] else ''}"
                         if "uniform_seam_z" in c else "")
                out.append({"name": f"{scene} level {level}: no seam at unit borders (unit {c['seam_worst_unit']}, "
                                    f"z {c['seam_z']:.1f}{plain})", "value": c["seam_unit_z"], "pass": False})
    return out


def paper_table(cells: list[dict[str, Any]], scene: str, levels: list[str]) -> list[str]:
    """Rows agents, columns levels; each cell: seconds, mean pixel diff %, relMSE (and uniform's)."""
    lines = ["| agents | " + " | ".join(levels) + " |", "|---|" + "---|" * len(levels)]
    for n in sorted({c["agents"] for c in cells if c["scene"] == scene}):
        row = {c["level"]: c for c in cells if c["scene"] == scene and c["agents"] == n}
        parts = [f"{row[lv]['seconds']:.1f} s, {row[lv]['mean_pixel_diff_percent']:.2f} %, "
                 f"relMSE {row[lv]['relmse']:.4f}" if lv in row else "" for lv in levels]
        lines.append(f"| {n} | " + " | ".join(parts) + " |")
    first = min(c["agents"] for c in cells if c["scene"] == scene)
    row = {c["level"]: c for c in cells if c["scene"] == scene and c["agents"] == first}
    for prefix, title in (("uniform", "uniform, equal wall time"), ("render_uniform", "uniform, equal render time")):
        parts = [f"{row[lv][prefix + '_spp']} spp{_longer(row[lv], prefix)}, "
                 f"{row[lv][prefix + '_mean_pixel_diff_percent']:.2f} %, "
                 f"relMSE {row[lv][prefix + '_relmse']:.4f}" if lv in row else "" for lv in levels]
        lines.append(f"| {title} | " + " | ".join(parts) + " |")
    return lines


DENOISE_ABOUT = ("Denoised cells (`--denoise`): each job renders with a box filter, adds the denoiser's AOV pass and "
                 "denoises (its seconds hold both); raw uniform plain Mitsuba renders with the scene's own filter at "
                 "the spp taking the cell's wall time. Both are scored against one reference, the scene as written "
                 "(its own filter) at {ref_spp} spp, so a denoised image's error holds the filter's difference too. "
                 "\"its raw\" is the same job's raw image (OUT.raw.exr, box filter).")


def denoise_table(cells: list[dict[str, Any]], scene: str) -> list[str]:
    """A scene's denoised cells: time, errors, its raw image's, and raw uniform's at equal wall time."""
    lines = ["| agents | setting | s | AOV pass s | denoise s | relMSE | FLIP | its raw: relMSE, FLIP "
             "| raw uniform, equal wall time | relMSE / uniform | FLIP / uniform |", "|" + "---|" * 11]
    for c in (c for c in cells if c["scene"] == scene and denoised(c)):
        aov = f"{c['aov_pass_seconds']:.2f}" if "aov_pass_seconds" in c else "-"
        raw = f"{c['raw_relmse']:.4f}, {c['raw_flip']:.4f}" if "raw_relmse" in c else "-"
        lines.append(f"| {c['agents']} | {label(c)} | {c['seconds']:.1f} | {aov} | {c['denoise_seconds']:.2f} "
                     f"| {c['relmse']:.4f} | {c['flip']:.4f} | {raw} | {c['uniform_spp']} spp{_longer(c, 'uniform')}, "
                     f"relMSE {c['uniform_relmse']:.4f}, FLIP {c['uniform_flip']:.4f} "
                     f"| {c['relmse'] / max(c['uniform_relmse'], 1e-30):.3f} "
                     f"| {c['flip'] / max(c['uniform_flip'], 1e-30):.3f} |")
    return lines


def bias_line(cells: list[dict[str, Any]], scene: str) -> str:
    """The denoiser's bias on a scene, as its denoised cells carry it (`denoiser_bias`)."""
    c = next(c for c in cells if c["scene"] == scene and denoised(c))
    warning = f"; {c['bias_warning']}" if c.get("bias_warning") else ""
    return (f"denoiser's bias: {scene} denoised at {c['bias_spp']} spp (level off, one process, "
            f"{c['bias_seconds']:.1f} s) against the reference: relMSE {c['bias_relmse']:.4f}, FLIP "
            f"{c['bias_flip']:.4f}; its raw image (box filter) relMSE {c['bias_raw_relmse']:.4f}, FLIP "
            f"{c['bias_raw_flip']:.4f}; difference image accuracy-diff/{scene}-denoise-bias.png{warning}")


def denoise_targets(cells: list[dict[str, Any]], inprocess: bool) -> list[dict[str, Any]]:
    """The denoised targets (issue 64), per agent count and denoised setting: the medians over the scenes of
    the cells' relMSE and FLIP over raw uniform's at each cell's wall time (RELMSE_DENOISED, FLIP_DENOISED)."""
    mine = [c for c in cells if denoised(c)]
    out = []
    for n in sorted({c["agents"] for c in mine}):
        where = "one process" if inprocess else f"{n}-agent farm"
        for name in dict.fromkeys(label(c) for c in mine if c["agents"] == n):
            at = [c for c in mine if c["agents"] == n and label(c) == name]
            out += [ratio_target(at, metric, limit, f"{where}, {name}")
                    for metric, limit in (("relmse", RELMSE_DENOISED), ("flip", FLIP_DENOISED))]
    return out


def ratio_target(at: list[dict[str, Any]], metric: str, limit: float, what: str) -> dict[str, Any]:
    """One denoised target: the median over these cells of `metric` over raw uniform's, and each scene's."""
    name = (f"{what}: median {'relMSE' if metric == 'relmse' else 'FLIP'} over {len(at)} scene(s) <= {limit} x "
            "raw uniform (equal wall time)")
    unfit = [c["scene"] for c in at if not c.get("uniform_fits", True)]
    if unfit:  # not measured, so neither met nor missed
        return {"name": f"{name}; on {', '.join(unfit)} the cell took less than plain Mitsuba's 1 spp",
                "value": None, "limit": limit, "pass": False, "scenes": {}}
    ratios = {c["scene"]: c[metric] / max(c[f"uniform_{metric}"], 1e-30) for c in at}
    value = float(np.median(list(ratios.values())))
    return {"name": name, "value": value, "limit": limit, "pass": value <= limit, "scenes": ratios}


def denoise_target_line(t: dict[str, Any]) -> str:
    """A denoised target as printed: its figure, met or missed, and each scene's ratio."""
    if t["value"] is None:
        return f"target: {t['name']}: not measured"
    each = ", ".join(f"{scene} {ratio:.3f}" for scene, ratio in t["scenes"].items())
    return f"target: {t['name']}: {t['value']:.3f} {'met' if t['pass'] else 'missed'} ({each})"


def _longer(cell: dict[str, Any], prefix: str) -> str:
    """A note where the equal-wall-time baseline had to take longer than the cell (its least spp)."""
    unfit = prefix == "uniform" and not cell.get("uniform_fits", True)
    return " (the least; takes longer than the cell)" if unfit else ""


def spending_lines(cells: list[dict[str, Any]]) -> list[str]:
    """The cells' spending: "first run s" is the unmeasured warm-up's wall time (its new kernels compiled)."""
    lines = ["| scene | agents | level | s | first run s | CPU s | render s | pre-pass s | units "
             "| spp mean (min-max) | depth | diff % | RMSE | relMSE | FLIP | seam z (worst unit) "
             "| plain Mitsuba's seam z there |",
             "|" + "---|" * 17]
    for c in cells:
        plain = _seam_text(c, "uniform_seam_") if "uniform_seam_z" in c else "-"
        first = f"{c['first_seconds']:.1f}" if "first_seconds" in c else "-"
        lines.append(
            f"| {c['scene']} | {c['agents']} | {label(c)} | {c['seconds']:.1f} | {first} | {c['cpu_seconds']:.1f} "
            f"| {c['render_seconds']:.1f} | {c['prepass_seconds']:.2f} | {c['units']} "
            f"| {c['spp_mean']:.0f} ({c['spp_min']}-{c['spp_max']}) | {_depths(c)} "
            f"| {c['mean_pixel_diff_percent']:.2f} | {c['rmse']:.4f} | {c['relmse']:.4f} | {c['flip']:.4f} "
            f"| {_seam_text(c, 'seam_')} | {plain} |")
    return lines


def _seam_text(cell: dict[str, Any], prefix: str) -> str:
    """"z (worst unit's z[ SEAM])" of the seam figures stored under `prefix` in a cell."""
    return f"{cell[prefix + 'z']:.1f} ({cell[prefix + 'unit_z']:.1f}{' SEAM' if cell[prefix + 'seam'] else ''})"


def _depths(cell: dict[str, Any]) -> str:
    """The cell's depth range; Mitsuba's -1 (no limit) in words, as "-1--1" read as a typo."""
    low, high = (("unbounded" if d < 0 else str(d)) for d in (cell["depth_min"], cell["depth_max"]))
    return low if low == high == "unbounded" else f"{low}-{high}"


def format_report(result: dict[str, Any]) -> str:
    chosen = "".join(f", {k} {v}" for k, v in (result.get("asked") or {}).items())
    lines = [f"mode {result['mode']}{chosen}, user spp {result['spp']}, reference {result['ref_spp']} spp, "
             f"{result['threads']} threads; took {result['seconds']:.0f} s; load average (1 min) "
             f"{result['load'][0]:.1f} at the start, {result['load'][1]:.1f} at the end"
             + (f"; kept from a partial run (--resume): {', '.join(result['resumed'])}" if result.get("resumed")
                else "")
             + (f"; measured again, their files changed since the partial run: {', '.join(result['changed'])}"
                if result.get("changed") else ""), ""]
    cells = result["cells"]
    if any(denoised(c) for c in cells):
        lines += [DENOISE_ABOUT.format(ref_spp=result["ref_spp"]), ""]
    for scene in dict.fromkeys(c["scene"] for c in cells):
        about = result["scenes"][scene]
        lines += [f"## {scene} ({about['role']}: {about['path']} {about['defines']})", "",
                  *paper_table([c for c in cells if not denoised(c)], scene, result["levels"]), ""]
        if any(denoised(c) for c in cells if c["scene"] == scene):
            lines += [*denoise_table(cells, scene), "", bias_line(cells, scene), ""]
    lines += [*spending_lines(cells), ""]
    for t in result["targets"]:
        verdict = "not measured" if t["value"] is None else f"{t['value']:.3f} {'PASS' if t['pass'] else 'MISS'}"
        lines.append(f"target: {t['name']}: {verdict}")
    lines += [denoise_target_line(t) for t in result.get("denoise_targets") or []]
    return "\n".join(lines)


def write_outputs(result: dict[str, Any], out: Path) -> list[Path]:
    """accuracy.md, accuracy.csv and accuracy.png (error against time, fuzzy and uniform)."""
    out.mkdir(parents=True, exist_ok=True)
    md, csv_path, png = out / "accuracy.md", out / "accuracy.csv", out / "accuracy.png"
    md.write_text("# Accuracy against time (`quekaro bench accuracy`)\n\n" + format_report(result) + "\n")
    with csv_path.open("w", newline="") as fh:
        fields = list(dict.fromkeys(k for cell in result["cells"] for k in cell))  # resumed cells may lack some
        writer = csv.DictWriter(fh, fieldnames=fields)
        writer.writeheader()
        writer.writerows(result["cells"])
    plot(result["cells"], png)
    return [md, csv_path, png]


def plot(every: list[dict[str, Any]], path: Path) -> None:
    """One panel per scene: relMSE against seconds, the fuzzy levels (filled, per agent count, at wall
    time; hollow, fewest agents, at render time) against the line of uniform-spp plain renders; with
    denoised cells, those too (diamonds, at wall time) and the denoiser's bias (`plot_denoised`)."""
    cells = [c for c in every if not denoised(c)]
    scenes = list(dict.fromkeys(c["scene"] for c in cells))
    cols = min(3, len(scenes))
    rows = (len(scenes) + cols - 1) // cols
    fig = Figure(figsize=(4.2 * cols, 3.4 * rows), dpi=100)  # no pyplot: no GUI backend, no global state
    for k, scene in enumerate(scenes):
        ax = fig.add_subplot(rows, cols, k + 1)
        mine = [c for c in cells if c["scene"] == scene]
        first = min(c["agents"] for c in mine)
        for i, n in enumerate(sorted({c["agents"] for c in mine})):
            sel = sorted((c for c in mine if c["agents"] == n), key=lambda c: c["seconds"])
            how = "in passes" if sel[0].get("progressive") else "whole units"
            ax.plot([c["seconds"] for c in sel], [c["relmse"] for c in sel], "o", color=f"C{i}",
                    label=f"fuzzy, {how}, {n} agent(s), wall")
            for c in sel:
                ax.annotate(c["level"], (c["seconds"], c["relmse"]), fontsize=7)
            if n == first:
                ax.plot([c["render_seconds"] for c in sel], [c["relmse"] for c in sel], "o", mfc="none",
                        color=f"C{i}", label="fuzzy, render time")
        others = [c for c in every if c["scene"] == scene and denoised(c)]
        plot_denoised(ax, others)
        uniform = sorted([(c[f"{p}_seconds"], c[f"{p}_relmse"]) for c in mine if c["agents"] == first
                          for p in ("uniform", "render_uniform")]
                         + [(c["uniform_seconds"], c["uniform_relmse"]) for c in others])
        ax.plot(*zip(*uniform, strict=True), "s--", color="grey", alpha=0.7, label="uniform spp (plain)")
        ax.set_title(scene, fontsize=9)
        ax.set_xlabel("seconds", fontsize=8)
        ax.set_ylabel("relMSE", fontsize=8)
        ax.set_yscale("log")
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=7)
        if k == 0:
            ax.legend(fontsize=6)
    fig.tight_layout()
    write_plot(path, fig)


def plot_denoised(ax: Any, cells: list[dict[str, Any]]) -> None:
    """A scene's denoised cells on its panel (diamonds, per agent count, at wall time; colours after the raw
    cells') and the denoiser's bias as a dotted line: the error a denoised job keeps however long it runs."""
    counts = sorted({c["agents"] for c in cells})
    for i, n in enumerate(counts):
        sel = sorted((c for c in cells if c["agents"] == n), key=lambda c: c["seconds"])
        colour = f"C{i + 3}"
        ax.plot([c["seconds"] for c in sel], [c["relmse"] for c in sel], "D-", color=colour, ms=4,
                label=f"denoised, {n} agent(s), wall")
        for c in sel:
            ax.annotate(label(c).replace("uniform+denoise", "off+dn").replace("+denoise", "+dn"),
                        (c["seconds"], c["relmse"]), fontsize=7, color=colour)
    if cells:
        c = cells[0]
        ax.axhline(c["bias_relmse"], ls=":", color="C3", label=f"denoiser's bias ({c['bias_spp']} spp)")
