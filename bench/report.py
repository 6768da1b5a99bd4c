"""Where the benchmarks' figures go: `<out>/<name>.md` beside their CSVs and plots (docs/benchmarks by
default), the text a benchmark printed kept verbatim, so README.md can include it (bench.docs)."""

from __future__ import annotations

import argparse
from pathlib import Path

DEFAULT_OUT = Path(__file__).resolve().parent.parent / "docs" / "benchmarks"


def command_of(args: argparse.Namespace, default: str) -> str:
    """The command a report's title names: the one run (`bench.commands` keeps it as `args.command_line`,
    less --out), else `default` (a benchmark's run called from Python)."""
    return getattr(args, "command_line", None) or default


def write_report(out: Path, name: str, title: str, body: str, command: str, fenced: bool = True) -> Path:
    """`out`/`name`.md: a title naming the command that wrote it, then `body` (as printed, in a block, or
    as markdown when not `fenced`: tables then render in README)."""
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{name}.md"
    text = f"```\n{body.rstrip()}\n```" if fenced else body
    path.write_text(f"# {title} (`{command}`)\n\n{text}\n")
    return path


def publish_markdown(out: Path, name: str, title: str, command: str, body: str, show: bool) -> Path:
    """`write_report` of a markdown `body`, also printed when `show`."""
    if show:
        print(body)
    return write_report(out, name, title, body, command, fenced=False)
