"""A job's threads per agent (`submit -t`, JobInfo.threads) and an agent's host (Register.host): the agent
renders on the job's threads, never more than its own, its estimates scaled to them; the report says the
threads each unit rendered on, as Dr.Jit had them; `quekaro agents` shows each agent's host and threads."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest
from test_agent_state import Agent, Params, job, unit

from agents.render_agent import host_name
from core.model import messages as m
from farm.local import LocalFarm

REPO = Path(__file__).resolve().parent.parent
CBOX = REPO / "scenes" / "cbox.xml"


def test_an_agent_renders_on_the_jobs_threads_at_most_its_own() -> None:
    agent = Agent()
    agent.state.threads = 4
    assert agent.state.threads_for(job()) == 4  # the job names none: the agent's own
    assert agent.state.threads_for(replace(job(), threads=2)) == 2
    assert agent.state.threads_for(replace(job(), threads=16)) == 4  # never more than it was started with


def test_fewer_threads_are_estimated_as_slower_in_proportion() -> None:
    agent = Agent()
    agent.state.threads = 4
    p = Params(6, 16, 2)
    own = agent.state.base_estimate(unit(0), p, job())
    assert agent.state.base_estimate(unit(0), p, replace(job(), threads=1)) == pytest.approx(4 * own)
    assert agent.state.base_estimate(unit(0), p, replace(job(), threads=8)) == pytest.approx(own)


@pytest.mark.parametrize("threads", [0, 4097, True, 1.5])
def test_a_jobs_threads_outside_the_schema_are_refused(threads) -> None:
    performative, body = m.encode(m.CallForProposal(conversation="c", job=job(), units=(unit(0),),
                                                    reply_within_s=1.0))
    data = json.loads(body)
    data["job"]["threads"] = threads
    with pytest.raises(m.MessageError, match="threads"):
        m.parse(performative, json.dumps(data))


def test_a_host_name_is_what_register_may_carry() -> None:
    name = host_name()
    assert name is None or m.Register(conversation="r", speed=1.0, threads=1, rules="x", host=name).host == name
    with pytest.raises(m.MessageError, match="host"):
        m.encode(m.Register(conversation="r", speed=1.0, threads=1, rules="x", host="a b"))


@pytest.mark.slow
def test_submit_t_renders_each_unit_on_the_jobs_threads(tmp_path: Path) -> None:
    with LocalFarm(tmp_path / "home", agents=1, threads=2) as farm:
        farm.wait_for_agents()
        used = {}
        for name, extra in (("own", []), ("one", ["-t", "1"]), ("many", ["-t", "64"])):
            done = subprocess.run(
                [sys.executable, "-m", "quekaro", "submit", str(CBOX), "-D", "res=32", "-D", "spp=2", "--units",
                 "2", "--opt", "S", *extra, "--wait", "-o", str(tmp_path / f"{name}.exr"), "--home", str(farm.home)],
                capture_output=True, text=True, timeout=300)
            assert done.returncode == 0, done.stderr
            report = json.loads((tmp_path / f"{name}.json").read_text())
            used[name] = {u["threads"] for u in report["units"]}
        assert used == {"own": {2}, "one": {1}, "many": {2}}
        agents = subprocess.run([sys.executable, "-m", "quekaro", "agents", "--json", "--home", str(farm.home)],
                                capture_output=True, text=True, timeout=60, check=True)
        (row,) = json.loads(agents.stdout)
        assert (row["host"], row["threads"]) == (host_name(), 2)
