"""Where the benchmarks' figures go: `<out>/<name>.md` beside their CSVs and plots (docs/benchmarks by
default), the text a benchmark printed kept verbatim, so README.md can include it (bench.docs)."""

from __future__ import annotations

from pathlib import Path

DEFAULT_OUT = Path(__file__).resolve().parent.parent / "docs" / "benchmarks"


def write_report(out: Path, name: str, title: str, body: str, command: str) -> Path:
    """`out`/`name`.md: a title naming the command that wrote it, then `body` (as printed, in a block)."""
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{name}.md"
    path.write_text(f"# {title} (`{command}`)\n\n```\n{body.rstrip()}\n```\n")
    return path


def publish_markdown(out: Path, name: str, title: str, command: str, body: str, show: bool) -> Path:
    """`out`/`name`.md: the title naming the command, then `body` as markdown (tables render in README);
    `body` is also printed when `show`."""
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{name}.md"
    path.write_text(f"# {title} (`{command}`)\n\n{body}\n")
    if show:
        print(body)
    return path
