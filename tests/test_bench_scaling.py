"""The scaling benchmark at its smallest size: real unit timings, the real auction simulated, its JSON."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from bench import scaling as bench_scaling
from core.errors import QuekaroError
from core.model.geometry import Rect

REPO = Path(__file__).resolve().parent.parent

pytestmark = pytest.mark.slow  # a pre-pass and ~20 real unit renders


def small_args(tmp_path) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    bench_scaling.add_arguments(parser)
    args = parser.parse_args(["--res", "128", "--spp", "64", "--agents-max", "4", "--cell", "32",
                              "--measure-spp", "4", "--units", "4", "--repeats", "1", "--threads", "1",
                              "--out", str(tmp_path)])
    args.json = True
    return args


def test_scaling_json_has_rows_with_sane_efficiencies(tmp_path):
    result = bench_scaling.run(small_args(tmp_path))
    rows = result["rows"]
    assert [(r["speeds"], r["agents"]) for r in rows] == [
        (s, n) for s in ("equal", "mixed") for n in (1, 2, 4)]
    for r in rows:
        for key in ("efficiency", "naive_efficiency", "equal_efficiency", "auction_efficiency"):
            assert 0.05 < r[key] <= 1.2, (key, r)
        assert r["makespan_s"] > 0 and r["units"] >= 1 and r["target_units"] >= 4
    equal = [r for r in rows if r["speeds"] == "equal"]
    # More agents must finish sooner, and one agent on one tile is the baseline itself.
    assert equal[0]["makespan_s"] > equal[1]["makespan_s"] >= equal[2]["makespan_s"]
    assert equal[0]["naive_efficiency"] == pytest.approx(1.0, abs=0.2)
    assert result["measured"]["cells"] == 16 and result["t1_s"] > 0
    assert {t["agents"] for t in result["targets"]} == set()  # N=8 and 32 were not simulated
    png, full = Image.open(tmp_path / "scaling.png"), Image.open(tmp_path / "full-size" / "scaling.png")
    assert (png.mode, png.size) == ("P", (600, 360)) and full.size == (1200, 720)  # 8-bit at 100 dpi; 200 dpi
    assert "| equal | 4 |" in (tmp_path / "scaling.md").read_text()


def test_agent_counts_and_mixed_speeds():
    assert bench_scaling.agent_counts(64) == [1, 2, 4, 8, 16, 32, 64]
    assert bench_scaling.agent_counts(5) == [1, 2, 4]
    assert bench_scaling.speeds_for(5, mixed=True) == [1.0, 0.5, 1.5, 2.0, 1.0]
    assert bench_scaling.speeds_for(3, mixed=False) == [1.0, 1.0, 1.0]


def test_cell_times_spread_by_cost_and_a_timeless_map_is_refused():
    cells = [Rect(0, 0, 2, 2), Rect(2, 0, 2, 2)]
    cost = np.array([[1.0, 3.0, 1.0, 1.0], [0.0, 0.0, 1.0, 1.0]])
    per_sample = bench_scaling.spread_cell_times(cells, [0.5, 0.1], fixed=0.1, spp=4, cost=cost)
    assert per_sample[:, :2].sum() == pytest.approx((0.5 - 0.1) / 4)  # the cell's time above the fixed cost
    assert per_sample[0, 1] == pytest.approx(3 * per_sample[0, 0])  # in proportion to the pre-pass cost
    assert per_sample[:, 2:].sum() == 0.0  # as fast as a 1-spp render: nothing per sample
    with pytest.raises(QuekaroError, match="--measure-spp"):
        bench_scaling.spread_cell_times(cells, [0.1, 0.09], fixed=0.1, spp=4, cost=cost)


def test_cells_are_timed_in_the_variant_a_job_of_the_scene_renders_in(tmp_path):
    """A spectral scene's cells are timed spectral (as its jobs render), and cached apart from rgb."""
    cbox = REPO.parent / "shared" / "scenes" / "mitsuba-data" / "cbox" / "cbox.xml"
    tmap, _, cached = bench_scaling.measure_cached(cbox, 32, 16, 64, 1, tmp_path)
    assert not cached and tmap.info["variant"] == "llvm_ad_spectral"
    assert [p.name.endswith("-llvm_ad_spectral.npz") for p in tmp_path.glob("scaling-*.npz")] == [True]
    again, _, cached = bench_scaling.measure_cached(cbox, 32, 16, 64, 1, tmp_path)
    assert cached and again.info["variant"] == "llvm_ad_spectral"
