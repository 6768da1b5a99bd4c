"""`quekaro bench accuracy`: what accuracy costs in time, per (agents, optimisation level), against the
obvious alternative of lowering spp everywhere.

For each benchmark scene: a reference (no optimisation, `--ref-spp`) rendered once and cached; then the
grid agents x levels, each cell a real job, through a real local farm (`farm.local.LocalFarm`,
one farm per agent count) or, with `--inprocess`, through `planning.pipeline.render_job` (one process,
so only the smallest agent count runs). Each cell's job runs once unmeasured first (`--no-warmup`
skips it): Dr.Jit compiles a kernel per unit window size (~0.5 s each), which at the default size
would otherwise be most of a job's time and fall on whichever cell first meets a size. Then it runs
`--runs` times, timed. Per cell: the median wall seconds (submit to done) and CPU seconds of every
process involved; the errors against the reference (`core.render.metrics`), averaged over every run, the
warm-up included (independent samples: seeds follow the job id; one render's relMSE on a caustic swings
by tens of percent); and how the rules spent samples. The same plan is made every time (the pre-pass
seed follows the scene and options, `core.model.seeds.plan_seed`). In a farm whose agents hold two units,
a unit's render seconds include the overlap with the previous tile's upload (the CPU is shared), so the
equal-render-time matching is cleanest with `--inprocess`; `quekaro bench allocation` isolates the
allocation itself, with expected instead of sampled errors.

The uniform baseline: plain Mitsuba on the whole image at the single spp that takes the same time.
Render time is linear in spp (design.md section 3): the plain render is timed at two spp once, and the
line t(spp) = t0 + k spp gives the spp for a time. Two matchings are reported per level, both against
the level's cell with the fewest agents: `uniform_spp` matches the job's wall time (what a user waits
for, pre-pass and pipeline included), `render_uniform_spp` only its render seconds (the allocation
alone, overheads excluded). Each uniform render is averaged over as many seeds as the cell's errors.
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import os
import resource
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib import image as mpimg
from matplotlib.figure import Figure

from core.errors import QuekaroError
from core.model.geometry import Rect
from core.model.job import RenderOptions, SceneSpec
from core.render.bundle import make_bundle
from core.render.imageio import read_exr, write_exr
from core.render.metrics import all_metrics, diff_image
from core.render.scene import image_size
from core.render.worker import RenderRequest, RenderWorker
from farm.local import LocalFarm
from fuzzy.levels import LEVELS
from planning.pipeline import render_job

REPO = Path(__file__).resolve().parent.parent
SCENES = {"caustic-corner": REPO / "scenes" / "caustic-corner.xml",
          "glass-corner": REPO / "scenes" / "glass-corner.xml", "cbox": REPO / "scenes" / "cbox.xml"}
HETEROGENEOUS = "caustic-corner"
DEFAULT_OUT = REPO / "docs" / "benchmarks"
VARIANT = "llvm_ad_rgb"
JOB_TIMEOUT_S = 900.0
S_TIME_RATIO, S_DIFF_PERCENT, RELMSE_RATIO = 0.75, 1.21, 0.67  # the targets
DIFF_WHITE = 0.10  # a display difference of 10 % is white in the grey difference images


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="folder for table, CSV, plot, images")
    parser.add_argument("--cache", type=Path, default=Path.home() / ".cache" / "quekaro",
                        help="where references are cached")
    parser.add_argument("--scenes", default=HETEROGENEOUS, help=f"comma list of {', '.join(SCENES)}")
    parser.add_argument("--agents", default="1,2", help="comma list of agent counts")
    parser.add_argument("--levels", default="off,VS,S,N,B,VB", help="comma list of optimisation levels")
    parser.add_argument("--res", type=int, default=320, help="image side (the default grid takes ~5 min here)")
    parser.add_argument("--spp", type=int, default=128, help="the user's spp (what level off renders)")
    parser.add_argument("--ref-spp", type=int, default=2048, help="spp of the reference")
    parser.add_argument("--threads", type=int, default=2, help="threads in all, shared by the agents")
    parser.add_argument("--units", type=int, default=None,
                        help="target unit count at the optimised levels (default: the planner's choice)")
    parser.add_argument("--runs", type=int, default=2,
                        help="timed runs per cell (median time; errors averaged over these and the warm-up, "
                             "and each uniform baseline over as many seeds)")
    parser.add_argument("--no-warmup", dest="warmup", action="store_false",
                        help="time each cell's first run (cold kernels) instead of a second, warm one")
    parser.add_argument("--inprocess", action="store_true",
                        help="render_job in this process instead of a farm (smallest agent count only)")


def _csv_list(text: str, what: str) -> list[str]:
    items = [t.strip() for t in text.split(",") if t.strip()]
    if not items:
        raise QuekaroError(f"--{what}: expected a comma-separated list, got {text!r}")
    return items


def parse_grid(args: argparse.Namespace) -> tuple[list[str], list[int], list[str]]:
    """The scene names, agent counts and levels asked for, checked."""

    scenes = _csv_list(args.scenes, "scenes")
    for s in scenes:
        if s not in SCENES:
            raise QuekaroError(f"--scenes: unknown scene {s!r} (known: {', '.join(SCENES)})")
    try:
        agents = sorted({int(a) for a in _csv_list(args.agents, "agents")})
    except ValueError:
        raise QuekaroError(f"--agents {args.agents!r}: expected integers like 1,2") from None
    if agents[0] < 1:
        raise QuekaroError(f"--agents {args.agents!r}: counts must be at least 1")
    levels = _csv_list(args.levels, "levels")
    for level in levels:
        if level not in LEVELS:
            raise QuekaroError(f"--levels: unknown level {level!r} (known: {', '.join(LEVELS)})")
    if args.runs < 1:
        raise QuekaroError(f"--runs {args.runs}: at least one timed run per cell")
    if args.inprocess:
        agents = agents[:1]
    return scenes, agents, levels


# ---- plain renders: reference, uniform baseline ------------------------------------------------------


def plain_render(spec: Any, spp: int, threads: int, seed: int = 0) -> tuple[np.ndarray, float]:
    """The whole image at `spp` with the scene's own integrator, in a child process; (pixels, seconds)."""
    w, h = _size(spec)
    with RenderWorker() as worker:
        tile = worker.render(RenderRequest(spec, VARIANT, None, None, spp, seed, w, h, Rect(0, 0, w, h),
                                     threads=threads))
    return tile.pixels, float(tile.meta["seconds"])


