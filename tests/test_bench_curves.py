"""`bench.curves`: the README's figure is drawn from the accuracy reports' own numbers, every report it
names is committed, and a missing report is named."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from bench import curves


def test_every_report_the_figure_reads_is_committed_and_covers_the_suite() -> None:
    scenes = None
    for run in curves.RUNS:
        cells = curves.read_cells(curves.BENCHMARKS / run.csv)
        found = {c["scene"] for c in cells}
        assert scenes is None or found == scenes, run.csv
        scenes = found
        for scene in found:
            assert [p.level for p in curves.level_points(cells, scene)][-1] == "VB", (run.csv, scene)
            assert len(curves.uniform_points(cells, scene)) >= 2 * 5, (run.csv, scene)
    assert len(scenes) == 6


def test_the_points_are_the_csvs_and_the_fit_is_a_power_law(tmp_path: Path) -> None:
    run = curves.RUNS[0]
    with (curves.BENCHMARKS / run.csv).open(newline="") as fh:
        row = next(r for r in csv.DictReader(fh) if r["scene"] == "cbox" and r["level"] == "S")
    [point] = [p for p in curves.level_points(curves.read_cells(curves.BENCHMARKS / run.csv), "cbox") if p.level == "S"]
    assert (point.seconds, point.relmse) == (float(row["seconds"]), float(row["relmse"]))
    a, b = curves.power_fit([(1.0, 8.0), (2.0, 4.0), (4.0, 2.0)])
    assert a == pytest.approx(8.0) and b == pytest.approx(-1.0)


def test_the_figure_is_drawn_and_a_missing_report_is_named(tmp_path: Path) -> None:
    assert curves.draw(path=tmp_path / "curves.png")
    assert (tmp_path / "curves.png").stat().st_size < 100_000  # tests/test_repo_budget.py: an image
    assert not curves.draw(path=tmp_path / "curves.png")  # the same numbers: unchanged
    missing = curves.Run("one process", "whole units", "nowhere/accuracy.csv")
    with pytest.raises(SystemExit, match=r"nowhere/accuracy\.csv: no such report"):
        curves.draw((missing,), path=tmp_path / "other.png")
