"""What the page asks of the auction, as typed stimuli into the pure machine: drain an agent (no new award; it
finishes what it holds) and resume it, render a done unit again (its job, done or running, runs again), and
requeue a failed or cancelled job (its done units kept, the rest auctioned again, its failures forgiven; one
the auction does not know taken up from the store; one in passes going on from its passes). Each refusal is an
ignored record saying why; the machine's invariants hold after every stimulus."""

from __future__ import annotations

import dataclasses
import random
from collections import Counter

from auction_support import message, register, submit, tick, tile
from test_auction import (
    ONE_A_ROUND,
    awards,
    bid_all,
    events,
    failure,
    info,
    inform,
    informed,
    round_trip,
    sends,
    specs,
)

from core.image.passes import WEIGHT
from core.model import messages as m
from core.model.status import JobStatus
from master import auction as au
from planning.progressive import BUDGET, TIME, Goal


def make(costs: list[float], agents: list[str], config: au.Config = ONE_A_ROUND) -> au.Auction:
    a = au.Auction(config, rng=random.Random(3))
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


def finish_all(a: au.Auction, now: float, **tile_kw) -> tuple[list[int], list[au.Instruction]]:
    """Round trips until the job ends, every award's tile stored: the units awarded, in order, and what the
    last tile led to."""
    awarded, out = [], []
    a.__dict__.pop("_test_calls", None)  # calls made before the job ended: their rounds are closed
    while a.job_status("job-1") == JobStatus.RUNNING:
        for award in round_trip(a, now).values():
            awarded.append(award.message.unit.index)
            out = tile(a, award.message, 1.0, now + 0.5, **tile_kw)
            a.validate()
        now += 1.0
    return awarded, out


def cancelled_after(a: au.Auction, done: int) -> list[int]:
    """`done` units rendered, then the job cancelled: the units done."""
    finished = []
    while len(finished) < done:
        for award in list(round_trip(a, 0.0).values())[:done - len(finished)]:
            informed(a, award.to, inform(award, 1.0), 0.5)
            finished.append(award.message.unit.index)
    handle(a, au.JobCancelRequested("job-1"))
    return finished


def test_a_cancelled_job_requeued_keeps_its_done_units_and_auctions_only_the_rest() -> None:
    a = make([1.0, 2.0, 3.0, 4.0], ["A", "B"])
    kept = cancelled_after(a, 2)
    assert a.job_status("job-1") == JobStatus.CANCELLED and a.counts("job-1") == Counter(done=2, failed=2)
    out = handle(a, au.JobRequeueRequested("job-1", stimulus_id="requeue-job-1"), 1.0)
    rest = tuple(sorted({0, 1, 2, 3} - set(kept)))
    assert events(out) == [au.JobRequeued("job-1", rest, 2, "asked by the user")]
    assert a.job_view("job-1").status == "running" and a.job_view("job-1").error == ""
    assert a.counts("job-1") == Counter(done=2, pending=2)
    assert a.story("job-1", rest[0])[-1] == au.Transition("requeue-job-1", "failed", "pending", 1.0)
    awarded, last = finish_all(a, 2.0)
    assert sorted(awarded) == list(rest)  # the units done before the cancel are not rendered again
    assert events(last, au.JobDone) and a.counts("job-1") == Counter(done=4)


def test_a_failed_job_requeued_has_its_failures_forgiven_and_runs_to_its_end() -> None:
    a = make([1.0, 2.0], ["A"], au.Config(slots=2, max_unit_failures=2, blocklist_after=2))
    now, out = 0.0, []
    while not events(out, au.JobFailed):
        award = next(iter(round_trip(a, now).values()))
        out = message(a, award.to, failure(award, "out of memory"), now + 0.5)
        now += 1.0
    assert a.job_view("job-1").blocklist == ("A",) and "out of memory" in a.job_view("job-1").error
    out = handle(a, au.JobRequeueRequested("job-1"), now)
    assert [type(e) for e in events(out)] == [au.JobRequeued] and events(out)[0].count == 2
    assert a.job_view("job-1").blocklist == () and a.job_view("job-1").error == ""
    assert not events(tick(a, now), au.JobFailed)  # the unit that failed it does not fail it again at once
    awarded, last = finish_all(a, now + 1.0)
    assert sorted(awarded) == [0, 1] and events(last, au.JobDone)


def test_a_requeue_of_a_running_done_or_unknown_job_is_refused_saying_why() -> None:
    a = make([1.0], ["A"])
    running = "only a failed or cancelled job is requeued: it is running"
    assert reasons(handle(a, au.JobRequeueRequested("job-1"))) == [running]
    assert reasons(handle(a, au.JobRequeueRequested("job-2"))) == ["no job of that id the master auctions"]
    stranger = au.JobSubmitted(info("job-3"), specs([1.0]))
    assert reasons(handle(a, au.JobRequeueRequested("job-2", stranger))) == ["no job of that id the master auctions"]
    finish_all(a, 0.0)
    assert reasons(handle(a, au.JobRequeueRequested("job-1"))) == [
        "only a failed or cancelled job is requeued: it is done: render one of its units again (retry) instead"]
    assert a.job_status("job-1") == JobStatus.DONE


