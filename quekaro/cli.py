"""The `quekaro` command line: one sub-command family per module `quekaro/cmd_*.py`.

Each `cmd_*` module exposes `register(subparsers)`, adding its sub-commands, each with a handler
`func(args) -> int` (the exit status). Families installed beside the product (the benchmarks, `bench.cli`)
register through the `quekaro.commands` entry point, so that nothing here imports them.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from importlib.metadata import EntryPoint, entry_points

from core.errors import QuekaroError
from fuzzy.errors import FuzzyInputError, RuleFileError
from quekaro import cmd_diff, cmd_farm, cmd_render, cmd_rules

COMMAND_MODULES = (cmd_rules, cmd_render, cmd_diff, cmd_farm)
PLUGIN_GROUP = "quekaro.commands"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="quekaro",
        description="QUEKARO render farm: fuzzy-rule driven Mitsuba 3 rendering on agents over XMPP.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for module in COMMAND_MODULES:
        module.register(sub)
    for entry in entry_points(group=PLUGIN_GROUP):
        _register_plugin(sub, entry)
    return parser


def _register_plugin(sub: argparse._SubParsersAction, entry: EntryPoint) -> None:
    """A plugin's commands; one whose optional dependencies are missing answers with what to install."""
    try:
        register = entry.load()
    except ModuleNotFoundError as exc:
        parser = sub.add_parser(entry.name, help=f"(needs: pip install 'quekaro-farm[{entry.name}]')")
        parser.add_argument("rest", nargs=argparse.REMAINDER)
        parser.set_defaults(func=_missing(entry.name, exc.name or str(exc)))
        return
    register(sub)


def _missing(extra: str, module: str) -> Callable[[argparse.Namespace], int]:
    def refuse(args: argparse.Namespace) -> int:
        raise QuekaroError(f"'quekaro {extra}' needs the optional module {module!r}: "
                           f"pip install 'quekaro-farm[{extra}]'")

    return refuse


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["agent"]:
        # The render agent owns its options (python -m agents.render_agent takes the same ones). Lazy:
        # SPADE takes ~0.6 s to import, which every other command would pay.
        from agents.render_agent import main as agent_main

        return int(agent_main(argv[1:]) or 0)
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (QuekaroError, RuleFileError, FuzzyInputError) as exc:
        print(f"quekaro: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
