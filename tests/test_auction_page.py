"""What the page asks of the auction, as typed stimuli into the pure machine: drain an agent (no new award; it
finishes what it holds) and resume it, and render a done unit again (its job, done or running, runs again).
Each refusal is an ignored record saying why; the machine's invariants hold after every stimulus."""

from __future__ import annotations

import random
from collections import Counter

from auction_support import register, submit, tick
from test_auction import ONE_A_ROUND, awards, bid_all, events, info, inform, informed, round_trip, sends, specs

from core.model import messages as m
from core.model.status import JobStatus
from master import auction as au


def make(costs: list[float], agents: list[str]) -> au.Auction:
    a = au.Auction(ONE_A_ROUND, rng=random.Random(3))
    submit(a, info(), specs(costs))
    for name in agents:
        register(a, name, 0.0)
    return a


def handle(a: au.Auction, stimulus: au.Stimulus, now: float = 0.0) -> list[au.Instruction]:
    out = a.handle(stimulus, now)
    a.validate()
    return out


def reasons(out: list[au.Instruction]) -> list[str]:
    return [e.reason for e in events(out, au.MessageIgnored)]


def test_a_drained_agent_is_called_to_no_auction_and_resumed_it_is_again() -> None:
    a = make([1.0, 2.0, 3.0], ["A", "B"])
    assert events(handle(a, au.AgentDrainRequested("A")), au.AgentDrained) == [au.AgentDrained("A", 0)]
    assert [v.draining for v in a.agent_views(0.0)] == [True, False]
    assert {s.to for s in sends(tick(a, 0.0), m.CallForProposal)} == {"B"}
    assert events(handle(a, au.AgentResumeRequested("A")), au.AgentResumed) == [au.AgentResumed("A")]
    a.validate()
    assert "A" in {s.to for s in sends(tick(a, 5.0), m.CallForProposal)}


def test_a_drained_agent_finishes_what_it_holds_and_wins_nothing_in_a_round_it_was_called_to() -> None:
    a = make([1.0, 2.0, 3.0, 4.0], ["A", "B"])
    calls = sends(tick(a, 0.0), m.CallForProposal)  # a round A is called to, still open
    assert {c.to for c in calls} == {"A", "B"}
    assert events(handle(a, au.AgentDrainRequested("A")), au.AgentDrained) == [au.AgentDrained("A", 0)]
    bid_all(a, calls, 0.0)
    assert {s.to for s in awards(tick(a, 0.0)).values()} == {"B"}  # A bid, but is awarded nothing
    a.validate()

    b = make([1.0, 2.0, 3.0, 4.0], ["A", "B"])
    held = next(s for s in round_trip(b, 0.0).values() if s.to == "A")
    assert events(handle(b, au.AgentDrainRequested("A")), au.AgentDrained) == [au.AgentDrained("A", 1)]
    done = informed(b, "A", inform(held, 1.0), 1.0)  # the unit it held it still delivers
    assert events(done, au.UnitDone)[0].agent == "A"
    assert "A" not in {s.to for s in sends(tick(b, 2.0), m.CallForProposal)}
    b.validate()


def test_drain_and_resume_say_why_they_change_nothing() -> None:
    a = make([1.0], ["A"])
    assert reasons(handle(a, au.AgentDrainRequested("nobody@localhost"))) == ["no agent nobody@localhost is known"]
    assert reasons(handle(a, au.AgentResumeRequested("A"))) == ["agent A is not draining"]
    handle(a, au.AgentDrainRequested("A"))
    assert reasons(handle(a, au.AgentDrainRequested("A"))) == ["agent A is already draining"]


def test_a_done_unit_retried_goes_back_to_the_auction_and_its_done_job_runs_again() -> None:
    a = make([1.0, 2.0], ["A"])
    for _ in range(2):
        for award in round_trip(a, 0.0).values():
            informed(a, award.to, inform(award, 1.0), 1.0)
    assert a.job_status("job-1") == JobStatus.DONE
    out = handle(a, au.UnitRetryRequested("job-1", 0, stimulus_id="retry-1"), 2.0)
    assert events(out) == [au.UnitRetried("job-1", 0, "asked by the user")]
    assert a.job_status("job-1") == JobStatus.RUNNING and a.counts("job-1") == Counter(done=1, pending=1)
    assert a.story("job-1", 0)[-1].stimulus_id == "retry-1"
    [again] = round_trip(a, 3.0).values()
    assert again.message.unit.index == 0
    finished = informed(a, again.to, inform(again, 1.0), 4.0)
    assert events(finished, au.JobDone) and a.counts("job-1") == Counter(done=2)


def test_a_retry_of_a_unit_not_done_or_of_no_unit_is_refused_saying_why() -> None:
    a = make([1.0, 2.0], ["A"])
    assert reasons(handle(a, au.UnitRetryRequested("job-1", 0))) == [
        "the unit is pending and its job running: only a done unit is retried"]
    assert reasons(handle(a, au.UnitRetryRequested("job-1", 9))) == ["no such unit in a job the master auctions"]
    assert reasons(handle(a, au.UnitRetryRequested("job-2", 0))) == ["no such unit in a job the master auctions"]
    [award] = [s for s in round_trip(a, 0.0).values() if s.message.unit.index == 1]
    informed(a, award.to, inform(award, 1.0), 1.0)
    handle(a, au.JobCancelRequested("job-1"))
    assert a.counts("job-1") == Counter(done=1, failed=1)
    assert reasons(handle(a, au.UnitRetryRequested("job-1", 1))) == [
        "the unit is done and its job cancelled: only a done unit is retried"]
