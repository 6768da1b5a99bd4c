"""`quekaro bench first-tile`: a job's first tile on the page after its first award, end to end on a small
farm (its figures printed, not asserted against the target), and its summary's arithmetic."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import pytest

from bench.first_tile import PAGE, POLL, TARGET_S, Run, format_report, summary

REPO = Path(__file__).resolve().parent.parent


def args_of(**kw: object) -> argparse.Namespace:
    base = {"scene": Path("cbox.xml"), "res": 64, "spp": 16, "level": "off", "units": 4, "agents": 2,
            "threads": 1, "poll": 0.1}
    return argparse.Namespace(**{**base, **kw})


def a_run(round_: int, mode: str, watch: str, shown: float | None, tile: float = 0.5) -> Run:
    return Run(round_, mode, watch, f"job-{round_}-{mode}-{watch}", 0.1, tile, shown, 4 if mode == "passes" else 1,
               0.2, 0.05, tile - 0.1)


def test_the_summary_takes_the_steady_rounds_and_judges_the_pages_figure():
    runs = [a_run(1, mode, watch, 9.0) for mode in ("whole", "passes") for watch in (POLL, PAGE)]  # start-up
    runs += [a_run(r, "whole", w, s) for r, w, s in ((2, POLL, 0.8), (3, POLL, 1.0), (2, PAGE, 1.5), (3, PAGE, 1.7))]
    runs += [a_run(r, "passes", w, s) for r, w, s in ((2, POLL, 1.9), (3, POLL, None), (2, PAGE, 2.5), (3, PAGE, 2.7))]
    result = summary(args_of(), runs)
    assert result["steady_rounds"] == [2, 3] and result["target_s"] == TARGET_S
    assert result["medians"]["whole poll"]["shown_s"] == pytest.approx(0.9)
    assert result["medians"]["whole page"]["shown_s"] == pytest.approx(1.6)
    assert result["medians"]["passes poll"]["shown_s"] == pytest.approx(1.9)  # a job never seen counts for nothing
    assert result["meets_target"] == {"whole": True, "passes": False}
    text = format_report(args_of(), result)
    assert "whole  page 1.60 s (met)" in text and "passes page 2.60 s (missed)" in text, text
    assert ("4 unit(s) of 1 spp (a budget's first pass, its smallest, alone in its call), rendered 0.40 s "
            "(predicted 0.20 s") in text
    assert "1 unit(s) of 16 spp, rendered 0.40 s" in text and "page shows it 1.10 s later" in text, text
    assert len(text.splitlines()) == 2 + 2 + len(runs) + 2 + 2 * 2


@pytest.mark.slow
def test_bench_first_tile_runs_both_jobs_both_ways_and_prints_its_figures(tmp_path):
    cmd = [sys.executable, "-m", "quekaro", "bench", "first-tile", "--res", "64", "--spp", "16", "--units", "4",
           "--rounds", "1", "--json", "--out", str(tmp_path / "out")]
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads(done.stdout[done.stdout.index("\n{") + 1:])
    runs = result["runs"]
    assert sorted((r["mode"], r["watch"]) for r in runs) == sorted(
        (m, w) for m in ("whole", "passes") for w in (POLL, PAGE))
    for r in runs:
        assert r["award_s"] >= 0 and r["tile_s"] > 0 and r["call_units"] >= 1 and r["call_render_s"] > 0, r
        assert r["shown_s"] is None or r["shown_s"] >= r["tile_s"], r  # no preview shows a tile not yet recorded
    assert any(r["shown_s"] is not None for r in runs)
    assert set(result["meets_target"]) == {"whole", "passes"}
    text = (tmp_path / "out" / "first-tile.md").read_text()
    assert text.startswith("# First tile on the page (`quekaro bench first-tile --res 64")
    assert "Target: the first tile on the page within 2 s" in text and all(r["job_id"] in text for r in runs)
    assert len(result["load"]) == 2 and " Load average " in text
    assert (tmp_path / "out" / "first-tile.provenance.json").is_file()
