"""A progressive job in the master's real auction (bench.simulate drives it under a simulated clock): its
passes are auctioned as units, and idle agents take extra passes of the units slower agents hold."""

from __future__ import annotations

import dataclasses
import random

import pytest
from auction_support import register, tick, tile
from test_auction import ONE_A_ROUND, bid_all, events, info, round_trip, sends, specs

from bench.simulate import simulate
from core.image.passes import WEIGHT
from core.model import messages as m
from core.model.status import JobStatus
from master import auction as au
from master.web.logs import unit_lines
from planning.progressive import TIME, Goal

SPEEDS = [1.5, 0.5, 1.25, 0.75]  # bench.hosts' mixed speeds


def work_done(result, speeds) -> float:
    """What the agents rendered, in seconds at speed 1 (extra passes included)."""
    return sum(result.busy_s[f"agent{i}"] * s for i, s in enumerate(speeds))


def test_passes_remove_the_tail_that_whole_units_leave_on_mixed_speeds():
    """Eight equal units on four agents of mixed speeds: whole units end 20 % after the ideal (the
    capacity's time); the same job in passes ends within 1 % of it, for at most a tenth more work."""
    costs = [10.0] * 8
    ideal = sum(costs) / sum(SPEEDS)
    whole = simulate(costs, SPEEDS, latency=0.001)
    passes = simulate(costs, SPEEDS, latency=0.001, passes=True)
    assert whole.makespan > 1.15 * ideal
    assert passes.makespan < 1.01 * ideal, (passes.makespan, ideal)
    assert sum(costs) - 1e-6 <= work_done(passes, SPEEDS) <= 1.1 * sum(costs)


@pytest.mark.parametrize("agents", [1, 3, 16])
def test_a_job_in_passes_renders_its_samples_once_on_alike_agents(agents):
    costs = [3.0 + (i % 5) for i in range(24)]
    result = simulate(costs, [1.0] * agents, latency=0.002, passes=True)
    assert result.makespan >= sum(costs) / agents - 1e-6  # no agent renders faster than its speed
    # with equal agents few passes need a copy: the work done is the job's, and at most 10 % more
    assert sum(costs) - 1e-6 <= work_done(result, [1.0] * agents) <= 1.1 * sum(costs)


def test_a_time_goal_counts_its_seconds_from_its_first_award_not_its_submission():
    """A job queued while no agent could take it (a sequence's later frame behind the earlier ones): its
    2 s of rendering start at its first award, 100 s after it was submitted. Counted from the submission,
    its first merged passes ended it at once ("the 2 s of rendering are spent"), with a few spp a unit."""
    a = au.Auction(ONE_A_ROUND, rng=random.Random(3))
    job = dataclasses.replace(info(), passes=True, level="off")
    a.handle(au.JobSubmitted(job, specs([1.0, 2.0]), goal=Goal(TIME, 64, seconds=2.0)), 0.0)
    register(a, "A", 100.0)
    now, out = 100.0, []
    while now < 101.0 and not events(out, au.PassesSettled):
        for award in round_trip(a, now).values():
            unit = award.message.unit
            out += tile(a, award.message, 0.01, now + 0.01, channels=("R", "G", "B", WEIGHT), depth=8, spp=unit.spp)
            out += a.handle(au.PassMerged(job.job_id, unit.index, unit.spp, 0.01, 0.5 / unit.spp), now + 0.02)
            a.validate()
        now += 0.05
    assert not events(out, au.PassesSettled), events(out, au.PassesSettled)
    assert a.job_status(job.job_id) == JobStatus.RUNNING


def test_a_passs_records_name_its_unit_and_pass_as_the_user_knows_them(tmp_path):
    """A progressive job's unit rows are passes (row = pass x units + unit): the log's sentences say "unit 1,
    pass 0", never the row's index, and the page's lines of one unit (master.web.logs.unit_lines) hold
    every pass of it and none of another unit."""
    a = au.Auction(ONE_A_ROUND, rng=random.Random(3))
    job = dataclasses.replace(info(), passes=True, level="off")
    a.handle(au.JobSubmitted(job, specs([1.0, 2.0]), goal=Goal(TIME, 64, seconds=2.0)), 0.0)
    register(a, "A", 0.0)
    bid_all(a, sends(tick(a, 0.0), m.CallForProposal), 0.0)
    awarded = events(tick(a, 0.0), au.UnitAwarded)
    assert awarded
    for record in awarded:
        unit, pass_index = record.index % 2, record.index // 2
        assert record.sentence().startswith(f"unit {unit}, pass {pass_index} of job {job.job_id}: awarded to A")
    (tmp_path / "logs").mkdir()
    lines = ["unit 1, pass 0 of job j: awarded", "unit 1, pass 3 of job j: done", "unit 11, pass 0 of job j: x",
             "unit 1 of job j: whole", "unit 1, pass 2 of job jj: other job"]
    (tmp_path / "logs" / "master.log").write_text("\n".join(lines) + "\n")
    assert unit_lines(tmp_path, "j", 1) == lines[:2] + lines[3:4]