def _size(spec: Any) -> tuple[int, int]:
    return image_size(spec)


def reference(spec: Any, spp: int, threads: int, cache: Path) -> np.ndarray:
    """The scene at `spp`, no optimisation; cached under `cache` by scene file content, defines and spp."""
    key = hashlib.sha256(spec.path.read_bytes() + json.dumps([spec.defines, spp, VARIANT]).encode())
    path = cache / "references" / f"{spec.path.stem}-{key.hexdigest()[:16]}.exr"
    if path.exists():
        return read_exr(path)
    pixels, _ = plain_render(spec, spp, threads, seed=987654)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_exr(path, pixels)
    return pixels


#: The sample count's share of a render's time must exceed this (and MIN_SPP_SECONDS) before the line
#: t0 + k spp is trusted: below it, the two timings differ by noise and k could be ~0, which made the
#: uniform baseline ask Mitsuba for billions of samples on a 32 px image.
MIN_SPP_SHARE = 0.5
MIN_SPP_SECONDS = 0.02
MAX_TIMING_SPP = 1 << 14


def spp_timing(spec: Any, spp: int, threads: int) -> tuple[float, float]:
    """(t0, k) of t(spp) = t0 + k spp for a plain render, from the faster of two runs at two spp."""
    w, h = _size(spec)
    return fit_spp_line(lambda n: min(plain_render(spec, n, threads, seed=s)[1] for s in (1, 2)), spp,
                        what=f"{spec.path.name} at {w}x{h}")


