"""`quekaro bench ...`: registered through the `quekaro.commands` entry point (so the product never
imports the benchmarks), and light: the benchmarks themselves (`bench.commands`) load only when run."""

from __future__ import annotations

import argparse

from core.errors import QuekaroError


def register(sub: argparse._SubParsersAction) -> None:
    bench = sub.add_parser("bench", help="benchmarks that print figures (quekaro bench --help)", add_help=False)
    bench.add_argument("argv", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
    bench.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    try:
        # Lazy: the benchmarks import matplotlib and pyfuzzylite (~0.3 s), and pyfuzzylite sets up the
        # root logger when imported, which silenced the master's and agents' logs when every command paid it.
        from bench import commands
    except ModuleNotFoundError as exc:
        raise QuekaroError(f"'quekaro bench' needs the optional module {exc.name!r}: "
                           "pip install 'quekaro-farm[bench]'") from exc
    return commands.main(args.argv)
