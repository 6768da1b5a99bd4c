"""The `quekaro` command line: one sub-command family per module `quekaro/cmd_*.py`.

Each `cmd_*` module exposes `register(subparsers)`, adding its sub-commands, each with a handler
`func(args) -> int` (the exit status). Heavy imports (Mitsuba, SPADE) happen inside handlers so that
`quekaro --help` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from core.errors import QuekaroError
from fuzzy.errors import FuzzyInputError, RuleFileError

COMMAND_MODULES = (
    "quekaro.cmd_rules",
    "quekaro.cmd_render",
    "quekaro.cmd_diff",
    "quekaro.cmd_farm",
    "quekaro.cmd_bench",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="quekaro",
        description="QUEKARO render farm: fuzzy-rule driven Mitsuba 3 rendering on agents over XMPP.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name == name:
                continue  # that command family is not built yet
            raise
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["agent"]:
        # The render agent owns its options (python -m agents.render_agent takes the same ones).
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
