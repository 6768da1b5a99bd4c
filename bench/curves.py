"""The README's figure (`python -m bench.curves`, run by `make docs-figures`): per scene, relMSE against wall
time for uniform spp and each rule level rendered whole, in passes and adaptive, in one process and on a
2-agent farm. It reads the `quekaro bench accuracy --suite` reports' CSVs (`RUNS`); it renders nothing.
Each run measured its own uniform-spp renders; the figure pools them and draws their power-law fit.
"""

from __future__ import annotations

import csv
import sys
from pathlib import Path
from typing import NamedTuple

import numpy as np
from matplotlib.figure import Figure

from bench.images import write_plot
from core.model.levels import LEVELS

BENCHMARKS = Path(__file__).resolve().parent.parent / "docs" / "benchmarks"
FIGURE = BENCHMARKS / "curves.png"
COLUMNS = 3


class Run(NamedTuple):
    """One accuracy report: where it ran, how its jobs rendered, its CSV (relative to BENCHMARKS)."""

    where: str
    mode: str
    csv: str


RUNS = (
    Run("one process", "whole units", "inprocess/accuracy.csv"),
    Run("one process", "in passes", "inprocess-progressive/accuracy.csv"),
    Run("one process", "adaptive", "inprocess-adaptive/accuracy.csv"),
    Run("2-agent farm", "whole units", "accuracy.csv"),
    Run("2-agent farm", "in passes", "farm-progressive/accuracy.csv"),
    Run("2-agent farm", "adaptive", "farm-adaptive/accuracy.csv"),
)
STYLE = {"whole units": ("o", "C0"), "in passes": ("^", "C1"), "adaptive": ("D", "C2")}


class Point(NamedTuple):
    level: str
    seconds: float
    relmse: float


def read_cells(path: Path) -> list[dict[str, str]]:
    """The raw (not denoised) cells of one report's CSV; SystemExit naming the file when it is missing."""
    if not path.is_file():
        raise SystemExit(f"{path}: no such report (run its `quekaro bench accuracy --suite`)")
    with path.open(newline="") as fh:
        return [row for row in csv.DictReader(fh) if row.get("denoise", "False") != "True"]


def level_points(cells: list[dict[str, str]], scene: str) -> list[Point]:
    """A scene's rule levels at wall time, in LEVELS' order."""
    points = [Point(c["level"], float(c["seconds"]), float(c["relmse"])) for c in cells if c["scene"] == scene]
    return sorted(points, key=lambda p: LEVELS.index(p.level))


def uniform_points(cells: list[dict[str, str]], scene: str) -> list[tuple[float, float]]:
    """A scene's plain-Mitsuba renders at uniform spp (wall time, relMSE): at each cell's wall time and at
    its render time."""
    return [(float(c[f"{p}_seconds"]), float(c[f"{p}_relmse"])) for c in cells if c["scene"] == scene
            for p in ("uniform", "render_uniform") if c.get(f"{p}_seconds")]


def power_fit(points: list[tuple[float, float]]) -> tuple[float, float]:
    """(a, b) of relMSE = a * seconds^b, least squares in log-log; b is about -1 where a job's fixed
    time is small."""
    x, y = np.log([p[0] for p in points]), np.log([p[1] for p in points])
    b, log_a = np.polyfit(x, y, 1)
    return float(np.exp(log_a)), float(b)


def draw(runs: tuple[Run, ...] = RUNS, root: Path = BENCHMARKS, path: Path = FIGURE) -> bool:
    """The figure at `path`: the scenes in rows of COLUMNS panels, first in one process, then on the farm.
    True when the image there changed."""
    cells = {run: read_cells(root / run.csv) for run in runs}
    places = list(dict.fromkeys(run.where for run in runs))
    scenes = list(dict.fromkeys(c["scene"] for run in runs for c in cells[run]))
    panels = [(where, scene) for where in places for scene in scenes]
    rows = -(-len(panels) // COLUMNS)
    fig = Figure(figsize=(3.3 * COLUMNS, 2.5 * rows), dpi=100)
    for k, (where, scene) in enumerate(panels):
        ax = fig.add_subplot(rows, COLUMNS, k + 1)
        panel(ax, [run for run in runs if run.where == where], cells, scene)
        ax.set_title(f"{scene}, {where}", fontsize=9)
        if k == 0:
            ax.legend(fontsize=6, loc="lower left")
    fig.tight_layout()
    return write_plot(path, fig)


def panel(ax: object, runs: list[Run], cells: dict[Run, list[dict[str, str]]], scene: str) -> None:
    """One scene at one place: every run's levels, and uniform spp's pooled renders with their fit."""
    uniform = [p for run in runs for p in uniform_points(cells[run], scene)]
    ax.plot(*zip(*uniform, strict=True), "s", color="grey", ms=3, alpha=0.6, label="uniform spp (plain)")
    a, b = power_fit(uniform)
    xs = np.linspace(min(p[0] for p in uniform), max(p[0] for p in uniform), 50)
    ax.plot(xs, a * xs ** b, "--", color="grey", lw=1, label="uniform, fit")
    for run in runs:
        points = level_points(cells[run], scene)
        marker, colour = STYLE[run.mode]
        ax.plot([p.seconds for p in points], [p.relmse for p in points], marker + "-", color=colour, ms=3, lw=0.8,
                label=f"levels, {run.mode}")
        for p in points:
            ax.annotate(p.level, (p.seconds, p.relmse), fontsize=6, color=colour)
    ax.set_yscale("log")
    ax.set_xlabel("wall seconds", fontsize=7)
    ax.set_ylabel("relMSE", fontsize=7)
    ax.tick_params(labelsize=6)
    ax.grid(alpha=0.3)


def main() -> int:
    changed = draw()
    print(f"{FIGURE}: {'written' if changed else 'unchanged'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
