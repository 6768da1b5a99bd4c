"""`quekaro bench adaptive` end to end on two small suite scenes (one process each, as for the suite)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent


@pytest.mark.slow
def test_bench_adaptive_measures_each_scene_at_equal_time(tmp_path):
    cmd = [sys.executable, "-m", "quekaro", "bench", "adaptive", "outdoor", "volume", "--res", "32", "--spp", "8",
           "--ref-spp", "64", "--seeds", "1", "--threads", "1", "--cache-dir", str(tmp_path / "cache"),
           "--out", str(tmp_path / "out"), "--json"]
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    result = json.loads(done.stdout)
    assert set(result["scenes"]) == {"outdoor", "volume"}
    for scene in result["scenes"].values():
        (run,) = scene["runs"]
        assert run["equal_spp"] >= 1 and run["adaptive_s"] > 0 and run["uniform_s"] > 0
        assert run["relmse_adaptive"] > 0 and run["relmse_equal"] > 0
        assert run["ratio_equal_time"] == pytest.approx(run["relmse_adaptive"] / run["relmse_equal"])
    text = (tmp_path / "out" / "adaptive.md").read_text()
    assert text.startswith("# The two-pass adaptive render against uniform spp (`quekaro bench adaptive`)")
    assert "| outdoor | report |" in text and "Median relMSE / uniform at equal render time" in text


@pytest.mark.slow
def test_bench_adaptive_takes_scene_files_outside_the_suite(tmp_path):
    files = [REPO / "core" / "data" / "scenes" / f"{n}.xml" for n in ("caustic-corner", "glass-corner")]
    cmd = [sys.executable, "-m", "quekaro", "bench", "adaptive", *map(str, files), "--res", "24", "--spp", "8",
           "--ref-spp", "32", "--seeds", "1", "--threads", "1", "--cache-dir", str(tmp_path / "cache"),
           "--out", str(tmp_path / "out"), "--json"]
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    scenes = json.loads(done.stdout)["scenes"]
    assert set(scenes) == {"caustic-corner", "glass-corner"}
    assert all(s["role"] == "report" and s["runs"][0]["relmse_adaptive"] > 0 for s in scenes.values())
