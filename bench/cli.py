"""`quekaro bench ...`: benchmarks that print figures (and JSON with `--json`).

The benchmarks sit above the product (they drive it from outside) and have their own optional
dependencies (`pip install 'quekaro-farm[bench]'`). The command line finds this module through the
`quekaro.commands` entry point, so the product never imports it. Each benchmark module exposes
`add_arguments(parser)` (optional) and `run(args) -> dict`; this module wires them to the command line.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from types import ModuleType

from bench import accuracy, allocation, fuzzy_engine, overhead, scaling
from bench import farm as farm_bench

BENCHMARKS: dict[str, tuple[ModuleType, str]] = {
    "fuzzy": (fuzzy_engine, "fuzzy engine: evaluations/s against pyfuzzylite, centroid exactness"),
    "overhead": (overhead, "pipeline overhead against one plain Mitsuba render"),
    "farm": (farm_bench, "farm overhead and 2-agent speedup"),
    "accuracy": (accuracy, "time and error per (agents, optimisation level)"),
    "allocation": (allocation, "each level's render time and relMSE against uniform spp, predicted"),
    "scaling": (scaling, "simulated auction scaling to 64 agents"),
}


def register(sub: argparse._SubParsersAction) -> None:
    bench = sub.add_parser("bench", help="benchmarks that print figures")
    bench_sub = bench.add_subparsers(dest="bench", metavar="BENCHMARK", required=True)
    for name, (module, help_text) in BENCHMARKS.items():
        parser = bench_sub.add_parser(name, help=help_text)
        parser.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
        parser.set_defaults(func=_runner(module))
        if hasattr(module, "add_arguments"):
            module.add_arguments(parser)


def _runner(module: ModuleType) -> Callable[[argparse.Namespace], int]:
    def run(args: argparse.Namespace) -> int:
        result = module.run(args)
        if args.json:
            print(json.dumps(result, indent=2, sort_keys=True))
        return 0

    return run
