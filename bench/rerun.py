"""`make bench` (python -m bench.rerun): write the benchmark summary's figure files again (docs/benchmarks/
README.md), each with the command that wrote it (its provenance), in the summary's order, then rewrite the
summary's blocks from them. By default only the stale ones (planned with a rule file other than the shipped
one); `--all` every one; REPORT arguments only those (stale or not); `--dry-run` prints the commands. Run it
alone on the machine: the figures are timings."""

from __future__ import annotations

import argparse
import shlex
import subprocess
import sys
import time
from pathlib import Path

from bench import docs, provenance

REPO = docs.REPO


def reports(readme: Path) -> list[Path]:
    """The report files README's blocks include, once each, in the README's order."""
    root = readme.parent
    return list(dict.fromkeys(root / path for path, _ in docs.blocks(readme.read_text())))


def planned(readme: Path, everything: bool, only: list[Path] | None = None) -> list[tuple[Path, list[str]]]:
    """(report, arguments after `quekaro bench`) for each report to write again: `only` these (README's
    order first, then any it does not include), else every included one that is stale, or `everything`."""
    included = reports(readme)
    todo = included
    if only:  # resolved: the reruns run in the README's folder, whatever the caller's
        place = {r.resolve(): i for i, r in enumerate(included)}
        todo = sorted(dict.fromkeys(p.resolve() for p in only), key=lambda p: place.get(p, len(place)))
    chosen = []
    for report in todo:
        made = provenance.load(report)
        if only or everything or provenance.stale(made):
            chosen.append((report, provenance.rerun_argv(report, made)))
    return chosen


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.rerun", description=__doc__.split("\n\n")[0])
    parser.add_argument("--all", action="store_true", help="every included report, not only the stale ones")
    parser.add_argument("--dry-run", action="store_true", help="print the commands, run nothing")
    parser.add_argument("--readme", type=Path, default=docs.SUMMARY, help=argparse.SUPPRESS)
    parser.add_argument("reports", nargs="*", type=Path, metavar="REPORT",
                        help="report files to write again (default: the README's stale ones)")
    args = parser.parse_args(argv)
    try:
        todo = planned(args.readme, args.all, args.reports)
    except provenance.ProvenanceError as exc:
        print(f"bench.rerun: {exc}", file=sys.stderr)
        return 2
    for report, bench_argv in todo:
        print(f"{_shown(report, args.readme.parent)}: quekaro bench {shlex.join(bench_argv)}", flush=True)
        if args.dry_run:
            continue
        started = time.perf_counter()
        # From the repository's root, where the commands ran (their scene and --out paths are relative to it).
        done = subprocess.run([sys.executable, "-m", "quekaro", "bench", *bench_argv], cwd=REPO)
        if done.returncode != 0:  # what was written before stays; this report and the rest are left as they were
            print(f"bench.rerun: {report} not written again (exit status {done.returncode})", file=sys.stderr)
            return done.returncode
        print(f"  written in {time.perf_counter() - started:.0f} s", flush=True)
    if not todo:
        print("bench.rerun: every included report is current" + ("" if args.all else " (--all: run them anyway)"))
    if not args.dry_run:
        print(docs.refresh_file(args.readme))
    return 0


def _shown(report: Path, root: Path) -> str:
    return str(report.relative_to(root)) if report.is_relative_to(root) else str(report)


if __name__ == "__main__":
    sys.exit(main())
