"""`quekaro bench master`: the master's auction on farms larger than one machine can host, simulated.

Weak scaling: each farm of N agents (mixed speeds, `bench.hosts.speeds_for`) gets a job of PER_AGENT_S seconds
of work per agent, in `farm_min_units(N)` units of log-normal costs, rendered whole and in passes
(`--progressive`), through the real `Auction` in `bench.simulate`. Each row prints the job's efficiency and the
auction's CPU per second of the job's makespan: the cores the master's decisions need. The issue's target at
1024 agents: efficiency >= 0.85 in passes, the master under one core. Where 1024 is not run, the cores are
projected from the largest runs (a power law), and the report says so.
"""

from __future__ import annotations

import argparse
import json
import math
import random
from pathlib import Path
from typing import Any

from bench.hosts import speeds_for
from bench.report import DEFAULT_OUT, command_of, write_report
from bench.simulate import simulate
from core.errors import QuekaroError
from planning.jobplan import farm_min_units

PER_AGENT_S = 150.0  # the 8-agent `bench hosts` job's share (1201 s over 8 agents)
COST_SIGMA = 0.5  # log-normal spread of the units' costs
LATENCY_S = 0.002
DELIVERY_S = 0.013  # a tile's upload, as `bench hosts` measured on Prosody
TARGET_AGENTS, TARGET_EFFICIENCY, TARGET_CORES = 1024, 0.85, 1.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--agents", default="64,128,256",
                        help="farm sizes, comma-separated (the auction's CPU grows faster than the farm: the "
                             "largest take minutes)")
    parser.add_argument("--per-agent-s", type=float, default=PER_AGENT_S, help="seconds of work per agent")
    parser.add_argument("--seed", type=int, default=1, help="the units' costs and the auction's tie-breaks")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT / "master.md", help="the report (.md; .json beside)")


def job_costs(n: int, per_agent_s: float, seed: int) -> list[float]:
    """farm_min_units(n) costs (seconds at speed 1) summing to n x per_agent_s."""
    rng = random.Random(seed)
    raw = [rng.lognormvariate(0.0, COST_SIGMA) for _ in range(farm_min_units(n))]
    total = n * per_agent_s
    return [total * r / sum(raw) for r in raw]


def run_row(n: int, per_agent_s: float, seed: int, passes: bool) -> dict[str, Any]:
    costs = job_costs(n, per_agent_s, seed)
    speeds = speeds_for(n)
    result = simulate(costs, speeds, latency=LATENCY_S, delivery=DELIVERY_S, seed=seed, passes=passes)
    return {"agents": n, "passes": passes, "units": len(costs), "messages": result.messages,
            "makespan_s": result.makespan, "efficiency": sum(costs) / (sum(speeds) * result.makespan),
            "master_cpu_s": result.master_cpu_s, "master_cores": result.master_cpu_s / result.makespan}


def project_cores(rows: list[dict[str, Any]], agents: int) -> float | None:
    """The master's cores at `agents`, from the power law through the two largest runs in passes."""
    runs = sorted((r["agents"], r["master_cores"]) for r in rows if r["passes"] and r["master_cores"] > 0)
    if len(runs) < 2:
        return None
    (n0, c0), (n1, c1) = runs[-2], runs[-1]
    slope = math.log(c1 / c0) / math.log(n1 / n0)
    return c1 * (agents / n1) ** slope


def format_report(result: dict[str, Any]) -> str:
    lines = [f"job: {result['per_agent_s']:.0f} s of work per agent, farm_min_units(N) units (log-normal costs, "
             f"sigma {COST_SIGMA}), mixed speeds {result['speeds']}, latency {LATENCY_S * 1e3:.0f} ms, tile "
             f"delivery {DELIVERY_S * 1e3:.0f} ms; the real Auction, its CPU measured in this process",
             "", "| agents | units | rendered | messages | makespan s | efficiency | master CPU s | master cores |",
             "|---|---|---|---|---|---|---|---|"]
    for r in result["rows"]:
        lines.append(f"| {r['agents']} | {r['units']} | {'in passes' if r['passes'] else 'whole'} | "
                     f"{r['messages']} | {r['makespan_s']:.1f} | {r['efficiency']:.3f} | {r['master_cpu_s']:.1f} "
                     f"| {r['master_cores']:.3f} |")
    lines += ["", _target_line(result)]
    return "\n".join(lines)


def _target_line(result: dict[str, Any]) -> str:
    row = next((r for r in result["rows"] if r["agents"] == TARGET_AGENTS and r["passes"]), None)
    if row is not None:
        met = row["efficiency"] >= TARGET_EFFICIENCY and row["master_cores"] < TARGET_CORES
        return (f"target at {TARGET_AGENTS} agents in passes: efficiency >= {TARGET_EFFICIENCY}, master < "
                f"{TARGET_CORES:.0f} core: {row['efficiency']:.3f}, {row['master_cores']:.2f} cores "
                f"{'PASS' if met else 'MISS'}")
    cores = result["projected_cores"]
    if cores is None:
        return f"target at {TARGET_AGENTS} agents: not run, and too few runs in passes to project"
    verdict = "MISS (projected)" if cores >= TARGET_CORES else "projected under one core, not run"
    return (f"target at {TARGET_AGENTS} agents in passes: master < {TARGET_CORES:.0f} core: not run; the two "
            f"largest runs' power law projects {cores:.1f} cores: {verdict}")


def run(args: argparse.Namespace) -> dict[str, Any]:
    counts = [int(c) for c in str(args.agents).split(",") if c.strip()]
    if not counts or min(counts) < 1:
        raise QuekaroError(f"--agents {args.agents!r}: farm sizes of at least one agent")
    rows = [run_row(n, args.per_agent_s, args.seed, passes) for n in counts for passes in (False, True)]
    result = {"per_agent_s": args.per_agent_s, "seed": args.seed, "speeds": list(speeds_for(4)), "rows": rows}
    result["projected_cores"] = project_cores(rows, TARGET_AGENTS)
    text = format_report(result)
    out = Path(args.out)
    report = write_report(out.parent, out.stem, "The master's auction at simulated farm sizes", text,
                          command_of(args, "quekaro bench master"))
    out.with_suffix(".json").write_text(json.dumps(result, indent=1))
    result["report"] = str(report)
    if not args.json:
        print(text)
    return result
