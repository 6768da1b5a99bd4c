"""README.md is the front door and docs/ the guide: the README stays short and starts with the two commands,
every relative link in them resolves inside the repository, and nothing the repository holds points outside
the clone (test data under ../shared/scenes, which CI provides beside it, excepted)."""

from __future__ import annotations

import re
import statistics
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
README = REPO / "README.md"
LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
FENCE = re.compile(r"^(```|~~~).*?^\1", re.S | re.M)
OUTSIDE_NOTE = re.compile(r"\.\./shared/(?!scenes\b)")
BARE_DESIGN = re.compile(r"(?<![\w/.-])design\.md")
MEDIAN = re.compile(r"^target: level (?!off)\w+(?: in passes)?: median relMSE over \d+ scene\(s\) <= [\d.]+ x uniform "
                    r"\(equal wall time\): (\d+\.\d+)", re.M)
# the 64-spp accuracy runs the README's advice sums up: one process and farm, whole, in passes and adaptive
ADVICE_REPORTS = ("accuracy.md", "inprocess/accuracy.md", "inprocess-progressive/accuracy.md",
                  "farm-progressive/accuracy.md", "inprocess-adaptive/accuracy.md", "farm-adaptive/accuracy.md")


def repo_files() -> list[Path]:
    """Tracked files and untracked ones git does not ignore (new pages count before their commit)."""
    listed = subprocess.run(["git", "-C", str(REPO), "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
                            capture_output=True, check=True, timeout=60).stdout.decode()
    return [REPO / name for name in dict.fromkeys(listed.split("\0")) if name and (REPO / name).is_file()]


def text_of(path: Path) -> str | None:
    data = path.read_bytes()
    if b"\0" in data[:8192]:
        return None
    try:
        return data.decode()
    except UnicodeDecodeError:
        return None


def links(markdown: str) -> list[str]:
    """Link targets outside code blocks and code spans."""
    prose = re.sub(r"`[^`\n]*`", "", FENCE.sub("", markdown))
    return [m.group(1) for m in LINK.finditer(prose)]


def anchors(markdown: str) -> set[str]:
    """The anchors GitHub makes of a page's headings."""
    heads = re.findall(r"^#{1,6} +(.+?) *$", FENCE.sub("", markdown), re.M)
    return {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-") for h in heads}


def broken_links(text: str, page: Path) -> list[str]:
    """The links of `text`, the page at `page`, that leave the repository, name no file, or name a heading
    the target page lacks."""
    bad = []
    for target in links(text):
        if re.match(r"[a-z][a-z0-9+.-]*:", target, re.I):
            continue  # https:, mailto:
        path, _, anchor = target.partition("#")
        dest = (page.parent / path).resolve()
        if not dest.is_relative_to(REPO):
            bad.append(f"{target} (outside the repository)")
        elif path and not dest.exists():
            bad.append(f"{target} (no such file)")
        elif anchor and (not path or dest.suffix == ".md") and anchor not in anchors(
                dest.read_text() if path else text):
            bad.append(f"{target} (no heading for #{anchor})")
    return bad


def test_readme_is_under_200_lines() -> None:
    lines = README.read_text().count("\n")
    assert lines < 200, f"README.md has {lines} lines: move detail into docs/"


def test_readme_starts_with_make_demo_and_make_test() -> None:
    block = re.search(r"^```\w*\n(.*?)^```", README.read_text(), re.S | re.M)
    assert block, "README.md has no code block"
    commands = [line.split("#")[0].strip() for line in block.group(1).splitlines() if line.strip()]
    assert commands[:2] == ["make demo", "make test"], f"README.md's first code block starts {commands[:2]}"


def test_every_relative_link_in_the_readme_and_docs_resolves() -> None:
    pages = [README, *sorted((REPO / "docs").rglob("*.md"))]
    bad = {str(page.relative_to(REPO)): broken for page in pages if (broken := broken_links(page.read_text(), page))}
    assert not bad, f"broken links: {bad}"


def test_the_link_check_finds_a_missing_file_an_escape_and_a_missing_heading() -> None:
    text = ("# Probe page\n[a](rendering.md) [b](missing.md) [c](../../outside.md) [d](rendering.md#no-such) "
            "`[e](missing-in-code.md)` [f](https://example.org/x.md) [g](rendering.md#goals-in-passes) "
            "[h](#probe-page) [i](#elsewhere)\n")
    found = [bad.split(" ")[0] for bad in broken_links(text, REPO / "docs" / "probe.md")]
    assert found == ["missing.md", "../../outside.md", "rendering.md#no-such", "#elsewhere"]


def test_nothing_points_outside_the_clone() -> None:
    """No markdown link leaves the repository, no file names ../shared/ beyond its scenes (the design note
    now lives in docs/design.md), and every mention of design.md is docs/design.md (a page in docs/ may
    link it as design.md)."""
    bad = []
    for path in repo_files():
        text = text_of(path)
        if text is None or path == Path(__file__).resolve():  # this file states the rule
            continue
        name = str(path.relative_to(REPO))
        for m in OUTSIDE_NOTE.finditer(text):
            bad.append(f"{name}: {text[m.start():m.start() + 40].splitlines()[0]}")
        in_docs = path.parent == REPO / "docs"
        for m in BARE_DESIGN.finditer(text):
            if not (in_docs and text[max(0, m.start() - 2):m.start()] in ("](", " [")):
                bad.append(f"{name}:{text.count(chr(10), 0, m.start()) + 1}: bare design.md (write docs/design.md)")
        if path.suffix == ".md":
            for target in links(text):
                dest = (path.parent / target.partition("#")[0]).resolve()
                if not re.match(r"[a-z][a-z0-9+.-]*:", target, re.I) and not dest.is_relative_to(REPO):
                    bad.append(f"{name}: link {target} leaves the repository")
    assert not bad, "references outside the clone:\n" + "\n".join(bad)


def test_the_readmes_advice_states_the_reports_range() -> None:
    """The README's 'lower --spp' advice quotes the range of the rule levels' median relMSE against plain
    Mitsuba at equal wall time over the 64-spp accuracy reports: a rerun that moves it fails here."""
    bench = REPO / "docs" / "benchmarks"
    medians = [float(v) for name in ADVICE_REPORTS for v in MEDIAN.findall((bench / name).read_text())]
    assert len(medians) == 5 * len(ADVICE_REPORTS), f"expected five levels' medians per report, got {medians}"
    stated = f"{min(medians):.2f}-{max(medians):.2f}x"
    assert stated in README.read_text(), f"README.md should say the rule levels are {stated} plain Mitsuba's relMSE"
    assert statistics.median(medians) > 1, "the levels now beat uniform spp: the README's advice must change"
