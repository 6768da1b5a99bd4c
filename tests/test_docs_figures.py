"""Figures in README.md come from the files the benchmarks and reports write, never typed by hand."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def test_readme_compat_line_is_the_one_the_report_wrote():
    written = (REPO / "docs" / "compat.md").read_text()
    line = re.search(r"^\d+ of \d+ scenes of the compatibility suite render as Mitsuba renders them\.$", written,
                     re.MULTILINE)
    assert line, "docs/compat.md has no summary line: run tests/compat_report.py"
    readme = (REPO / "README.md").read_text()
    marker = readme.index("<!-- compat-summary")
    assert readme[marker:].splitlines()[1] == line.group(0)