def fit_spp_line(seconds_at: Callable[[int], float], spp: int, what: str = "the scene") -> tuple[float, float]:
    """(t0, k) through two timings, the higher spp raised 4x at a time until samples cost a measurable
    share of its time (MIN_SPP_SHARE of t0, at least MIN_SPP_SECONDS); QuekaroError past MAX_TIMING_SPP."""
    lo = max(1, spp // 4)
    t_lo = seconds_at(lo)
    hi = max(spp, lo + 1)
    while True:
        t_hi = seconds_at(hi)
        grown = t_hi - t_lo
        if grown >= max(MIN_SPP_SECONDS, MIN_SPP_SHARE * t_lo):
            k = grown / (hi - lo)
            return max(t_lo - k * lo, 0.0), k
        if hi * 4 > MAX_TIMING_SPP:
            raise QuekaroError(
                f"{what}: a render at {hi} spp took {t_hi:.3f} s against {t_lo:.3f} s at {lo} spp; the cost "
                f"of a sample is too small to time, so no uniform spp can be matched to a cell's time "
                f"(raise --res)")
        hi *= 4


# ---- CPU time --------------------------------------------------------------------------------------


def _proc_table() -> dict[int, tuple[int, float]]:
    """pid -> (parent pid, user + system CPU seconds) of every process readable in /proc."""
    tick = os.sysconf("SC_CLK_TCK")
    out = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            text = Path(f"/proc/{entry}/stat").read_text()
        except OSError:
            continue
        fields = text[text.rindex(")") + 2:].split()  # after the command name, which may hold spaces
        out[int(entry)] = (int(fields[1]), (int(fields[11]) + int(fields[12])) / tick)
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
def farm_runner(agents: int, threads: int, home: Path, units: int | None = None) -> Iterator[Any]:
    """A function (spec, level, spp, out) -> (report, wall s, CPU s) running jobs on a real local farm."""

    with LocalFarm(home, agents=agents, threads=max(1, threads // agents)) as farm:
        farm.wait_for_agents()
        client = farm.client()

        def run_job(spec: Any, level: str, spp: int, out: Path) -> tuple[dict, float, float]:
            bundle = make_bundle(spec.path, spec.defines, out.with_suffix(".tar")).path.read_bytes()
            roots = [p.pid for _, p in farm.procs]  # this process (and the XMPP server in it): _self_cpu
            cpu0, start = tree_cpu_seconds(roots) + _self_cpu(), time.perf_counter()
            options = {"level": level, "spp": spp} | ({"units": units} if units and level != "off" else {})
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
def inprocess_runner(threads: int, units: int | None = None) -> Iterator[Any]:
    """The same function as `farm_runner`, with `planning.pipeline.render_job` in this process."""

    def run_job(spec: Any, level: str, spp: int, out: Path) -> tuple[dict, float, float]:
        cpu0, start = _self_cpu(), time.perf_counter()
        chosen = units if units and level != "off" else None
        report = render_job(spec, RenderOptions(level=level, spp=spp, threads=threads, units=chosen), out)
        return report, time.perf_counter() - start, _self_cpu() - cpu0

    yield run_job


def spent(report: dict[str, Any]) -> dict[str, Any]:
    """How the rules spent samples: pixel-weighted mean spp, spp and depth ranges, unit count."""
    units = report["units"]
    area = np.array([u["rect"][2] * u["rect"][3] for u in units], dtype=float)
    spp = np.array([u["spp"] for u in units], dtype=float)
    depth = np.array([u["depth"] if u["depth"] is not None else -1 for u in units], dtype=float)
    return {
        "units": len(units), "spp_mean": float((spp * area).sum() / area.sum()),
        "spp_min": int(spp.min()), "spp_max": int(spp.max()), "depth_min": int(depth.min()),
        "depth_max": int(depth.max()), "render_seconds": float(report["totals"]["render_seconds"]),
        "prepass_seconds": float(report["totals"].get("prepass_seconds", 0.0)),
    }


def scene_cells(name: str, agents: list[int], levels: list[str], args: argparse.Namespace,
                work: Path) -> list[dict[str, Any]]:
    """Every (agents, level) cell of one scene, with errors and the uniform baseline."""

    spec = SceneSpec(SCENES[name], {"res": str(args.res)})
    ref = reference(spec, args.ref_spp, args.threads, Path(args.cache))
    t0, k = spp_timing(spec, args.spp, args.threads)
    cells, diffs = [], {}
    for n in agents:
        runner = (inprocess_runner(args.threads, args.units) if args.inprocess
                  else farm_runner(n, args.threads, work / f"farm-{name}-{n}", args.units))
        with runner as run_job:
            for level in levels:
                images = []
                if args.warmup:  # compiles this job's kernels (one per unit window size) before timing it
                    warm = work / f"{name}-{n}-{level}-warm.exr"
                    run_job(spec, level, args.spp, warm)
                    images.append(read_exr(warm))
                timed = []
                for r in range(args.runs):
                    out = work / f"{name}-{n}-{level}-{r}.exr"
                    timed.append(run_job(spec, level, args.spp, out))
                    images.append(read_exr(out))
                image = images[-1]
                used = [spent(report) for report, _, _ in timed]
                cell = {"scene": name, "agents": n, "level": level,
                        "seconds": float(np.median([wall for _, wall, _ in timed])),
                        "cpu_seconds": float(np.median([cpu for _, _, cpu in timed])),
                        "seconds_runs": [wall for _, wall, _ in timed],
                        **mean_metrics(images, ref), **used[-1],
                        "render_seconds": float(np.median([u["render_seconds"] for u in used]))}
                cells.append(cell)
                if n == agents[0]:
                    diffs[level] = diff_image(image, ref)
    uniform = uniform_baseline(spec, cells, agents[0], args, (t0, k), ref)
    for cell in cells:
        cell.update(uniform[cell["level"]])
    write_diff_images(name, diffs, Path(args.out))
    return cells


def mean_metrics(images: list[np.ndarray], ref: np.ndarray) -> dict[str, float]:
    """Every metric averaged over independent renders of one setting (one render's relMSE swings by tens
    of percent on a caustic, where a few pixels hold most of the error); `relmse_runs` lists them."""
    runs = [all_metrics(image, ref) for image in images]
    mean = {key: float(np.mean([r[key] for r in runs])) for key in runs[0]}
    return {**mean, "relmse_runs": [r["relmse"] for r in runs]}


def uniform_baseline(spec: Any, cells: list[dict[str, Any]], n: int, args: argparse.Namespace,
                     line: tuple[float, float], ref: np.ndarray) -> dict[str, dict[str, Any]]:
    """Per level: plain renders at the spp taking the wall time and the render time of its n-agent cell."""
    t0, k = line
    out = {}
    for cell in (c for c in cells if c["agents"] == n):
        entry = {"uniform_t0_s": t0, "uniform_s_per_spp": k}
        for prefix, seconds in (("uniform", cell["seconds"]), ("render_uniform", cell["render_seconds"])):
            spp = max(1, round((seconds - t0) / k))
            runs = args.runs + int(args.warmup)  # as many images as the cell's errors average
            renders = [plain_render(spec, spp, args.threads, seed=4242 + spp + 7919 * i) for i in range(runs)]
            secs = min(t for _, t in renders)
            metrics = mean_metrics([pixels for pixels, _ in renders], ref)
            entry.update({f"{prefix}_spp": spp, f"{prefix}_seconds": secs,
                          **{f"{prefix}_{m}": v for m, v in metrics.items()}})
        out[cell["level"]] = entry
    return out


# ---- outputs ---------------------------------------------------------------------------------------


def write_diff_images(name: str, diffs: dict[str, np.ndarray], out: Path) -> None:
    """Grey difference images against the reference, one per level (white = DIFF_WHITE or more)."""
    folder = out / "accuracy-diff"
    folder.mkdir(parents=True, exist_ok=True)
    for level, diff in diffs.items():
        mpimg.imsave(folder / f"{name}-{level}.png", np.clip(diff / DIFF_WHITE, 0, 1), cmap="gray", vmin=0, vmax=1)


def run(args: argparse.Namespace) -> dict[str, Any]:
    scenes, agents, levels = parse_grid(args)
    started = time.perf_counter()
    cells: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="quekaro-bench-") as tmp:
        for name in scenes:
            cells += scene_cells(name, agents, levels, args, Path(tmp))
    result = {
        "res": args.res, "spp": args.spp, "ref_spp": args.ref_spp, "threads": args.threads,
        "mode": "inprocess" if args.inprocess else "farm", "agents": agents, "levels": levels,
        "cells": cells, "targets": targets(cells, agents[0]), "seconds": time.perf_counter() - started,
    }
    result["outputs"] = [str(p) for p in write_outputs(result, Path(args.out))]
    if not args.json:
        print(format_report(result))
    return result


def targets(cells: list[dict[str, Any]], n: int) -> list[dict[str, Any]]:
    """The issue's targets on the heterogeneous scene (else the first scene), n-agent cells."""
    scene = HETEROGENEOUS if any(c["scene"] == HETEROGENEOUS for c in cells) else cells[0]["scene"]
    by_level = {c["level"]: c for c in cells if c["scene"] == scene and c["agents"] == n}
    out = []
    if "S" in by_level and "off" in by_level:
        ratio = by_level["S"]["seconds"] / by_level["off"]["seconds"]
        out.append({"name": f"{scene} level S time <= {S_TIME_RATIO} x off", "value": ratio,
                    "pass": ratio <= S_TIME_RATIO})
    if "S" in by_level:
        diff = by_level["S"]["mean_pixel_diff_percent"]
        out.append({"name": f"{scene} level S mean pixel diff <= {S_DIFF_PERCENT} %", "value": diff,
                    "pass": diff <= S_DIFF_PERCENT})
    for level, c in by_level.items():
        if level == "off":
            continue
        for prefix, what in (("uniform", "wall"), ("render_uniform", "render")):
            ratio = c["relmse"] / max(c[f"{prefix}_relmse"], 1e-30)
            out.append({"name": f"{scene} level {level} relMSE <= {RELMSE_RATIO} x uniform (equal {what} time)",
                        "value": ratio, "pass": ratio <= RELMSE_RATIO})
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
    for prefix, label in (("uniform", "uniform, equal wall time"), ("render_uniform", "uniform, equal render time")):
        parts = [f"{row[lv][prefix + '_spp']} spp, {row[lv][prefix + '_mean_pixel_diff_percent']:.2f} %, "
                 f"relMSE {row[lv][prefix + '_relmse']:.4f}" if lv in row else "" for lv in levels]
        lines.append(f"| {label} | " + " | ".join(parts) + " |")
    return lines


def spending_lines(cells: list[dict[str, Any]]) -> list[str]:
    lines = ["| scene | agents | level | s | CPU s | render s | pre-pass s | units | spp mean (min-max) "
             "| depth | diff % | RMSE | relMSE | FLIP |", "|" + "---|" * 14]
    for c in cells:
        lines.append(
            f"| {c['scene']} | {c['agents']} | {c['level']} | {c['seconds']:.1f} | {c['cpu_seconds']:.1f} "
            f"| {c['render_seconds']:.1f} | {c['prepass_seconds']:.2f} | {c['units']} "
            f"| {c['spp_mean']:.0f} ({c['spp_min']}-{c['spp_max']}) | {c['depth_min']}-{c['depth_max']} "
            f"| {c['mean_pixel_diff_percent']:.2f} | {c['rmse']:.4f} | {c['relmse']:.4f} | {c['flip']:.4f} |")
    return lines


def format_report(result: dict[str, Any]) -> str:
    lines = [f"mode {result['mode']}, {result['res']}x{result['res']}, user spp {result['spp']}, reference "
             f"{result['ref_spp']} spp, {result['threads']} threads; took {result['seconds']:.0f} s", ""]
    for scene in dict.fromkeys(c["scene"] for c in result["cells"]):
        lines += [f"## {scene}", "", *paper_table(result["cells"], scene, result["levels"]), ""]
    lines += [*spending_lines(result["cells"]), ""]
    for t in result["targets"]:
        lines.append(f"target: {t['name']}: {t['value']:.3f} {'PASS' if t['pass'] else 'MISS'}")
    return "\n".join(lines)


def write_outputs(result: dict[str, Any], out: Path) -> list[Path]:
    """accuracy.md, accuracy.csv and accuracy.png (error against time, fuzzy and uniform)."""
    out.mkdir(parents=True, exist_ok=True)
    md, csv_path, png = out / "accuracy.md", out / "accuracy.csv", out / "accuracy.png"
    md.write_text("# Accuracy against time (`quekaro bench accuracy`)\n\n" + format_report(result) + "\n")
    with csv_path.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(result["cells"][0]))
        writer.writeheader()
        writer.writerows(result["cells"])
    plot(result["cells"], png)
    return [md, csv_path, png]


def plot(cells: list[dict[str, Any]], path: Path) -> None:
    """relMSE against seconds, a Pareto view: fuzzy cells at their wall time (filled, per agent count) and
    at their render time (hollow, fewest agents), and every uniform-spp render at its render time."""
    fig = Figure(figsize=(6.4, 4.2), dpi=100)  # no pyplot: no GUI backend, no global figure state
    ax = fig.subplots()
    for i, (scene, n) in enumerate(dict.fromkeys((c["scene"], c["agents"]) for c in cells)):
        sel = sorted((c for c in cells if c["scene"] == scene and c["agents"] == n), key=lambda c: c["seconds"])
        ax.plot([c["seconds"] for c in sel], [c["relmse"] for c in sel], "o-", color=f"C{i}",
                label=f"fuzzy, {scene}, {n} agent(s), wall time")
        for c in sel:
            ax.annotate(c["level"], (c["seconds"], c["relmse"]), fontsize=7)
        if n != min(c["agents"] for c in cells if c["scene"] == scene):
            continue
        ax.plot([c["render_seconds"] for c in sel], [c["relmse"] for c in sel], "o", mfc="none", color=f"C{i}",
                label=f"fuzzy, {scene}, {n} agent(s), render time")
        uniform = sorted((c[f"{p}_seconds"], c[f"{p}_relmse"]) for c in sel for p in ("uniform", "render_uniform"))
        ax.plot(*zip(*uniform, strict=True), "s--", color="grey", alpha=0.7, label=f"uniform spp, {scene}")
    ax.set_xlabel("seconds")
    ax.set_ylabel("relative MSE against the reference")
    ax.set_yscale("log")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=6.5)
    fig.tight_layout()
    fig.savefig(path)
