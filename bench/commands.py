"""The benchmarks' command line (`quekaro bench BENCHMARK ...`, via `bench.cli`): each benchmark module
exposes `add_arguments(parser)` (optional) and `run(args) -> dict`; this wires them to a parser, prints
the result (one JSON object with `--json`) and keeps the provenance of the report it wrote (the result's
`report`: the command, and the hash of the rule file that the module's `rules_file(args)` names)."""

from __future__ import annotations

import argparse
import json
import shlex
import time
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

from bench import (
    accuracy,
    adaptive,
    allocation,
    denoise,
    first_tile,
    fuzzy_engine,
    hosts,
    master_load,
    overhead,
    provenance,
    scaling,
    threshold,
)
from bench import farm as farm_bench

BENCHMARKS: dict[str, tuple[ModuleType, str]] = {
    "fuzzy": (fuzzy_engine, "fuzzy engine: evaluations/s against pyfuzzylite, centroid exactness"),
    "overhead": (overhead, "pipeline overhead against one plain Mitsuba render"),
    "farm": (farm_bench, "farm overhead and 2-agent speedup"),
    "accuracy": (accuracy, "time and error per (agents, optimisation level)"),
    "allocation": (allocation, "each level's render time and relMSE against uniform spp, predicted"),
    "adaptive": (adaptive, "the two-pass per-pixel adaptive render against uniform spp at equal render time"),
    "threshold": (threshold, "the progressive render to a noise goal against uniform spp reaching it in every unit"),
    "denoise": (denoise, "the denoiser's gain at the same spp, with the scene's filter and with a box one"),
    "scaling": (scaling, "simulated auction scaling to 64 agents"),
    "hosts": (hosts, "the real protocol (XMPP server, master, agent processes) at 8-64 emulated agents"),
    "master": (master_load, "the master's auction CPU and the job's efficiency at simulated farms of 64-1024 agents"),
    "first-tile": (first_tile, "a job's first award to its first tile on the page, whole units and passes"),
}


def main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    return args.func(args, argv)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="quekaro bench", description="benchmarks that print figures")
    bench_sub = parser.add_subparsers(dest="bench", metavar="BENCHMARK", required=True)
    for name, (module, help_text) in BENCHMARKS.items():
        one = bench_sub.add_parser(name, help=help_text)
        one.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
        one.set_defaults(func=_runner(module))
        if hasattr(module, "add_arguments"):
            module.add_arguments(one)
    return parser


def _runner(module: ModuleType) -> Callable[[argparse.Namespace, list[str]], int]:
    def run(args: argparse.Namespace, argv: list[str]) -> int:
        started = time.perf_counter()
        args.command_line = shlex.join(["quekaro", "bench", *provenance.reproducible(argv)])  # report titles
        result = module.run(args)
        if result.get("report"):
            rules = module.rules_file(args) if hasattr(module, "rules_file") else None
            provenance.record(Path(result["report"]), argv, rules, time.perf_counter() - started,
                              out_is_file=Path(args.out).suffix == ".md")
        if args.json:
            print(json.dumps(result, indent=2, sort_keys=True))
        return 0

    return run
