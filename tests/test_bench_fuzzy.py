"""`quekaro bench fuzzy` at its smallest: the engine against pyfuzzylite on the shipped rule base."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from bench import fuzzy_engine

REPO = Path(__file__).resolve().parent.parent


def test_a_tiny_run_measures_both_engines_and_their_agreement(tmp_path: Path) -> None:
    done = subprocess.run([sys.executable, "-m", "quekaro", "bench", "fuzzy", "--json", "--units", "200",
                           "--repeats", "1", "--check-units", "5", "--check-points", "2000", "--out", str(tmp_path)],
                          cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    result = json.loads(done.stdout)
    assert result["units"] == 200 and result["rules"] > 0 and result["evals_per_s"] > 0
    # The exact centroid against a 2,000-point numerical integration: within its discretisation.
    assert 0 <= result["centroid_max_rel_error"] < 1e-3
    # pyfuzzylite samples its centroid (1,000 points by default): the two agree to that resolution.
    assert result["pyfuzzylite_evals_per_s"] > 0 and result["pyfuzzylite_max_abs_diff"] < 1e-2
    assert fuzzy_engine.format_table(result) in (tmp_path / "fuzzy.md").read_text()
