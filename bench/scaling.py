"""`quekaro bench scaling`: how the auction scales to 64 agents, by simulation from measured unit costs.

`measure_cached` times every cell of a grid for real once (cached) and spreads the times into a per-pixel
`TimeMap`; `simulate_row` runs N = 1, 2, 4, ... agents through `bench.simulate.simulate` (the master's real
`Auction` under a simulated clock) on the fuzzy partition, one tile per agent, and auctioned equal tiles.
Efficiency is T1 / (sum of speeds x TN).
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from bench.images import write_plot
from bench.simulate import simulate
from core.errors import QuekaroError
from core.model import integrators
from core.model.geometry import Rect
from core.model.job import SceneSpec
from core.render.process import RenderProcess, RenderRequest
from core.scene import scene as scene_mod
from core.scene.scene import expand, film_info
from planning.accuracy import content_key, job_variant
from planning.accuracy import default_cache as default_cache_dir
from planning.complexity import COST_SPP, NOISE_SHARE, PREPASS_SPP, ComplexityMap, prepass
from planning.jobplan import farm_min_units
from planning.partition import equal_tiles, partition

REPO = Path(__file__).resolve().parent.parent
DEFAULT_SCENE = REPO / "scenes" / "caustic-corner.xml"
DEFAULT_OUT = REPO / "docs" / "benchmarks"
MIXED_SPEEDS = (1.0, 0.5, 1.5, 2.0)  # cycled: agent i has speed MIXED_SPEEDS[i % 4]
BAND = 2  # every unit renders this many extra pixels on each side (the gaussian filter's reach)
TARGETS = {8: 0.9, 32: 0.8}
# A unit's delivery on this machine: the agent log's "in all" minus "render", 22-30 ms a unit
# (caustic-corner 320x320, level S, one agent).
DELIVERY_S = 0.025
# Runs per cell of the time map (fastest kept). With two runs back to back, three measurements of the
# same scene on this shared machine gave 0.67-0.82 efficiency at N=32: one cell timed during a busy
# spell makes its units look long, and the simulated tail with them.
MEASURE_PASSES = 3


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", type=Path, default=DEFAULT_SCENE)
    parser.add_argument("--res", type=int, default=512, help="image side of the simulated job")
    parser.add_argument("--spp", type=int, default=1024, help="spp of the simulated job")
    parser.add_argument("--agents-max", type=int, default=64)
    parser.add_argument("--units", type=int, default=16, help="least target unit count of the partition")
    parser.add_argument("--units-per-agent", type=int,
                        help="the partition targets at least this many units per agent (default: as the "
                             "farm's master, planning.jobplan.farm_min_units)")
    parser.add_argument("--repeats", type=int, default=3, help="simulations (seeds) averaged per cell")
    parser.add_argument("--cell", type=int, default=32, help="side of the grid cells timed for real")
    parser.add_argument("--measure-spp", type=int, default=64, help="spp of the real cell renders")
    # 2 ms one way: docs/design.md section 4 measured a 1.8 ms round trip through SPADE's server (pessimistic).
    parser.add_argument("--latency", type=float, default=0.002, help="one-way message latency, seconds")
    parser.add_argument("--delivery", type=float, default=DELIVERY_S,
                        help="seconds from a unit's render end to its inform (tile written, hashed, uploaded)")
    parser.add_argument("--jitter", type=float, default=0.05,
                        help="render times vary uniformly by +- this fraction around the estimate")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="folder for the table and plot")
    parser.add_argument("--remeasure", action="store_true",
                        help="render the cells again instead of reading the cached measurement")
    parser.add_argument("--cache-dir", type=Path, default=None,
                        help="where measurements are cached (default $XDG_CACHE_HOME/quekaro or ~/.cache/quekaro)")


@dataclass
class TimeMap:
    """Seconds per sample of every pixel on a speed-1 agent, and the fixed seconds of one unit render."""

    per_sample: np.ndarray  # (H, W)
    fixed_s: float
    info: dict[str, Any]

    def unit_seconds(self, rect: Rect, spp: int, band: int = BAND) -> float:
        """fixed_s + spp x the time map summed over the unit's window, on an agent of speed 1. Render time
        is linear in spp (docs/design.md section 3), so the job's spp need not be rendered to measure it."""
        h, w = self.per_sample.shape
        window = rect.window(band, w, h)
        return self.fixed_s + spp * float(self.per_sample[window.slices()].sum())


