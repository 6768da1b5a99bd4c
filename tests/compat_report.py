"""Print (and write to docs/compat.md) how many scenes of the compatibility suite render as Mitsuba renders
them, through `quekaro render --opt off` and through a real 2-agent farm.

    .venv/bin/python tests/compat_report.py

The same comparisons as tests/test_compat.py (tests/compat_cases.py, tests/render_check.py), gathered into
one table instead of pass/fail test cases. The README's line is checked against the file this writes.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

from compat_cases import CASES, REPO, job_args, problems, quekaro, wait_done
from render_check import FALSE_FAILURES

from farm.local import LocalFarm

OUT = REPO / "docs" / "compat.md"


def summary_line(passed: int, total: int) -> str:
    return f"{passed} of {total} scenes of the compatibility suite render as Mitsuba renders them"


def _in_process(tmp: Path) -> dict[str, list[str]]:
    found = {}
    for case in CASES:
        out = tmp / f"{case.name}.exr"
        done = quekaro("render", *job_args(case), "-o", str(out), "--threads", "2")
        found[case.name] = problems(case, out) if done.returncode == 0 else [done.stderr.strip()[-300:]]
    return found


def _farm(tmp: Path) -> dict[str, list[str]]:
    found = {}
    with LocalFarm(tmp / "farm", agents=2, threads=1) as farm:
        farm.wait_for_agents()
        jobs = {c.name: quekaro("submit", *job_args(c), "--home", str(tmp / "farm")) for c in CASES}
        for case in CASES:
            submitted = jobs[case.name]
            if submitted.returncode != 0:
                found[case.name] = [submitted.stderr.strip()[-300:]]
                continue
            job_id = submitted.stdout.strip().splitlines()[-1]
            job = wait_done(farm.client(), job_id)
            out = tmp / f"farm-{case.name}.exr"
            fetched = quekaro("result", job_id, "-o", str(out), "--home", str(tmp / "farm"))
            ok = job["status"] == "done" and fetched.returncode == 0
            found[case.name] = problems(case, out) if ok else [f"job {job['status']}: {job.get('error')}"]
    return found


def main() -> int:
    with tempfile.TemporaryDirectory() as tmp:
        local, farm = _in_process(Path(tmp)), _farm(Path(tmp))
    rows = ["| scene | file | quekaro render | 2-agent farm |", "|---|---|---|---|"]
    passed = 0
    for case in CASES:
        both = not local[case.name] and not farm[case.name]
        passed += both
        cells = ["same" if not found[case.name] else "DIFFERENT: " + "; ".join(found[case.name])[:200]
                 for found in (local, farm)]
        rows.append(f"| {case.name} | `{case.file}` | {cells[0]} | {cells[1]} |")
    line = summary_line(passed, len(CASES))
    text = "\n".join([
        "# Compatibility suite", "",
        "Written by `.venv/bin/python tests/compat_report.py`: each scene of tests/compat/scenes rendered by",
        "`quekaro render --opt off` and by a real 2-agent farm, compared with plain Mitsuba rendering the same",
        "file in the same variant (tests/render_check.py: a per-pixel test on mean and variance, Sidak-corrected;",
        f"false failures, Mitsuba against Mitsuba: {FALSE_FAILURES}).", "",
        line + ".", "", *rows, ""])
    OUT.write_text(text)
    print("\n".join(rows))
    print(line)
    return 0 if passed == len(CASES) else 1


if __name__ == "__main__":
    sys.exit(main())
