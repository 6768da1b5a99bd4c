"""Each benchmark report keeps how it was made (bench.provenance), and `make bench` (bench.rerun) writes
the stale ones again with their own commands."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from bench import accuracy, allocation, provenance, rerun
from bench.commands import build_parser
from bench.docs import included
from core.data import default_rules_path
from fuzzy import load_rulebase

REPO = Path(__file__).resolve().parent.parent
TINY_FUZZY = ["fuzzy", "--units", "200", "--repeats", "1", "--check-units", "2", "--check-points", "2000"]


def test_where_a_report_goes_and_resuming_are_not_part_of_its_command() -> None:
    argv = ["accuracy", "--out", "/tmp/x", "--suite", "--resume", "--out=/tmp/y", "--runs", "1"]
    assert provenance.reproducible(argv) == ["accuracy", "--suite", "--runs", "1"]
    assert provenance.reproducible(["scaling"]) == ["scaling"]


def _retuned(path: Path) -> Path:
    """The shipped rules with one Ls set moved: rules that compute otherwise."""
    shipped = default_rules_path().read_text()
    moved = shipped.replace('<fset label="S" a="0.15" b="0.3" c="0.3" d="0.5"/>',
                            '<fset label="S" a="0.15" b="0.35" c="0.35" d="0.5"/>')
    assert moved != shipped
    path.write_text(moved)
    return path


def test_a_record_reads_back_and_names_its_rules_by_digest(tmp_path: Path) -> None:
    report, rules = tmp_path / "accuracy.md", _retuned(tmp_path / "rules.xml")
    report.write_text("# figures\n")
    path = provenance.record(report, ["accuracy", "--out", str(tmp_path), "--levels", "off,S"], rules, 12.5,
                             out_is_file=False)
    assert path == tmp_path / "accuracy.provenance.json"
    made = provenance.load(report)
    assert made.command == ["accuracy", "--levels", "off,S"] and made.seconds == 12.5
    assert made.rules_digest == load_rulebase(rules).digest() != load_rulebase(default_rules_path()).digest()
    assert re.fullmatch(r"[0-9a-f]{40}(\+dirty)?", made.revision), made.revision  # this is a git checkout
    assert provenance.rerun_argv(report, made) == ["accuracy", "--levels", "off,S", "--out", str(tmp_path)]
    assert provenance.stale(made)  # planned with rules other than the shipped ones
    assert not provenance.stale(made, rules)
    rules.write_text(rules.read_text().replace("<quekaro", "<!-- prose only -->\n<quekaro"))
    assert not provenance.stale(made, rules)  # the file's bytes changed, not what its rules compute
    rules.write_text(default_rules_path().read_text())
    assert provenance.stale(made, rules)


def test_a_report_planned_without_rules_is_never_stale(tmp_path: Path) -> None:
    report = tmp_path / "hosts.md"
    provenance.record(report, ["hosts", "--out", str(report)], None, None, out_is_file=True)
    made = provenance.load(report)
    assert made.rules_digest is None and not provenance.stale(made)
    assert provenance.rerun_argv(report, made) == ["hosts", "--out", str(report)]


@pytest.mark.parametrize(("text", "says"), [
    (None, "no provenance"),
    ("{not json", "not readable JSON"),
    ("[1, 2]", "not a JSON object"),
    (json.dumps({"command": ["scaling"], "out_is_file": False}),
     "missing field(s) revision, rules_digest, seconds, written"),
    (json.dumps({"command": ["scaling"], "out_is_file": False, "rules_digest": None, "revision": "x",
                 "written": "2026", "seconds": 1, "by": "hand"}), "unknown field(s) by"),
    (json.dumps({"command": "scaling", "out_is_file": False, "rules_digest": None, "revision": "x",
                 "written": "2026", "seconds": 1}), "field command must be"),
])
def test_a_missing_or_malformed_provenance_is_refused_naming_file_and_field(tmp_path: Path, text: str | None,
                                                                            says: str) -> None:
    report = tmp_path / "scaling.md"
    if text is not None:
        provenance.sidecar(report).write_text(text)
    with pytest.raises(provenance.ProvenanceError) as err:
        provenance.load(report)
    assert str(provenance.sidecar(report)) in str(err.value) and says in str(err.value)


def test_a_benchmark_names_the_rule_file_only_when_its_levels_plan_with_one(tmp_path: Path) -> None:
    parser = build_parser()
    rules = tmp_path / "retune.xml"
    assert accuracy.rules_file(parser.parse_args(["accuracy", "--levels", "off"])) is None
    assert accuracy.rules_file(parser.parse_args(["accuracy", "--levels", "off,S"])) == default_rules_path()
    assert accuracy.rules_file(parser.parse_args(["accuracy", "--rules", str(rules)])) == rules
    assert allocation.rules_file(parser.parse_args(["allocation", "--rules", str(rules)])) == rules


def _include(readme: Path, reports: list[str]) -> None:
    readme.write_text("".join(f"<!-- include {r} -->\n{included(readme.parent / r)}<!-- /include -->\n"
                              for r in reports))


def test_rerun_picks_the_stale_reports_in_the_readmes_order(tmp_path: Path, capsys) -> None:
    for name, rules in (("a", tmp_path / "old-rules.xml"), ("b", default_rules_path()), ("c", None)):
        (tmp_path / name).mkdir()
        report = tmp_path / name / "allocation.md"
        report.write_text(f"# t\n\n{name}\n")
        if rules is not None and not rules.exists():
            _retuned(rules)
        provenance.record(report, ["allocation", "--spp", "8"], rules, 1.0, out_is_file=False)
    readme = tmp_path / "README.md"
    _include(readme, ["c/allocation.md", "b/allocation.md", "a/allocation.md"])
    assert rerun.main(["--dry-run", "--readme", str(readme)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines == [f"a/allocation.md: quekaro bench allocation --spp 8 --out {tmp_path / 'a'}"]
    assert rerun.main(["--dry-run", "--all", "--readme", str(readme)]) == 0
    assert [line.split(":")[0] for line in capsys.readouterr().out.splitlines()] == [
        "c/allocation.md", "b/allocation.md", "a/allocation.md"]
    # Named reports run whether stale or not, in the README's order.
    named = [str(tmp_path / "b" / "allocation.md"), str(tmp_path / "c" / "allocation.md")]
    assert rerun.main(["--dry-run", "--readme", str(readme), *named]) == 0
    assert [line.split(":")[0] for line in capsys.readouterr().out.splitlines()] == [
        "c/allocation.md", "b/allocation.md"]


def test_rerun_refuses_a_report_without_provenance_naming_it(tmp_path: Path, capsys) -> None:
    (tmp_path / "scaling.md").write_text("# t\n\nx\n")
    readme = tmp_path / "README.md"
    _include(readme, ["scaling.md"])
    assert rerun.main(["--dry-run", "--all", "--readme", str(readme)]) == 2
    assert "scaling.provenance.json: no provenance" in capsys.readouterr().err


@pytest.mark.slow
def test_a_benchmark_keeps_its_provenance_and_rerun_writes_the_report_again(tmp_path: Path) -> None:
    """A real `quekaro bench fuzzy` records its command and the shipped rules' digest; `bench.rerun --all`
    runs that command again (a real process) and rewrites both the report and the README's block."""
    done = subprocess.run([sys.executable, "-m", "quekaro", "bench", *TINY_FUZZY, "--out", str(tmp_path)],
                          cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    report = tmp_path / "fuzzy.md"
    made = provenance.load(report)
    assert made.command == TINY_FUZZY and not made.out_is_file and made.seconds > 0
    assert made.rules_digest == load_rulebase(default_rules_path()).digest() and not provenance.stale(made)
    figures = report.read_text()
    assert figures.startswith(f"# Fuzzy engine against pyfuzzylite (`quekaro bench {' '.join(TINY_FUZZY)}`)")
    report.write_text("# Fuzzy engine\n\nfigures typed by hand\n")
    readme = tmp_path / "README.md"
    _include(readme, ["fuzzy.md"])
    assert rerun.main(["--all", "--readme", str(readme)]) == 0
    again = report.read_text()
    assert "typed by hand" not in again and again.splitlines()[0] == figures.splitlines()[0]
    assert "200 random units" in again and "evals/s" in again  # the recorded command's --units, measured anew
    assert readme.read_text() == f"<!-- include fuzzy.md -->\n{included(report)}<!-- /include -->\n"
    assert provenance.load(report).written >= made.written


def test_the_revision_is_dirty_for_code_not_for_the_reports_a_run_rewrites(tmp_path: Path) -> None:
    def git(*args: str) -> None:
        subprocess.run(["git", "-C", str(tmp_path), *args], check=True, capture_output=True)

    git("init", "-q")
    (tmp_path / "docs").mkdir()
    for name in ("docs/a.md", "README.md", "code.py"):
        (tmp_path / name).write_text("1\n")
    git("add", "-A")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "c")
    clean = provenance.revision(tmp_path)
    assert re.fullmatch(r"[0-9a-f]{40}", clean), clean
    (tmp_path / "docs" / "a.md").write_text("2\n")
    (tmp_path / "README.md").write_text("2\n")
    assert provenance.revision(tmp_path) == clean
    (tmp_path / "code.py").write_text("2\n")
    assert provenance.revision(tmp_path) == clean + "+dirty"
    assert provenance.revision(tmp_path / "docs" / "nowhere") == "unknown"
