"""Figures in docs/benchmarks/README.md (the summary page) and README.md's compatibility line come from the
files the benchmarks and reports write, never typed by hand."""

from __future__ import annotations

import re
from pathlib import Path

from bench import provenance
from bench.commands import build_parser
from bench.docs import BLOCK, SUMMARY, blocks, expected, included, refresh

REPO = Path(__file__).resolve().parent.parent


def test_readme_compat_line_is_the_one_the_report_wrote():
    written = (REPO / "docs" / "compat.md").read_text()
    line = re.search(r"^\d+ of \d+ scenes of the compatibility suite render as Mitsuba renders them\.$", written,
                     re.MULTILINE)
    assert line, "docs/compat.md has no summary line: run tests/compat_report.py"
    readme = (REPO / "README.md").read_text()
    marker = readme.index("<!-- compat-summary")
    assert readme[marker:].splitlines()[1] == line.group(0)


def test_every_included_figure_block_is_its_file() -> None:
    page = SUMMARY.read_text()
    found = blocks(page)
    assert len(found) >= 4, "docs/benchmarks/README.md includes no benchmark files"
    for path, _ in found:
        assert (SUMMARY.parent / path).is_file(), f"docs/benchmarks/README.md includes {path}, which does not exist"
    for (path, body), (_, wanted) in zip(found, expected(page, SUMMARY.parent), strict=True):
        assert body == wanted, f"docs/benchmarks/README.md's block of {path} differs from it: make docs-figures"


def test_every_included_report_says_how_it_was_made_and_planned_with_the_shipped_rules() -> None:
    """A block's report keeps the command that wrote it (one `quekaro bench` parses, writing where the report
    is) and the hash of the rule file its levels planned with: a retuned rule file whose figures were not
    written again (make bench) fails here, naming them."""
    parser = build_parser()
    stale = []
    for path, _ in blocks(SUMMARY.read_text()):
        report = SUMMARY.parent / path
        made = provenance.load(report)
        args = parser.parse_args(provenance.rerun_argv(report, made))
        assert args.bench == made.command[0], f"{path}: its provenance's command runs {args.bench}"
        assert Path(args.out) in (report, report.parent), f"{path}: its command writes to {args.out}"
        if provenance.stale(made):
            stale.append(path)
    assert not stale, f"planned with another rule file than the shipped one (run make bench): {stale}"


def test_every_report_under_docs_says_how_it_was_made() -> None:
    """Reports the summary page only links (a rerun, a tried and dropped setting) keep their provenance too."""
    parser = build_parser()
    found = [md for md in sorted((REPO / "docs" / "benchmarks").rglob("*.md")) if md.name != "README.md"]
    assert len(found) >= 15
    for report in found:
        made = provenance.load(report)
        assert parser.parse_args(provenance.rerun_argv(report, made)).bench == made.command[0], report


def test_no_figure_is_typed_on_the_summary_page() -> None:
    """Outside the included blocks and code, the summary page holds no target line and no decimal number,
    and its tables no number at all: figures come from files."""
    prose = BLOCK.sub("", SUMMARY.read_text())
    prose = re.sub(r"```.*?```", "", prose, flags=re.S)
    prose = re.sub(r"`[^`]*`", "", prose)
    typed = [line for line in prose.splitlines()
             if "target:" in line or re.search(r"\d+\.\d+", line) or (line.startswith("|") and re.search(r"\d", line))]
    assert not typed, f"figures typed by hand in docs/benchmarks/README.md: {typed}"


def test_a_targets_block_holds_the_command_and_the_target_lines(tmp_path: Path) -> None:
    (tmp_path / "fig.md").write_text("# Title\n\n| a |\n| 1.5 |\ntarget: x <= 2: 1.5 PASS\n"
                                     "Target: y (medians):\n  whole 0.8 s (met)\nafter\n")
    provenance.write(tmp_path / "fig.md", provenance.Provenance(
        command=["fuzzy", "--seconds", "1"], out_is_file=True, rules_digest=None, revision="r", written="w",
        seconds=None))
    assert included(tmp_path / "fig.md", "targets") == (
        "```text\n$ quekaro bench fuzzy --seconds 1\ntarget: x <= 2: 1.5 PASS\nTarget: y (medians):\n"
        "  whole 0.8 s (met)\n```\n")


def test_an_included_files_headings_nest_under_the_pages_section(tmp_path: Path) -> None:
    (tmp_path / "fig.md").write_text(
        "# Title (`cmd`)\n\n## scene a\n\n| a |\n|---|\n| 1.5 |\n#### deep\n#not a heading\n")
    assert included(tmp_path / "fig.md") == "#### scene a\n\n| a |\n|---|\n| 1.5 |\n###### deep\n#not a heading\n"


def test_no_included_heading_sits_beside_the_pages_sections() -> None:
    for path, body in blocks(SUMMARY.read_text()):
        shallow = [line for line in body.splitlines() if re.match(r"#{1,3} ", line)]
        assert not shallow, f"the summary page's block of {path} has headings at the page's own levels: {shallow}"


def test_refresh_rewrites_a_stale_block(tmp_path: Path) -> None:
    (tmp_path / "fig.md").write_text("# Title (`cmd`)\n\n| a |\n|---|\n| 1.5 |\n")
    readme = tmp_path / "README.md"
    readme.write_text("x\n<!-- include fig.md -->\n| a |\n| 9.9 |\n<!-- /include -->\ny\n")
    assert refresh(readme) == "x\n<!-- include fig.md -->\n| a |\n|---|\n| 1.5 |\n<!-- /include -->\ny\n"
