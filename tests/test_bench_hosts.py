"""`quekaro bench hosts` end to end at its smallest: the embedded XMPP server, the master and two emulated
agent processes, one job, against the simulator's prediction; `--json` prints the result alone."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from bench import hosts

REPO = Path(__file__).resolve().parent.parent


@pytest.mark.slow
@pytest.mark.alone  # the benchmark waits for idle CPUs before it submits (up to 3 minutes)
@pytest.mark.parametrize("progressive", [False, True], ids=["whole", "passes"])
def test_two_emulated_agents_finish_a_job_and_json_is_the_whole_stdout(tmp_path: Path, progressive: bool) -> None:
    costs, out = tmp_path / "costs.json", tmp_path / "hosts.md"
    done = subprocess.run([sys.executable, "-m", "quekaro", "bench", "hosts", "--json", "--agents", "2",
                           "--t1", "4", "--costs", str(costs), "--out", str(out),
                           *(["--progressive"] if progressive else [])],
                          cwd=REPO, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    result = json.loads(done.stdout)  # progress went to stderr
    assert "2 emulated agents" in done.stderr and costs.is_file()  # the missing cost map was measured
    (row,) = result["rows"]
    assert row["agents"] == 2 and row["units"] >= 2 and row["tiles"] >= row["units"]
    assert row["report_units"] == row["report_emulated_units"] == row["units"]  # every tile emulated
    assert 0 < row["efficiency"] <= 1.0 + 1e-9 and row["makespan_s"] > 0 and row["sim_makespan_s"] > 0
    # The simulator without latencies bounds it with them (their seeds' tie-breaks aside).
    assert row["sim_efficiency"] <= row["sim_instant_efficiency"] * 1.02 <= 1.02 + 1e-9
    assert row["heavy_modules"] == []  # an emulated agent loads no Mitsuba or Dr.Jit
    assert 0 < row["busy_during"] <= 1 and all(row["cpu_s"][k] > 0 for k in ("master", "server", "agents"))
    # In passes at level off the units draw samples on their own pixels (their bands spill): the samples
    # they draw cost T1 and each render call's fixed cost, no band (the bound is within 5 % of 1).
    assert row["spill"] == progressive
    bound = result["t1_s"] / row["units_seconds"]
    assert (0.95 < bound <= 1.0) if progressive else bound < 0.97, bound  # bands of 2 px sampled
    assert hosts.format_report(result) in out.read_text()
