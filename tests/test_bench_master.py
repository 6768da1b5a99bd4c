"""bench.master_load: the simulated farm's rows, the auction's CPU and the projection to 1024 agents."""

from __future__ import annotations

import json
import math

import pytest

from bench import master_load as ml
from bench.commands import main


def test_costs_sum_to_the_work_of_the_farm() -> None:
    costs = ml.job_costs(16, 150.0, seed=3)
    assert len(costs) == 16 * 3 + 8 and math.isclose(sum(costs), 16 * 150.0)
    assert min(costs) > 0 and max(costs) / min(costs) > 2  # log-normal: units differ


def test_the_projection_follows_the_power_law_through_the_largest_runs() -> None:
    rows = [{"agents": n, "passes": True, "master_cores": 0.01 * (n / 8) ** 2} for n in (8, 16, 32)]
    rows.append({"agents": 64, "passes": False, "master_cores": 99.0})  # whole units: not used
    assert math.isclose(ml.project_cores(rows, 1024), 0.01 * 128 ** 2)
    assert ml.project_cores(rows[:1], 1024) is None


@pytest.mark.slow
def test_the_command_writes_rows_whole_and_in_passes_with_the_masters_cpu(tmp_path, capsys) -> None:
    out = tmp_path / "master.md"
    assert main(["master", "--agents", "4,8", "--per-agent-s", "20", "--out", str(out)]) == 0
    result = json.loads(out.with_suffix(".json").read_text())
    assert [(r["agents"], r["passes"]) for r in result["rows"]] == [(4, False), (4, True), (8, False), (8, True)]
    for row in result["rows"]:
        assert 0 < row["efficiency"] <= 1.0 + 1e-9 and row["master_cpu_s"] > 0
        assert math.isclose(row["master_cores"], row["master_cpu_s"] / row["makespan_s"])
    assert result["projected_cores"] is not None
    text = out.read_text()
    assert "quekaro bench master" in text and "| 8 | 32 | in passes |" in text and "projects" in text
    assert "target at 1024 agents" in capsys.readouterr().out
