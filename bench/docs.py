"""`make docs-figures` (python -m bench.docs): README.md's figures, copied from the files the benchmarks
wrote. `refresh` rewrites every block `<!-- include docs/benchmarks/NAME.md -->` ... `<!-- /include -->`
from its file (`included`); tests/test_docs_figures.py checks that each block equals its file, so no figure
is typed by hand.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
BLOCK = re.compile(r"(<!-- include (?P<path>\S+) -->\n)(?P<body>.*?)(<!-- /include -->)", re.S)
HEADING = re.compile(r"^(#{1,6}) ")
NEST = 2  # the README's blocks sit under `###` sections


def included(path: Path) -> str:
    """What a block holds of the file at `path`: everything after its `# title` line, trimmed, with
    its headings NEST levels deeper (at most six), so that a file's `## scene` sits under the README's
    `### section`, not beside its `## Benchmarks`."""
    lines = path.read_text().splitlines()
    if lines and lines[0].startswith("# "):
        lines = lines[1:]
    nested = [HEADING.sub(lambda m: "#" * min(6, len(m.group(1)) + NEST) + " ", line) for line in lines]
    return "\n".join(nested).strip() + "\n"


def blocks(text: str) -> list[tuple[str, str]]:
    """(cited path, block body) for every include block of a markdown text."""
    return [(m.group("path"), m.group("body")) for m in BLOCK.finditer(text)]


def refresh(readme: Path, root: Path = REPO) -> str:
    """The README with every block rewritten from its file (a missing file is an error naming it)."""
    def body(match: re.Match) -> str:
        source = root / match.group("path")
        if not source.is_file():
            raise SystemExit(f"{readme}: include of {match.group('path')}: no such file (run its benchmark)")
        return match.group(1) + included(source) + match.group(4)

    return BLOCK.sub(body, readme.read_text())


def refresh_file(readme: Path) -> str:
    """Rewrite `readme`'s blocks from the files beside it that they cite; a line saying what changed."""
    new = refresh(readme, readme.parent)
    changed = new != readme.read_text()
    readme.write_text(new)
    return f"{readme}: {len(blocks(new))} included figure blocks" + (", updated" if changed else ", unchanged")


def main() -> int:
    print(refresh_file(REPO / "README.md"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