def test_a_job_the_auction_does_not_know_is_requeued_as_the_store_holds_it() -> None:
    """It ended before this master started: taken up with its done units done and its failures forgiven."""
    a = au.Auction(ONE_A_ROUND, rng=random.Random(3))
    register(a, "A", 0.0)
    store_says = au.JobSubmitted(info(), specs([1.0, 2.0, 3.0]), done=frozenset({1}),
                                 failures=tuple((0, "A", "crash") for _ in range(9)), delivered_by={1: "A"})
    out = handle(a, au.JobRequeueRequested("job-1", store_says, stimulus_id="requeue-job-1"), 1.0)
    assert events(out) == [au.JobRequeued("job-1", (0, 2), 2, "asked by the user")]
    assert a.counts("job-1") == Counter(done=1, pending=2) and a.job_view("job-1").blocklist == ()
    awarded, last = finish_all(a, 2.0)
    assert sorted(awarded) == [0, 2] and events(last, au.JobDone)


def in_passes(goal: Goal) -> au.Auction:
    a = au.Auction(ONE_A_ROUND, rng=random.Random(3))
    a.handle(au.JobSubmitted(dataclasses.replace(info(), passes=True, level="off"), specs([1.0, 2.0]), goal=goal), 0.0)
    register(a, "A", 0.0)
    return a


PASS_TILE = {"channels": ("R", "G", "B", WEIGHT), "depth": 8}  # what the job in passes takes of a pass (info())


def test_a_cancelled_job_in_passes_requeued_goes_on_from_its_passes() -> None:
    """Its machine still waits for the passes its cancel stopped: back to pending, they are what it renders."""
    a = in_passes(Goal(BUDGET, 4))
    ordered = a.counts("job-1")["pending"]
    first = next(iter(round_trip(a, 0.0).values()))
    tile(a, first.message, 1.0, 0.5, **PASS_TILE)
    handle(a, au.JobCancelRequested("job-1"))
    assert a.counts("job-1") == Counter(done=1, failed=ordered - 1)
    out = handle(a, au.JobRequeueRequested("job-1"), 1.0)
    assert events(out)[0].count == ordered - 1 and a.counts("job-1") == Counter(done=1, pending=ordered - 1)
    awarded, last = finish_all(a, 2.0, **PASS_TILE)
    assert first.message.unit.index not in awarded and len(awarded) == ordered - 1
    assert [type(e) for e in events(last)][-2:] == [au.PassesSettled, au.JobDone]


def test_a_job_with_a_time_goal_is_not_requeued() -> None:
    a = in_passes(Goal(TIME, 64, seconds=10.0))
    handle(a, au.JobCancelRequested("job-1"))
    assert reasons(handle(a, au.JobRequeueRequested("job-1"))) == [
        "a job with a time goal spends its seconds from its first pass: submit it again instead"]
    assert a.job_status("job-1") == JobStatus.CANCELLED


def test_the_look_ahead_counts_on_no_drained_agent() -> None:
    """A drained agent takes no new unit: a unit projected to it would never be offered to the others."""
    a = make([4.0, 1.0], ["A", "B"])
    handle(a, au.AgentDrainRequested("A"))
    assert {p.agent for p in a.projection("job-1", 0.0).values()} == {"B"}
    awarded, last = finish_all(a, 0.0)
    assert sorted(awarded) == [0, 1] and events(last, au.JobDone)


def test_a_slow_pass_that_an_idle_agents_extra_pass_stood_in_for_is_withdrawn_and_its_tile_ignored() -> None:
    """B holds a pass and goes quiet; A, idle, renders an extra pass of that unit. When A's lands the unit
    has its budget: B's pass is withdrawn (B told to stop), the job ends, and B's late tile adds nothing."""
    a = in_passes(Goal(BUDGET, 4))
    register(a, "B", 0.0)
    slow, now, out, landed = None, 0.0, [], Counter[int]()
    while a.job_status("job-1") == JobStatus.RUNNING and now < 40:
        for award in round_trip(a, now).values():
            if slow is None and award.to == "B":
                slow = award
                continue
            out += tile(a, award.message, 1.0, now + 0.5, **PASS_TILE)
            landed[au.pass_origin(award.message.unit.index, a.job_passes("job-1"))[0]] += award.message.unit.spp
            a.validate()
        now += 1.0
    assert slow is not None and a.job_status("job-1") == JobStatus.DONE
    [withdrawn] = events(out, au.PassesWithdrawn)
    assert withdrawn.units == (slow.message.unit.index,)
    assert any(isinstance(i, au.SendToAgent) and i.to == "B" and isinstance(i.message, m.Cancel)
               and i.message.index == slow.message.unit.index for i in out)
    late = tile(a, slow.message, 9.0, now, **PASS_TILE)
    assert [type(i) for i in late] == [au.MessageIgnored]
    assert landed == Counter({0: 4, 1: 4})  # the tiles kept: each unit has its budget, no more
