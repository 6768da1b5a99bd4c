"""Where a benchmark report came from, kept beside it as NAME.provenance.json: the command that
wrote it (less --out and --resume, so that it can write again anywhere, anew), the digest of the rules
its levels planned with (fuzzy.rulebase.RuleBase.digest: what they compute, so that an edit of the rule
file's comments or layout stales nothing), the code revision and when. A report planned with rules other
than the shipped ones is stale: the docs test names it, and `python -m bench.rerun` (make bench) writes it
again with its own command."""

from __future__ import annotations

import json
import subprocess
from dataclasses import asdict, dataclass, fields
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from core.data import DATA, default_rules_path
from core.errors import QuekaroError
from core.files import written_atomically
from fuzzy import load_rulebase

SUFFIX = ".provenance.json"
REPO = Path(__file__).resolve().parent.parent
SHIPPED_RULES = DATA / "rules" / "pathtracing.xml"


class ProvenanceError(QuekaroError):
    """A report's provenance file is missing or malformed (the message names the file and field)."""


@dataclass(frozen=True)
class Provenance:
    """How a report was made. `command` follows `quekaro bench`; `out_is_file`: its --out names the report
    itself (bench hosts), not the report's folder; `rules_digest`: None where no rule file planned it."""

    command: list[str]
    out_is_file: bool
    rules_digest: str | None
    revision: str
    written: str
    seconds: float | None
    note: str = ""  # how the record was made, where not by the run itself


def rules_for(args: Any, levels: list[str]) -> Path | None:
    """The rule file a run of these levels planned with: its --rules, else the default one; None when
    every level is off (level off plans with no rules)."""
    if all(level == "off" for level in levels):
        return None
    given = getattr(args, "rules", None)
    return Path(given) if given is not None else default_rules_path()


def sidecar(report: Path) -> Path:
    """The provenance file of `report` (NAME.md -> NAME.provenance.json, beside it)."""
    return report.with_name(report.stem + SUFFIX)


def reproducible(argv: list[str]) -> list[str]:
    """`argv` less `--out X` / `--out=X` (where a report goes is not how it is made) and `--resume` (run
    again, it would read the old run's cells instead of measuring anew)."""
    kept: list[str] = []
    skip = False
    for arg in argv:
        if skip:
            skip = False
        elif arg == "--out":
            skip = True
        elif not arg.startswith("--out=") and arg != "--resume":
            kept.append(arg)
    return kept


def revision(repo: Path = REPO) -> str:
    """The checkout's commit, `+dirty` when tracked files other than the reports (docs/, README.md, which
    a run of several benchmarks rewrites as it goes) differ from it; `unknown` outside a git checkout."""
    try:
        head = subprocess.run(["git", "-C", str(repo), "rev-parse", "HEAD"], capture_output=True, text=True,
                              timeout=30, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(repo), "status", "--porcelain", "--untracked-files=no", "--",
                                ".", ":!docs", ":!README.md"],
                               capture_output=True, text=True, timeout=30, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return head + ("+dirty" if dirty else "")


def record(report: Path, argv: list[str], rules: Path | None, seconds: float | None, out_is_file: bool) -> Path:
    """Write `report`'s provenance: `argv` as given after `quekaro bench`, `rules` the rule file it planned
    with (None: none)."""
    made = Provenance(command=reproducible(argv), out_is_file=out_is_file,
                      rules_digest=rules_digest(rules) if rules is not None else None, revision=revision(),
                      written=datetime.now(UTC).isoformat(timespec="seconds"), seconds=seconds)
    return write(report, made)


def write(report: Path, made: Provenance) -> Path:
    """`made` as `report`'s provenance file, written whole or not at all."""
    text = json.dumps(asdict(made), indent=1) + "\n"
    return written_atomically(sidecar(report), lambda tmp: tmp.write_text(text), "a benchmark's provenance")


def load(report: Path) -> Provenance:
    """`report`'s provenance; ProvenanceError naming the file (and field) when missing or malformed."""
    path = sidecar(report)
    try:
        raw = json.loads(path.read_text())
    except FileNotFoundError:
        raise ProvenanceError(f"{path}: no provenance for {report} (write it with its benchmark)") from None
    except (OSError, ValueError) as exc:
        raise ProvenanceError(f"{path}: not readable JSON ({exc})") from exc
    if not isinstance(raw, dict):
        raise ProvenanceError(f"{path}: not a JSON object")
    names = {f.name for f in fields(Provenance)}
    missing = sorted(names - {"note"} - raw.keys())
    unknown = sorted(raw.keys() - names)
    if missing or unknown:
        raise ProvenanceError(f"{path}: " + "; ".join(
            ([f"missing field(s) {', '.join(missing)}"] if missing else [])
            + ([f"unknown field(s) {', '.join(unknown)}"] if unknown else [])))
    if not (isinstance(raw["command"], list) and raw["command"] and all(isinstance(a, str) for a in raw["command"])):
        raise ProvenanceError(f"{path}: field command must be a non-empty list of strings")
    return Provenance(**raw)


def rerun_argv(report: Path, made: Provenance) -> list[str]:
    """The arguments after `quekaro bench` that write `report` again where it is."""
    return [*made.command, "--out", str(report if made.out_is_file else report.parent)]


def rules_digest(rules: Path) -> str:
    """The digest of what the rule file computes (fuzzy.rulebase.RuleBase.digest)."""
    return load_rulebase(rules).digest()


def stale(made: Provenance, rules: Path = SHIPPED_RULES) -> bool:
    """Whether the report planned with rules that compute otherwise than `rules` (the shipped file)."""
    return made.rules_digest is not None and made.rules_digest != rules_digest(rules)
