"""The `quekaro` command line: one sub-command family per module `quekaro/cmd_*.py`.

Each `cmd_*` module exposes `register(subparsers)`, adding its sub-commands, each with a handler
`func(args) -> int` (the exit status). Families installed beside the product (the benchmarks, `bench.cli`)
register through the `quekaro.commands` entry point, so that nothing here imports them. A command names
its module in OWNERS, so that it imports that module only: `quekaro render` need not load the farm's XMPP
server, TLS and client (~0.25 s of every job's wall time); `--help` and unknown commands load them all.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from importlib.metadata import entry_points

from core import logs
from core.errors import QuekaroError
from core.render import spawn

# The module that registers each top-level command (tests/test_cli.py checks it against what they register),
# in the order `quekaro --help` lists them.
OWNERS = {"rules": "quekaro.cmd_rules", "render": "quekaro.cmd_render", "diff": "quekaro.cmd_diff",
          **dict.fromkeys(("up", "down", "demo", "master", "agent", "submit", "status", "watch", "result", "cancel",
                           "agents", "logs", "requeue"), "quekaro.cmd_farm"),
          "ca": "quekaro.cmd_ca"}
COMMAND_MODULES = tuple(dict.fromkeys(OWNERS.values()))
PLUGIN_GROUP = "quekaro.commands"


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser of every command, or of `command` alone when a built-in module owns it (OWNERS)."""
    parser = argparse.ArgumentParser(
        prog="quekaro",
        description="QUEKARO render farm: fuzzy-rule driven Mitsuba 3 rendering on agents over XMPP.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    owner = OWNERS.get(command or "")
    for name in (owner,) if owner else COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    if owner is None:
        for entry in entry_points(group=PLUGIN_GROUP):
            entry.load()(sub)
    return parser


def command_parser(parser: argparse.ArgumentParser, command: str) -> argparse.ArgumentParser:
    """The sub-command's own parser, whose errors print its usage (not `quekaro COMMAND ...`'s)."""
    for action in parser._subparsers._group_actions if parser._subparsers else ():
        if isinstance(action, argparse._SubParsersAction) and command in action.choices:
            return action.choices[command]
    return parser


def main(argv: list[str] | None = None) -> int:
    """The command line; Ctrl-C anywhere is exit status 130 without a traceback."""
    try:
        return _main(argv)
    except KeyboardInterrupt:
        return 130


def _main(argv: list[str] | None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["agent"]:
        # The render agent owns its options (python -m agents.render_agent takes the same ones). Lazy:
        # SPADE takes ~0.6 s to import, which every other command would pay.
        from agents.render_agent import main as agent_main

        return int(agent_main(argv[1:]) or 0)
    if argv[:1] == ["render"]:
        spawn.start_early()  # its Mitsuba import overlaps this process's imports (the job takes it)
    try:
        return _run(argv)
    finally:
        spawn.discard_early()


def _run(argv: list[str]) -> int:
    from fuzzy.errors import FuzzyInputError, RuleFileError  # after the early start: `fuzzy` loads numpy

    parser = build_parser(argv[0] if argv else None)
    args, extra = parser.parse_known_args(argv)
    if extra and not hasattr(args, "argv"):  # only pass-through commands (`bench`) take what is left
        command_parser(parser, args.command).error(f"unrecognized arguments: {' '.join(extra)}")
    if extra:
        args.argv = [*extra, *args.argv] if extra and extra[0].startswith("-") else [*args.argv, *extra]
    if getattr(args, "verbose", 0):
        logs.verbose(args.verbose)
    try:
        return int(args.func(args) or 0)
    except (QuekaroError, RuleFileError, FuzzyInputError) as exc:
        print(f"quekaro: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # `quekaro status | head -1`: the reader left; say nothing more (Python's recipe)
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1


if __name__ == "__main__":
    sys.exit(main())
