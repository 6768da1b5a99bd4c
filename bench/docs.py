"""`make docs-figures` (python -m bench.docs): the benchmark summary page's figures (docs/benchmarks/README.md),
copied from the files the benchmarks wrote. `refresh` rewrites every block `<!-- include NAME.md -->` (the
whole report) or `<!-- include NAME.md targets -->` (its command and target lines) ... `<!-- /include -->`
from its file, a path relative to the page; tests/test_docs_figures.py checks that each block equals what
its file gives, so no figure is typed by hand.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

from bench import provenance

REPO = Path(__file__).resolve().parent.parent
SUMMARY = REPO / "docs" / "benchmarks" / "README.md"
BLOCK = re.compile(r"(<!-- include (?P<path>\S+)(?: (?P<mode>targets))? -->\n)(?P<body>.*?)(<!-- /include -->)",
                   re.S)
HEADING = re.compile(r"^(#{1,6}) ")
NEST = 2  # the page's blocks sit under `##` sections
TARGET = re.compile(r"target", re.I)


def included(path: Path, mode: str | None = None) -> str:
    """What a block holds of the report at `path`: with mode `targets`, `targets(path)`; else everything
    after its `# title` line, trimmed, with its headings NEST levels deeper (at most six), so that a
    report's `## scene` sits under the page's `## section`, not beside it."""
    if mode == "targets":
        return targets(path)
    lines = path.read_text().splitlines()
    if lines and lines[0].startswith("# "):
        lines = lines[1:]
    nested = [HEADING.sub(lambda m: "#" * min(6, len(m.group(1)) + NEST) + " ", line) for line in lines]
    return "\n".join(nested).strip() + "\n"


def targets(path: Path) -> str:
    """The report's command (from its provenance) and each line naming a target, with the indented lines
    that continue it, verbatim in a text block."""
    kept = ["$ quekaro bench " + " ".join(provenance.load(path).command)]
    going = False
    for line in path.read_text().splitlines():
        going = bool(TARGET.search(line)) or (going and line.startswith(" ") and line.strip() != "")
        if going:
            kept.append(line)
    return "```text\n" + "\n".join(kept) + "\n```\n"


def blocks(text: str) -> list[tuple[str, str]]:
    """(cited path, block body) for every include block of a markdown text."""
    return [(m.group("path"), m.group("body")) for m in BLOCK.finditer(text)]


def expected(text: str, root: Path) -> list[tuple[str, str]]:
    """(cited path, what its block should hold) for every include block of a page whose paths start at
    `root`."""
    return [(m.group("path"), included(root / m.group("path"), m.group("mode"))) for m in BLOCK.finditer(text)]


def refresh(page: Path, root: Path | None = None) -> str:
    """The page with every block rewritten from its file, a path relative to `root` (default: the page's
    folder); a missing file is an error naming it."""
    base = page.parent if root is None else root

    def body(match: re.Match) -> str:
        source = base / match.group("path")
        if not source.is_file():
            raise SystemExit(f"{page}: include of {match.group('path')}: no such file (run its benchmark)")
        return match.group(1) + included(source, match.group("mode")) + match.group(5)

    return BLOCK.sub(body, page.read_text())


def refresh_file(page: Path) -> str:
    """Rewrite `page`'s blocks from the files they cite; a line saying what changed."""
    new = refresh(page)
    changed = new != page.read_text()
    page.write_text(new)
    return f"{page}: {len(blocks(new))} included figure blocks" + (", updated" if changed else ", unchanged")


def main() -> int:
    print(refresh_file(SUMMARY))
    return 0


if __name__ == "__main__":
    sys.exit(main())
