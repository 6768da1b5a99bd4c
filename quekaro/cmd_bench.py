"""`quekaro bench ...`: benchmark scripts that print figures (and JSON with `--json`).

Each benchmark lives beside the code it measures and exposes `add_arguments(parser)` (optional) and
`run(args) -> dict`; this module only wires them to the command line and prints the result.
"""

from __future__ import annotations

import argparse
import importlib
import json

BENCHMARKS = {
    "fuzzy": ("bench.fuzzy_engine", "fuzzy engine: evaluations/s against pyfuzzylite, centroid exactness"),
    "overhead": ("bench.overhead", "pipeline overhead against one plain Mitsuba render"),
    "farm": ("bench.farm", "farm overhead and 2-agent speedup"),
    "accuracy": ("bench.accuracy", "time and error per (agents, optimisation level)"),
    "allocation": ("bench.allocation", "each level's render time and relMSE against uniform spp, predicted"),
    "scaling": ("bench.scaling", "simulated auction scaling to 64 agents"),
}


def register(sub: argparse._SubParsersAction) -> None:
    bench = sub.add_parser("bench", help="benchmarks that print figures")
    bench_sub = bench.add_subparsers(dest="bench", metavar="BENCHMARK", required=True)
    for name, (module_name, help_text) in BENCHMARKS.items():
        parser = bench_sub.add_parser(name, help=help_text)
        parser.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
        parser.set_defaults(func=_runner(module_name))
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            if exc.name != module_name:
                raise
            continue
        if hasattr(module, "add_arguments"):
            module.add_arguments(parser)


def _runner(module_name: str):
    def run(args: argparse.Namespace) -> int:
        module = importlib.import_module(module_name)
        result = module.run(args)
        if args.json:
            print(json.dumps(result, indent=2, sort_keys=True))
        return 0

    return run
