"""`quekaro bench farm`: the alternation of its sides, its ratios, and one tiny real run."""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from bench import farm as bench_farm

REPO = Path(__file__).resolve().parent.parent


def test_sides_alternate_after_one_warm_up_each() -> None:
    calls: list[str] = []

    def side(name: str, seconds: float):
        def measure() -> float:
            calls.append(name)
            return seconds + len(calls)
        return measure

    times = bench_farm.alternate({"a": side("a", 10.0), "b": side("b", 20.0)}, repeats=3)
    assert calls == ["a", "b"] + ["a", "b"] * 3  # warm-ups are not in the results
    assert times == {"a": [13.0, 15.0, 17.0], "b": [24.0, 26.0, 28.0]}


def test_ratios_use_each_sides_fastest_run() -> None:
    args = argparse.Namespace(scene=Path("s.xml"), res=8, spp=1, level="off", units=1, threads=2, repeats=2)
    r = bench_farm._result(args, {"render": [30.0, 20.0], "farm": [21.0, 40.0]},
                           {"one": [50.0, 40.0], "two": [25.0, 30.0], "passes": [29.0, 26.0]})
    assert r["overhead_ratio"] == pytest.approx(21.0 / 20.0)
    assert r["speedup_2_agents"] == pytest.approx(40.0 / 25.0)
    assert r["overhead_ratio_median"] == pytest.approx(30.5 / 25.0)
    assert r["passes_ratio"] == pytest.approx(26.0 / 25.0)
    assert r["passes_ratio_median"] == pytest.approx(27.5 / 27.5)
    assert "MISS" in bench_farm.format_report(r) and "PASS" in bench_farm.format_report(r)


@pytest.mark.slow
def test_tiny_real_run_prints_json_with_the_issues_keys(tmp_path: Path) -> None:
    out = subprocess.run([sys.executable, "-m", "quekaro", "bench", "farm", "--json", "--res", "32", "--spp", "2",
                          "--units", "4", "--repeats", "1", "--out", str(tmp_path)], cwd=REPO, capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    result = json.loads(out.stdout)
    for key in ("overhead_ratio", "speedup_2_agents", "passes_ratio"):
        assert math.isfinite(result[key]) and result[key] > 0
    assert all(len(v) == 1 and v[0] > 0 for v in result["runs"].values())
    assert bench_farm.format_report(result) in (tmp_path / "farm.md").read_text()