def scene_integrator(node: Any) -> tuple[str, int]:
    """The type and max_depth of the scene's top-level `<integrator>` element as its XML states them (path,
    8 if unstated)."""
    kind = node.get("type", "path") if node is not None else "path"
    depth = 8
    for child in node if node is not None else ():
        if child.tag == "integer" and child.get("name") == "max_depth":
            depth = int(child.get("value", depth))
    return kind, depth


def measure(spec: SceneSpec, cell: int, spp: int, threads: int) -> tuple[TimeMap, Any]:
    """The pre-pass complexity map and the measured per-pixel time map of the scene at its film's size:
    every `cell` px cell rendered at `spp` in a RenderProcess (the fastest of MEASURE_PASSES runs), and the
    fixed cost of one render call (a cell at 1 spp)."""
    info = film_info(spec)
    width, height = info.width, info.height
    variant = job_variant(spec)  # a job of this scene renders in it (spectral data: the spectral variant)
    elem = integrators.scene_element(expand(spec).root)
    kind, depth = scene_integrator(elem)
    loaded = scene_mod.load(spec, variant, threads)
    # A wrapper (aov, moment) is no radiance integrator of its own: the pre-pass estimates with the one it
    # wraps, as a job's does (core.model.integrators.radiance_xml), and the cells render the scene's own.
    wraps = elem is not None and integrators.kind(kind).nests
    estimate = integrators.radiance_xml(elem, depth) if wraps else kind
    cmap = prepass(loaded, width, height, integrator=estimate, max_depth=depth, threads=threads)
    if wraps:
        kind, depth = None, None
    cells = [Rect(x, y, min(cell, width - x), min(cell, height - y))
             for y in range(0, height, cell) for x in range(0, width, cell)]

    def job(rect: Rect, n: int, seed: int) -> RenderRequest:
        # Cells are timed without a band: the map holds what each pixel costs; units pay their band.
        return RenderRequest(spec, variant, kind, depth, n, seed, width, height, rect, band=0,
                             threads=threads)

    started = time.perf_counter()
    with RenderProcess() as worker:
        for rect in cells[:2]:  # compile the kernels of both spp before timing anything
            worker.render(job(rect, 1, 0))
            worker.render(job(rect, spp, 0))
        probe = cells[:: max(1, len(cells) // 8)]
        fixed = float(np.median([min(worker.render(job(r, 1, s)).meta["seconds"] for s in (1, 2))
                                 for r in probe]))
        # The fastest of MEASURE_PASSES runs, each pass over every cell in turn: the machine is shared, a
        # slow run measures the neighbours, and a busy spell would hit back-to-back runs of one cell alike.
        passes = [[worker.render(job(r, spp, MEASURE_PASSES * i + j + 1)).meta["seconds"]
                   for i, r in enumerate(cells)] for j in range(MEASURE_PASSES)]
        seconds = [min(runs) for runs in zip(*passes, strict=True)]
        # Twice, the faster kept: the first compiles the whole image's kernel (~2 s on caustic-corner 500x300).
        whole = min(worker.render(job(Rect(0, 0, width, height), spp, s)).meta["seconds"] for s in (0, 1))
    per_sample = spread_cell_times(cells, seconds, fixed, spp, cmap.cost)
    cell_cost = [float(cmap.cost[r.slices()].sum()) for r in cells]
    tmap = TimeMap(per_sample, fixed, {
        "cells": len(cells), "cell": cell, "measure_spp": spp, "fixed_s": fixed, "variant": variant,
        "measure_seconds": time.perf_counter() - started, "prepass_seconds": cmap.seconds,
        "cell_seconds_min": min(seconds), "cell_seconds_max": max(seconds),
        "cost_time_rank_corr": _rank_corr(cell_cost, seconds),
        "whole_image_measured_s": whole,
        "whole_image_predicted_s": tmap_whole(per_sample, fixed, spp),
    })
    return tmap, cmap


def suite_spec(entry: Any, res: int) -> SceneSpec:
    """A suite scene (bench.suite.SuiteScene) at `res` wide, as the suite's benchmarks measure it."""
    defines = entry.with_size(res)
    return measured_spec(entry.path.resolve(), res, defines=defines if "width" in defines else None)


def measured_spec(scene_path: Path, res: int, height: int | None = None,
                  defines: dict[str, str] | None = None) -> SceneSpec:
    """The scene as measured: its `defines` when given (the size is then the film's), else `-D res`, and
    `-D height` when it differs (as bench.hosts's wide scene reads), where the scene has a `res` parameter;
    a scene without one renders at its film's own size (Mitsuba refuses a -D it does not use)."""
    if defines is not None:
        return SceneSpec(scene_path, dict(defines))
    if "res" not in expand(SceneSpec(scene_path)).params:
        return SceneSpec(scene_path, {})
    height = height or res
    return SceneSpec(scene_path, {"res": str(res)} if height == res else {"res": str(res), "height": str(height)})


def spread_cell_times(cells: Sequence[Rect], seconds: Sequence[float], fixed: float, spp: int,
                      cost: np.ndarray) -> np.ndarray:
    """Seconds per sample of every pixel: each cell's time above the fixed cost of a render call, over its
    spp, spread over the cell's pixels in proportion to their pre-pass cost. Refuses a map with no time at
    all (every cell as fast as a 1-spp render): nothing would be measured, and each sample would look free."""
    per_sample = np.zeros(cost.shape)
    for rect, sec in zip(cells, seconds, strict=True):
        c = cost[rect.slices()]
        share = c / c.sum() if c.sum() > 0 else np.full(c.shape, 1 / c.size)
        per_sample[rect.slices()] = max(sec - fixed, 0.0) / spp * share
    if not per_sample.sum() > 0:
        raise QuekaroError(f"no cell at {spp} spp took longer than a 1-spp render ({fixed * 1000:.1f} ms): "
                           "the cost of a sample cannot be measured; raise --measure-spp or --cell")
    return per_sample




def cache_file(cache_dir: Path | None, spec: SceneSpec, cell: int, spp: int, threads: int, variant: str) -> Path:
    """Where the measurement of these inputs is cached: keyed by the content of every file the scene reads
    and its -D parameters (hence its size; planning.accuracy.content_key), the cell side, spp, threads, the
    pre-pass's sample split (the cached complexity map, hence the partition, depends on it), the timing
    passes per cell and the variant the cells rendered in."""
    digest = content_key(spec)
    prepass = f"p{PREPASS_SPP}-{COST_SPP}-{NOISE_SHARE}"
    return (Path(cache_dir or default_cache_dir())
            / f"scaling-{digest}-c{cell}-s{spp}-t{threads}-{prepass}-m{MEASURE_PASSES}-{variant}.npz")


def measure_cached(scene_path: Path, res: int, cell: int, spp: int, threads: int,
                   cache_dir: Path | None = None, remeasure: bool = False,
                   height: int | None = None, defines: dict[str, str] | None = None) -> tuple[TimeMap, Any, bool]:
    """`measure` of the scene at `measured_spec(scene_path, res, height, defines)`, read from the cache when
    it holds these inputs (and `remeasure` is false); the third value says whether it came from the
    cache. A cache file that cannot be read is measured again. A measurement takes ~60 s."""
    spec = measured_spec(scene_path, res, height, defines)
    variant = job_variant(spec)
    path = cache_file(cache_dir, spec, cell, spp, threads, variant)
    if path.exists() and not remeasure:
        try:
            with np.load(path, allow_pickle=False) as data:
                mean = data["mean"] if data["has_mean"] else None
                cmap = ComplexityMap(data["cost"], data["noise"], float(data["prepass_seconds"]),
                                     json.loads(str(data["cmap_info"])), mean)
                tmap = TimeMap(data["per_sample"], float(data["fixed_s"]), json.loads(str(data["tmap_info"])))
            return tmap, cmap, True
        except (OSError, KeyError, ValueError) as exc:
            print(f"cache {path} unreadable ({exc}); measuring again", file=sys.stderr)
    tmap, cmap = measure(spec, cell, spp, threads)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.stem + ".tmp.npz")
    np.savez(tmp, per_sample=tmap.per_sample, fixed_s=tmap.fixed_s, tmap_info=json.dumps(tmap.info),
             cost=cmap.cost, noise=cmap.noise, has_mean=cmap.mean is not None,
             mean=cmap.mean if cmap.mean is not None else np.zeros(0), prepass_seconds=cmap.seconds,
             cmap_info=json.dumps(cmap.info, default=str))
    tmp.replace(path)  # atomic: a run stopped halfway leaves no half-written cache
    return tmap, cmap, False


def tmap_whole(per_sample: np.ndarray, fixed: float, spp: int) -> float:
    return fixed + spp * float(per_sample.sum())


def _rank_corr(a: Sequence[float], b: Sequence[float]) -> float:
    ra, rb = np.argsort(np.argsort(a)), np.argsort(np.argsort(b))
    if np.std(ra) == 0 or np.std(rb) == 0:
        return 0.0
    return float(np.corrcoef(ra, rb)[0, 1])


def speeds_for(n: int, mixed: bool) -> list[float]:
    return [MIXED_SPEEDS[i % len(MIXED_SPEEDS)] if mixed else 1.0 for i in range(n)]


def agent_counts(agents_max: int) -> list[int]:
    counts, n = [], 1
    while n <= agents_max:
        counts.append(n)
        n *= 2
    return counts


def simulate_row(tmap: TimeMap, cmap: Any, n: int, mixed: bool, args: argparse.Namespace,
                 t1: float) -> dict[str, Any]:
    """Makespan and efficiency of three splits on n agents: the fuzzy partition of the pre-pass, with
    max(--units, farm_min_units(n)) target units as the master gives; naive, one equal tile per agent; and
    equal tiles, as many as the partition's units, through the same auction. `auction_efficiency` divides by
    the same units' time on one agent: the auction's loss alone, without the cost of splitting the image."""
    res = tmap.per_sample.shape[0]
    speeds = speeds_for(n, mixed)
    per_agent = farm_min_units(n) if args.units_per_agent is None else args.units_per_agent * n
    target = max(args.units, per_agent)
    units = [u.rect for u in partition(cmap, target_units=target)]
    naive = equal_tiles(res, res, n)
    equal = equal_tiles(res, res, len(units))

    def run(rects: list[Rect], on: list[float]) -> float:
        costs = [tmap.unit_seconds(r, args.spp) for r in rects]
        # Mean over a few seeds: the jitter makes one run's tail a matter of luck.
        runs = [simulate(costs, on, latency=args.latency, seed=s, jitter=args.jitter,
                         delivery=args.delivery)
                for s in range(args.repeats)]
        return float(np.mean([r.makespan for r in runs]))

    fuzzy_t, naive_t, equal_t = run(units, speeds), run(naive, speeds), run(equal, speeds)
    one_agent = run(units, [1.0])
    capacity = sum(speeds)
    return {
        "agents": n, "speeds": "mixed" if mixed else "equal", "capacity": capacity, "units": len(units),
        "target_units": target, "makespan_s": fuzzy_t, "efficiency": t1 / (capacity * fuzzy_t),
        "auction_efficiency": one_agent / (capacity * fuzzy_t),
        "naive_tiles": len(naive), "naive_makespan_s": naive_t, "naive_efficiency": t1 / (capacity * naive_t),
        "equal_units": len(equal), "equal_makespan_s": equal_t,
        "equal_efficiency": t1 / (capacity * equal_t),
    }


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Measure, then simulate every agent count at equal and at mixed speeds. T1 is the whole image
    rendered as one unit by one agent of speed 1: the stricter baseline (no units, so no bands twice)."""
    tmap, cmap, cached = measure_cached(args.scene, args.res, args.cell, args.measure_spp, args.threads,
                                        args.cache_dir, args.remeasure)
    whole = Rect(0, 0, args.res, args.res)
    t1 = simulate([tmap.unit_seconds(whole, args.spp, band=0)], [1.0], latency=args.latency,
                  delivery=args.delivery).makespan
    rows = [simulate_row(tmap, cmap, n, mixed, args, t1)
            for mixed in (False, True) for n in agent_counts(args.agents_max)]
    result = {
        "scene": str(args.scene), "res": args.res, "spp": args.spp, "latency_s": args.latency,
        "delivery_s": args.delivery,
        "jitter": args.jitter, "t1_s": t1, "mixed_speeds": list(MIXED_SPEEDS), "measured": tmap.info,
        "measurement_cached": cached,
        "rows": rows, "targets": _targets(rows),
    }
    paths = write_outputs(result, Path(args.out))
    result["outputs"] = [str(p) for p in paths]
    result["report"] = result["outputs"][0]  # scaling.md
    if not args.json:
        print(format_report(result))
    return result


def _targets(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    out = []
    for speeds in ("equal", "mixed"):
        for n, goal in TARGETS.items():
            row = next((r for r in rows if r["agents"] == n and r["speeds"] == speeds), None)
            if row is not None:
                out.append({"agents": n, "speeds": speeds, "target": goal, "efficiency": row["efficiency"],
                            "pass": row["efficiency"] >= goal})
    return out


def table_lines(rows: list[dict[str, Any]]) -> list[str]:
    head = ("| speeds | agents | units | makespan s | efficiency | auction eff. | naive (1 tile/agent) s | naive eff. "
            "| equal tiles auctioned s | equal eff. |")
    lines = [head, "|" + "---|" * 10]
    for r in rows:
        lines.append(
            f"| {r['speeds']} | {r['agents']} | {r['units']} | {r['makespan_s']:.2f} | {r['efficiency']:.3f} "
            f"| {r['auction_efficiency']:.3f} | {r['naive_makespan_s']:.2f} | {r['naive_efficiency']:.3f} "
            f"| {r['equal_makespan_s']:.2f} | {r['equal_efficiency']:.3f} |")
    return lines


def format_report(result: dict[str, Any]) -> str:
    m = result["measured"]
    lines = [
        f"scene {result['scene']} at {result['res']}x{result['res']}, job spp {result['spp']}; "
        f"T1 (one agent, one unit) {result['t1_s']:.1f} s",
        f"measured: {m['cells']} cells of {m['cell']} px at {m['measure_spp']} spp in {m['measure_seconds']:.1f} s "
        f"(cell {m['cell_seconds_min']:.3f}-{m['cell_seconds_max']:.3f} s, fixed per unit {m['fixed_s']:.4f} s, "
        f"rank corr. pre-pass cost vs time {m['cost_time_rank_corr']:.2f}); whole image "
        f"{m['whole_image_measured_s']:.2f} s measured vs {m['whole_image_predicted_s']:.2f} s predicted",
        f"latency {result['latency_s'] * 1000:.1f} ms one way, tile delivery {result['delivery_s'] * 1000:.0f} ms, "
        f"jitter +-{result['jitter'] * 100:.0f} %, "
        f"mixed speeds cycle {result['mixed_speeds']} (efficiency uses their sum); the job is submitted once "
        f"the agents have registered; measurement {'from the cache' if result.get('measurement_cached') else 'new'}",
        "", *table_lines(result["rows"]), "",
    ]
    for t in result["targets"]:
        verdict = "PASS" if t["pass"] else "MISS"
        lines.append(f"target: efficiency >= {t['target']} at N={t['agents']} ({t['speeds']} speeds): "
                     f"{t['efficiency']:.3f} {verdict}")
    lines.append("outputs: " + ", ".join(result.get("outputs", [])))
    return "\n".join(lines)


def write_outputs(result: dict[str, Any], out: Path) -> list[Path]:
    """scaling.md (table), scaling.csv (rows) and scaling.png (efficiency against agents)."""
    out.mkdir(parents=True, exist_ok=True)
    md, csv_path, png = out / "scaling.md", out / "scaling.csv", out / "scaling.png"
    md.write_text("\n".join(["# Simulated scaling (`quekaro bench scaling`)", "",
                             format_report({**result, "outputs": []}).rsplit("\noutputs:", 1)[0], ""]))
    rows = result["rows"]
    with csv_path.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    plot(rows, png)
    return [md, csv_path, png]


def plot(rows: list[dict[str, Any]], path: Path) -> None:
    # A Figure of its own (no pyplot): no backend to select, no global figure state to close.
    fig = Figure(figsize=(6, 3.6), dpi=100)
    ax = fig.subplots()
    styles = {"equal": "-", "mixed": "--"}
    for speeds, style in styles.items():
        sel = [r for r in rows if r["speeds"] == speeds]
        n = [r["agents"] for r in sel]
        ax.plot(n, [r["efficiency"] for r in sel], "o" + style, color="C0", label=f"fuzzy partition, {speeds}")
        ax.plot(n, [r["equal_efficiency"] for r in sel], "s" + style, color="C2",
                label=f"equal tiles auctioned, {speeds}")
        ax.plot(n, [r["naive_efficiency"] for r in sel], "x" + style, color="C3",
                label=f"1 tile per agent, {speeds}")
    ax.set_xscale("log", base=2)
    ax.set_ylim(0, 1.05)
    ax.set_xlabel("agents")
    ax.set_ylabel("efficiency T1 / (capacity x TN)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=6.5, loc="lower left")
    fig.tight_layout()
    write_plot(path, fig)
