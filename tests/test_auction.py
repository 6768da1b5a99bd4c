"""The auction state machine: awards, credits, timeouts, failures, ignored results, typed events, simulated
clock (`bench.simulate`)."""

from __future__ import annotations

import dataclasses
import itertools
import random
from collections import Counter
from typing import TypeVar

import pytest
from auction_support import cancel, informed, message, register, stored, submit, tick, uploadable
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bench.simulate import simulate
from core.model import messages as m
from core.model.geometry import Rect
from core.model.status import JobStatus, UnitStatus
from core.model.units import WorkUnit
from master import auction as au

HASH = "cd" * 32


def info(job_id: str = "job-1") -> m.JobInfo:
    return m.JobInfo(
        job_id=job_id,
        scene_url="http://127.0.0.1:8765/scene",
        scene_hash=HASH,
        width=64,
        height=64,
        spp=16,
        depth=8,
        level="S",
        ranges={"C": (0.0, 1.0)},
    )


def specs(costs: list[float]) -> list[WorkUnit]:
    return [
        WorkUnit(index=i, rect=Rect(0, 0, 8, 8), C=c, S=64, Nd=0.0, cost=c) for i, c in enumerate(costs)
    ]


def sends(cmds: list[au.Instruction], kind: type | None = None, to: str | None = None) -> list[au.SendToAgent]:
    out = [c for c in cmds if isinstance(c, au.SendToAgent)]
    for c in out:
        m.encode(c.message)  # every message the auction emits must pass the schema
    return [c for c in out if (kind is None or isinstance(c.message, kind)) and (to is None or c.to == to)]


E = TypeVar("E", bound=au.Record)


def events(cmds: list[au.Instruction], kind: type[E] = au.Record) -> list[E]:
    return [c for c in cmds if isinstance(c, kind)]


# One unit a round and a call (2 slots): what most tests here take; units won in batches have their own tests.
ONE_A_ROUND = au.Config(slots=2)


def make(costs: list[float], agents: list[str], config: au.Config | None = None) -> au.Auction:
    a = au.Auction(config or ONE_A_ROUND, rng=random.Random(7))
    if costs:
        submit(a, info(), specs(costs))
    for name in agents:
        register(a, name, 0.0)
    return a


def bid_all(
    a: au.Auction, cmds: list[au.Instruction], now: float, speeds: dict[str, float] | None = None
) -> None:
    """Every called agent proposes its speed x cost on every unit it was offered."""
    for send in sends(cmds, m.CallForProposal):
        speed = (speeds or {}).get(send.to, 1.0)
        est = tuple(m.Estimate(index=u.index, seconds=u.cost / speed) for u in send.message.units)
        out = message(a,
            send.to, m.Propose(conversation=send.message.conversation, job_id=send.message.job.job_id, estimates=est),
            now
        )
        assert out == []


def awards(cmds: list[au.Instruction]) -> dict[int, au.SendToAgent]:
    return {s.message.unit.index: s for s in sends(cmds, m.Award)}


def inform(award: au.SendToAgent, seconds: float) -> m.Inform:
    msg = award.message
    return m.Inform(
        conversation=msg.conversation,
        job_id=msg.job.job_id,
        index=msg.unit.index,
        token=msg.token,
        tile_hash=HASH,
        depth=4,
        spp=8,
        band=2,
        seconds=seconds,
        nonfinite=0,
    )


def failure(award: au.SendToAgent, reason: str = "boom") -> m.Failure:
    msg = award.message
    return m.Failure(
        conversation=msg.conversation,
        job_id=msg.job.job_id,
        index=msg.unit.index,
        token=msg.token,
        reason=reason,
    )


def round_trip(a: au.Auction, now: float, speeds: dict[str, float] | None = None) -> dict[int, au.SendToAgent]:
    """A tick's calls for proposals (and those the last round trip's decision made), every agent bids, a tick
    decides: the awards made. The calls that tick makes wait for the next round trip."""
    bid_all(a, [*a.__dict__.pop("_test_calls", []), *tick(a, now)], now, speeds)
    decided = tick(a, now)
    a.__dict__["_test_calls"] = sends(decided, m.CallForProposal)
    return awards(decided)


def test_happy_path_most_costly_units_first_and_job_done() -> None:
    a = make([1.0, 5.0, 3.0], ["A", "B"])
    cfps = sends(tick(a, 0.0), m.CallForProposal)
    assert {s.to for s in cfps} == {"A", "B"}
    assert [u.index for u in cfps[0].message.units] == [1, 2]  # the two most costly, costliest first
    assert a.counts("job-1") == Counter(announced=2, pending=1)
    bid_all(a, [*cfps], 0.0)
    got = awards(tick(a, 0.0))
    assert sorted(got) == [1, 2] and {s.to for s in got.values()} == {"A", "B"}
    done = []
    for award in got.values():
        done += informed(a, award.to, inform(award, 1.0), 1.0)
    assert len(events(done, au.UnitDone)) == 2 and not events(done, au.JobDone)
    last = round_trip(a, 1.0)
    assert list(last) == [0]
    out = informed(a, last[0].to, inform(last[0], 1.0), 2.0)
    assert events(out, au.JobDone) and a._jobs["job-1"].status == JobStatus.DONE
    assert a.counts("job-1") == Counter(done=3)


def test_events_are_typed_and_keep_tokens_out_of_their_repr() -> None:
    a = make([1.0], ["A"])
    bid_all(a, tick(a, 0.0), 0.0)
    out = tick(a, 0.0)
    award = awards(out)[0]
    token = award.message.token
    deadline = 1.0 * a.config.render_factor + a.config.render_slack_s
    assert events(out) == [au.UnitAwarded("job-1", 0, "A", token, estimate=1.0, attempt=1, deadline=deadline)]
    done = informed(a, "A", inform(award, 1.05), 1.0)
    assert [type(e) for e in done] == [au.UnitDone, au.JobDone]
    ev = done[0]
    assert (ev.token, ev.seconds, ev.tile_hash, ev.credits, ev.on_time) == (token, 1.05, HASH, 1, True)
    assert ev.params == {"depth": 4, "spp": 8, "band": 2, "nonfinite": 0}
    assert token not in repr(events(out)[0]) and token not in repr(ev)


def test_add_job_refuses_done_units_it_does_not_have() -> None:
    with pytest.raises(ValueError, match=r"done units \[7\] unknown"):
        submit(au.Auction(), info(), specs([1.0]), done=[0, 7])


def test_contested_unit_goes_to_best_record_and_others_are_rejected() -> None:
    a = make([2.0], ["A", "B"])
    a._agents["B"].credits = 3
    bid_all(a, tick(a, 0.0), 0.0)
    out = tick(a, 0.0)
    assert awards(out)[0].to == "B"
    assert [s.to for s in sends(out, m.Reject)] == ["A"]


def test_record_ties_go_to_the_lower_estimate() -> None:
    a = make([2.0], ["A", "B"])
    assert round_trip(a, 0.0, {"A": 1.0, "B": 1.5})[0].to == "B"


def test_much_slower_bidder_does_not_get_the_big_unit_despite_its_record() -> None:
    a = make([8.0, 1.0], ["fast", "slow"])
    a._agents["slow"].credits = 5
    got = round_trip(a, 0.0, {"fast": 4.0, "slow": 1.0})
    assert got[0].to == "fast" and got[1].to == "slow"


def test_credits_follow_the_ten_percent_rule() -> None:
    a = make([1.0, 1.0], ["A"])
    first = round_trip(a, 0.0)
    informed(a, "A", inform(first[0], 1.09), 1.1)  # within 10 % of 1.0
    assert a._agents["A"].credits == 1
    second = round_trip(a, 2.0)
    out = informed(a, "A", inform(second[1], 1.2), 3.2)  # 20 % over
    assert a._agents["A"].credits == 0
    assert events(out, au.UnitDone)[0].on_time is False


def test_unanswered_cfp_is_announced_again_after_a_pause_that_doubles_until_the_agent_answers() -> None:
    a = make([1.0], ["A"])
    assert sends(tick(a, 0.0), m.CallForProposal)
    assert tick(a, 1.0) == []  # still waiting for A
    timeout = a.config.cfp_timeout_s
    assert tick(a, timeout) == [au.AgentSilent("A", timeout)]  # nobody bid: the unit is free again
    assert a.counts("job-1") == Counter(pending=1)
    assert tick(a, 2 * timeout - 0.01) == [] and a.next_deadline() == pytest.approx(2 * timeout)
    [cfp] = sends(tick(a, 2 * timeout), m.CallForProposal, to="A")
    assert tick(a, 3 * timeout) == [au.AgentSilent("A", 2 * timeout)]  # silent again: twice the pause
    assert tick(a, 5 * timeout - 0.01) == []
    [cfp] = sends(tick(a, 5 * timeout), m.CallForProposal, to="A")
    message(a, "A", m.Refuse(conversation=cfp.message.conversation, job_id="job-1", reason="busy"), 5 * timeout)
    out = tick(a, 5 * timeout)
    assert events(out) == [] and a._agents["A"].silences == 0  # it answered: no pause
    assert sends(out, m.CallForProposal, to="A")


def test_a_fast_agent_that_never_bids_does_not_keep_the_units_from_the_others() -> None:
    """It registers a thousand times faster than the others, so the look-ahead gives it the units; it
    never answers: after its first silence the others are called to them."""
    a = make([1.0, 1.0], ["honest"])
    register(a, "mute", 0.0, speed=1000.0)
    called = {s.to for s in sends(tick(a, 0.0), m.CallForProposal)}
    assert called == {"mute"}  # projected everything: the honest agent is not called
    assert {s.to for s in sends(tick(a, a.config.cfp_timeout_s), m.CallForProposal)} == {"honest"}
    register(a, "mute", 3.0, speed=1000.0)  # registering again does not end its pause
    assert a._agents["mute"].silent_until is not None


def test_an_agent_back_from_being_lost_is_not_held_to_the_calls_it_missed() -> None:
    a = make([1.0], ["A"])
    tick(a, 0.0)
    tick(a, a.config.cfp_timeout_s)  # its link is down: the call goes unanswered
    assert a._agents["A"].silences == 1
    tick(a, a.config.heartbeat_timeout_s + 1.0)
    assert a._agents["A"].lost
    back = message(a, "A", m.Heartbeat(conversation="h", busy=()), 20.0)
    assert events(back, au.AgentBack) and a._agents["A"].silences == 0 and a._agents["A"].silent_until is None
    assert sends(tick(a, 20.0), m.CallForProposal, to="A")


def test_refusal_resolves_the_round_at_once() -> None:
    a = make([1.0], ["A"])
    cfp = sends(tick(a, 0.0), m.CallForProposal)[0].message
    message(a, "A", m.Refuse(conversation=cfp.conversation, job_id="job-1", reason="busy"), 0.1)
    out = tick(a, 0.1)  # resolved before its deadline: the unit is free, and offered again at once
    assert events(out) == [] and sends(out, m.CallForProposal, to="A")


def test_lost_agent_gives_its_units_to_another() -> None:
    a = make([1.0, 1.0], ["A", "B"])
    got = round_trip(a, 0.0)
    holder_of_0 = got[0].to
    other = "B" if holder_of_0 == "A" else "A"
    informed(a, other, inform(got[1], 1.0), 1.0)
    t = a.config.heartbeat_timeout_s + 0.5
    message(a, other, m.Heartbeat(conversation="h", busy=()), t)
    out = tick(a, t)
    assert [e.agent for e in events(out, au.AgentLost)] == [holder_of_0]
    assert [(e.index, e.reason) for e in events(out, au.UnitRequeued)] == [(0, f"agent {holder_of_0} lost")]
    bid_all(a, out, t)
    again = awards(tick(a, t))
    assert again[0].to == other
    # The lost agent's late tile is harmless: its token is no longer the unit's.
    late = informed(a, holder_of_0, inform(got[0], 1.0), t + 1)
    assert events(late, au.MessageIgnored)[0].reason == "tile: wrong token"
    assert informed(a, other, inform(again[0], 1.0), t + 1)[-1] == au.JobDone("job-1")


def test_an_agent_lost_long_enough_is_forgotten_and_keeps_its_credits_if_it_comes_back() -> None:
    a = make([], ["A", "B"])  # no job: no auction round sets a timer
    a._agents["A"].credits = 3
    lost_at = a.config.heartbeat_timeout_s + 0.5
    message(a, "B", m.Heartbeat(conversation="h", busy=()), lost_at)
    assert [e.agent for e in events(tick(a, lost_at), au.AgentLost)] == ["A"]
    forget_at = a.config.forget_lost_s + 0.5  # A was last seen at 0
    message(a, "B", m.Heartbeat(conversation="h", busy=()), forget_at - 1)
    assert a.next_deadline() == pytest.approx(a.config.forget_lost_s)  # a timer wakes the master for it
    assert events(tick(a, forget_at - 1), au.AgentForgotten) == [] and "A" in a._agents
    assert events(tick(a, forget_at), au.AgentForgotten) == [au.AgentForgotten("A")]
    assert set(a._agents) == {"B"}
    register(a, "A", forget_at + 1)
    assert a._agents["A"].credits == 3 and not a._agents["A"].lost


def test_a_failure_without_blame_requeues_the_unit_and_counts_nothing_against_its_agent() -> None:
    a = make([1.0], ["A", "B"])
    got = round_trip(a, 0.0)
    holder = got[0].to
    failure = m.Failure(conversation=got[0].message.conversation, job_id="job-1", index=0,
                        token=got[0].message.token, reason="No space left on device")
    assert events(a.handle(au.DiskFull(free_bytes=0), 0.5), au.JobsPaused)  # a failure may be the disk's
    out = message(a, holder, failure, 1.0)
    assert [(e.index, e.reason) for e in events(out, au.UnitRequeued)] == [
        (0, f"failed on {holder}, not counted: No space left on device")]
    assert events(out, au.UnitFailed) == [] and a._agents[holder].credits == 0
    unit = a._jobs["job-1"].units[0]
    assert unit.status == UnitStatus.PENDING and unit.failures == 0 and holder not in unit.failed_on


def test_render_deadline_cancels_and_retries_elsewhere() -> None:
    a = make([1.0], ["A", "B"])
    a._agents["A"].credits = 1
    got = round_trip(a, 0.0)
    assert got[0].to == "A"
    deadline = 1.0 * a.config.render_factor + a.config.render_slack_s
    rendering = (m.HeldUnit(job_id="job-1", index=0),)
    assert message(a, "A", m.Heartbeat(conversation="h", busy=rendering), deadline - 1) == []
    message(a, "B", m.Heartbeat(conversation="h", busy=()), deadline - 1)
    out = tick(a, deadline + 0.1)
    assert [s.message.reason for s in sends(out, m.Cancel, to="A")] == ["render deadline passed"]
    assert events(out, au.UnitFailed)[0].agent == "A"
    cfps = sends(out, m.CallForProposal)
    assert [s.to for s in cfps] == ["B"]  # A is not offered the unit it failed


def test_failure_is_retried_on_another_agent_and_blocklists_after_three() -> None:
    a = make([1.0] * 5, ["bad", "good"])
    a._agents["bad"].credits = 100  # it wins every contest until it is blocklisted
    failed_units = []
    now = 0.0
    while not a._jobs["job-1"].blocklist:
        got = round_trip(a, now)
        for index, award in got.items():
            if award.to == "bad":
                out = message(a, "bad", failure(award), now)
                failed_units.append(index)
            else:
                out = informed(a, "good", inform(award, 1.0), now)
        now += 1
    assert len(failed_units) == 3
    assert a._jobs["job-1"].blocklist == {"bad"}
    assert events(out, au.AgentBlocklisted)[0].reason == "3 failed units of this job"
    for _ in range(10):
        got = round_trip(a, now)
        assert all(s.to == "good" for s in got.values())
        for award in got.values():
            out = informed(a, "good", inform(award, 1.0), now)
        now += 1
        if a._jobs["job-1"].status != JobStatus.RUNNING:
            break
    assert a._jobs["job-1"].status == JobStatus.DONE


def test_a_unit_failing_everywhere_goes_to_another_agent_first_and_fails_its_job_with_the_reason() -> None:
    a = make([1.0, 1.0], ["A", "B"])
    got = round_trip(a, 0.0)
    informed(a, got[1].to, inform(got[1], 1.0), 0.5)
    tried, out, now = [], message(a, got[0].to, failure(got[0], "scene crashed"), 0.5), 1.0
    tried.append(got[0].to)
    while not events(out, au.JobFailed):
        retry = round_trip(a, now)
        tried.append(retry[0].to)
        out = message(a, retry[0].to, failure(retry[0], "scene crashed"), now + 0.5)
        now += 1.0
    assert tried[1] != tried[0]  # retried elsewhere first, then where it failed too
    assert len(tried) == a.config.max_unit_failures
    reason = events(out, au.JobFailed)[0].reason
    assert "unit 0 failed 5 times" in reason and "scene crashed" in reason, reason
    assert a._jobs["job-1"].status == JobStatus.FAILED and tick(a, now) == []


def _finish(a: au.Auction, now: float) -> list[tuple[int, str]]:
    """Rounds until the job ends, every award informed; the (unit, agent) of each award."""
    given = []
    while a._jobs["job-1"].status == JobStatus.RUNNING and now < 100.0:
        for index, award in round_trip(a, now).items():
            given.append((index, award.to))
            informed(a, award.to, inform(award, 1.0), now + 0.5)
        now += 1.0
    return given


def test_on_one_agent_a_failed_unit_is_retried_there_and_the_job_completes() -> None:
    """A render killed once (for memory, say) failed the job at once: no other agent to retry it on."""
    a = make([1.0, 1.0], ["A"])
    got = round_trip(a, 0.0)
    (index, award), = got.items()
    out = message(a, "A", failure(award, "render process killed by SIGKILL"), 0.5)
    assert not events(out, au.JobFailed)
    assert (index, "A") in _finish(a, 1.0)
    assert a._jobs["job-1"].status == JobStatus.DONE


def test_a_unit_goes_back_to_where_it_failed_while_the_other_agent_is_lost() -> None:
    a = make([1.0, 1.0, 1.0], ["A", "B"])
    got = round_trip(a, 0.0)
    on_a = next(i for i, s in got.items() if s.to == "A")
    message(a, "A", failure(got[on_a], "killed"), 0.5)
    late = a.config.heartbeat_timeout_s + 1.0
    message(a, "A", m.Heartbeat(conversation="h", busy=()), late - 0.5)
    tick(a, late)  # B, silent past the timeout, is lost: its unit returns to the auction
    assert a._agents["B"].lost and a._jobs["job-1"].status == JobStatus.RUNNING
    assert (on_a, "A") in _finish(a, late)
    assert a._jobs["job-1"].status == JobStatus.DONE


def test_a_unit_goes_back_to_where_it_failed_while_the_other_agent_does_not_answer() -> None:
    """An agent that beats but never bids is live, not usable: the unit waited for it for ever."""
    a = make([1.0], ["A", "B"])
    now = 0.0
    while not a._jobs["job-1"].units[0].failures:
        for send in sends(tick(a, now), m.CallForProposal, to="A"):  # B stays silent
            message(a, "A", m.Propose(conversation=send.message.conversation, job_id="job-1", estimates=tuple(
                m.Estimate(index=u.index, seconds=1.0) for u in send.message.units)), now)
        for award in awards(tick(a, now + a.config.cfp_timeout_s)).values():
            message(a, award.to, failure(award, "killed"), now + 2.5)
        now += 3.0
    given = []
    while a._jobs["job-1"].status == JobStatus.RUNNING and now < 60.0:
        for send in sends(tick(a, now), m.CallForProposal, to="A"):
            message(a, "A", m.Propose(conversation=send.message.conversation, job_id="job-1", estimates=tuple(
                m.Estimate(index=u.index, seconds=1.0) for u in send.message.units)), now)
        for award in awards(tick(a, now + a.config.cfp_timeout_s)).values():
            given.append(award.to)
            informed(a, award.to, inform(award, 1.0), now + 2.5)
        now += 3.0
    assert a._agents["B"].silences >= 1 and given == ["A"]  # B was called, never answered, and left out
    assert a._jobs["job-1"].status == JobStatus.DONE


def test_a_job_fails_when_every_agent_is_blocklisted_for_it() -> None:
    a = make([1.0] * 4, ["A"])
    now, out = 0.0, []
    while not events(out, au.JobFailed):
        for award in round_trip(a, now).values():
            out += message(a, "A", failure(award, "scene crashed"), now + 0.5)
        now += 1.0
    reason = events(out, au.JobFailed)[0].reason
    assert a._jobs["job-1"].blocklist == {"A"} and "every agent is blocklisted for the job: A" in reason, reason


def test_no_agents_at_all_is_waiting_not_failing() -> None:
    a = make([1.0], [])
    assert tick(a, 1000.0) == [] and a._jobs["job-1"].status == JobStatus.RUNNING


def test_duplicate_forged_and_late_results_are_ignored() -> None:
    a = make([1.0, 1.0], ["A", "B"])
    got = round_trip(a, 0.0)
    award = got[0]
    intruder = "B" if award.to == "A" else "A"
    good = inform(award, 1.0)
    forged = dataclasses.replace(good, token="f" * 32)
    # A tile counts by its token alone (the data plane's check), for the award's holder; a message also by
    # its sender and conversation.
    checks = [
        (informed(a, award.to, forged, 0.5), "tile: wrong token"),
        (message(a, intruder, failure(award), 0.5), "unit not awarded to this agent"),
        (informed(a, award.to, dataclasses.replace(good, job_id="nope"), 0.5), "tile: unknown job or unit"),
        (message(a, award.to, dataclasses.replace(failure(award), conversation="x"), 0.5), "wrong conversation id"),
        (message(a, award.to, dataclasses.replace(failure(award), token="f" * 32), 0.5), "wrong token"),
    ]
    for out, reason in checks:
        assert [e.reason for e in events(out, au.MessageIgnored)] == [reason]
    assert events(informed(a, award.to, inform(award, 1.0), 1.0), au.UnitDone)
    again = informed(a, award.to, inform(award, 1.0), 1.1)
    assert [e.reason for e in again] == ["tile: unit already done"]
    assert a.counts("job-1")["done"] == 1


def test_proposals_outside_the_auction_are_ignored() -> None:
    a = au.Auction(ONE_A_ROUND, rng=random.Random(7))
    submit(a, info("other"), specs([1.0]))
    register(a, "B", 0.0)
    assert [s.to for s in round_trip(a, 0.0).values()] == ["B"]  # busy with the other job's unit: not called
    submit(a, info(), specs([1.0]))
    register(a, "A", 0.0)
    cfp = sends(tick(a, 0.0), m.CallForProposal)[0].message
    est = (m.Estimate(index=0, seconds=1.0),)
    assert events(
        message(a, "B", m.Propose(conversation=cfp.conversation, job_id="job-1", estimates=est), 0)
    )
    assert events(message(a, "A", m.Propose(conversation="unknown", job_id="job-1", estimates=est), 0))
    assert message(a, "A", m.Propose(conversation=cfp.conversation, job_id="job-1", estimates=est), 0) == []
    repeat = message(a, "A", m.Propose(conversation=cfp.conversation, job_id="job-1", estimates=est), 0)
    assert events(repeat)[0].reason == "already answered this auction"


def test_heartbeat_reconciles_lost_awards_and_stale_work() -> None:
    a = make([1.0], ["A"])
    got = round_trip(a, 0.0)
    assert message(a, "A", m.Heartbeat(conversation="h", busy=()), 1.0) == []  # within the grace
    out = message(a, "A", m.Heartbeat(conversation="h", busy=()), a.config.award_grace_s + 1)
    assert events(out, au.UnitRequeued)[0].reason == "award not acknowledged by the agent"
    assert not uploadable(a, "job-1", 0, got[0].message.token)
    stale = message(a,
        "A", m.Heartbeat(conversation="h", busy=(m.HeldUnit(job_id="job-1", index=0),)), 20
    )
    assert [s.message.index for s in sends(stale, m.Cancel, to="A")] == [0]


def test_a_heartbeat_that_crossed_its_own_delivery_cancels_nothing() -> None:
    """An agent lists a unit as busy until its upload's answer comes; a heartbeat sent just before the
    tile landed arrives after it. Cancelling then would make the agent drop its own delivered unit (no
    Inform, no timing learned); another agent still on the done unit is stopped."""
    a = make([1.0], ["A", "B"])
    got = round_trip(a, 0.0)
    winner = got[0].to
    other = "B" if winner == "A" else "A"
    assert events(informed(a, winner, inform(got[0], 0.5), 1.0), au.UnitDone)
    held = (m.HeldUnit(job_id="job-1", index=0),)
    assert sends(message(a, winner, m.Heartbeat(conversation="h", busy=held), 1.1), m.Cancel) == []
    stale = message(a, other, m.Heartbeat(conversation="h", busy=held), 1.2)
    assert [s.message.index for s in sends(stale, m.Cancel, to=other)] == [0]


def test_upload_allowed_only_for_the_current_token() -> None:
    a = make([1.0], ["A"])
    got = round_trip(a, 0.0)
    token = got[0].message.token
    assert len(token) == 32 and uploadable(a, "job-1", 0, token)
    assert not uploadable(a, "job-1", 0, "0" * 32)
    assert not uploadable(a, "job-1", 1, token) and not uploadable(a, "nope", 0, token)


def test_cancel_job_stops_its_agents() -> None:
    a = make([1.0, 1.0], ["A", "B"])
    round_trip(a, 0.0)
    out = cancel(a, "job-1")
    assert {s.to for s in sends(out, m.Cancel)} == {"A", "B"}
    assert a.counts("job-1") == Counter(failed=2)
    assert all(not s.holding for s in a._agents.values())
    assert events(cancel(a, "job-1"), au.MessageIgnored)


def test_resumed_job_keeps_done_units_and_past_failures() -> None:
    a = au.Auction(au.Config(blocklist_after=2), rng=random.Random(1))
    submit(a, info(), specs([1.0, 1.0, 1.0]), done=[0], failures=[(1, "X", "crash"), (2, "X", "crash")])
    register(a, "X", 0.0)
    register(a, "Y", 0.0)
    assert a._jobs["job-1"].blocklist == {"X"}
    assert {s.to for s in sends(tick(a, 0.0), m.CallForProposal)} == {"Y"}


def test_tokens_and_conversations_are_unique_and_seeded() -> None:
    def tokens(seed: int) -> list[str]:
        a = au.Auction(rng=random.Random(seed))
        submit(a, info(), specs([1.0] * 20))
        for i in range(20):
            register(a, f"a{i}", 0.0)
        return [s.message.token for s in round_trip(a, 0.0).values()]

    assert tokens(3) == tokens(3) and len(set(tokens(3))) == 20 and tokens(3) != tokens(4)


# --- random event sequences: no unit is ever lost or done twice ---------------------------------------------

ops = st.lists(
    st.tuples(
        st.sampled_from(["tick", "bid", "refuse", "inform", "inform-late", "fail", "beat", "silence", "dup"]),
        st.integers(0, 3),  # which agent
        st.floats(0.0, 20.0),  # time step
    ),
    max_size=60,
)


def check_invariants(a: au.Auction) -> None:
    holders: Counter[tuple[str, int]] = Counter()
    for agent in a._agents.values():
        holders.update(agent.holding)
    for job in a._jobs.values():
        for unit in job.units.values():
            key = (job.info.job_id, unit.spec.index)
            if unit.status == UnitStatus.AWARDED:
                assert holders[key] == 1 and key in a._agents[unit.agent].holding
            else:
                assert holders[key] == 0
            if job.status == JobStatus.RUNNING:
                assert unit.status != UnitStatus.FAILED
    for agent in a._agents.values():
        assert len(agent.holding) <= a.config.slots
        for rates in (agent.rates, agent.late_rates):
            assert set(rates) <= set(a._jobs) and all(0 < r < float("inf") for r in rates.values())
    # Safety of the look-ahead: every open unit is projected to some agent that may take it, if one exists.
    now = max((ag.last_seen for ag in a._agents.values()), default=0.0)
    for job in a._jobs.values():
        if job.status != JobStatus.RUNNING:
            continue
        plan = a.projection(job.info.job_id, now)
        live = {ag.name for ag in a._agents.values() if not ag.lost and ag.silent_until is None} - job.blocklist
        for unit in job.units.values():
            if unit.status in (UnitStatus.PENDING, UnitStatus.ANNOUNCED) and live - unit.failed_on:
                assert plan[unit.spec.index].agent in live - unit.failed_on


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(ops, st.integers(1, 8), st.integers(1, 2))
def test_random_event_sequences_never_lose_a_unit(sequence, n_units: int, slots: int) -> None:
    a = make([float(1 + i % 3) for i in range(n_units)], [f"a{i}" for i in range(4)], au.Config(slots=slots))
    now, outstanding, done_events = 0.0, [], Counter()
    pending_cfps: list[au.SendToAgent] = []
    old_awards: list[au.SendToAgent] = []

    def feed(cmds: list[au.Instruction]) -> None:
        pending_cfps.extend(sends(cmds, m.CallForProposal))
        outstanding.extend(sends(cmds, m.Award))
        done_events.update(e.index for e in events(cmds, au.UnitDone))

    for op, who, step in sequence:
        now += step
        name = f"a{who}"
        if op == "tick":
            feed(tick(a, now))
        elif op in ("bid", "refuse") and pending_cfps:
            cfp = pending_cfps.pop(0)
            if op == "bid":
                est = tuple(m.Estimate(index=u.index, seconds=u.cost) for u in cfp.message.units)
                msg = m.Propose(conversation=cfp.message.conversation, job_id="job-1", estimates=est)
                feed(message(a, cfp.to, msg, now))
            else:
                feed(
                    message(a,
                        cfp.to,
                        m.Refuse(conversation=cfp.message.conversation, job_id="job-1", reason="no"),
                        now,
                    )
                )
        elif op in ("inform", "fail", "dup") and outstanding:
            award = outstanding.pop(0) if op != "dup" else outstanding[0]
            old_awards.append(award)
            msg = failure(award) if op == "fail" else inform(award, step)
            feed((message if op == "fail" else informed)(a, award.to, msg, now))
        elif op == "inform-late" and old_awards:
            award = old_awards[who % len(old_awards)]
            feed(informed(a, award.to, inform(award, step), now))
        elif op == "beat":
            busy = tuple(m.HeldUnit(job_id=j, index=i) for j, i in sorted(a._agents[name].holding))
            feed(message(a, name, m.Heartbeat(conversation="h", busy=busy), now))
        check_invariants(a)
    assert all(n == 1 for n in done_events.values())  # no unit done twice
    job = a._jobs["job-1"]
    done = {i for i, u in job.units.items() if u.status == UnitStatus.DONE}
    assert done == set(done_events)
    # Liveness: with one reliable agent from now on, the job ends (done, or failed with a reason).
    helper = "reliable"
    register(a, helper, now)
    for _ in range(4 * n_units + 10):
        if job.status != JobStatus.RUNNING:
            break
        now += a.config.heartbeat_timeout_s + a.config.render_slack_s + 100
        message(a, helper, m.Heartbeat(conversation="h", busy=()), now)
        cmds = tick(a, now)
        bid_all(a, [s for s in sends(cmds, m.CallForProposal) if s.to == helper], now)
        for award in awards(tick(a, now)).values():
            informed(a, award.to, inform(award, award.message.estimate_s), now)
        check_invariants(a)
    assert job.status != JobStatus.RUNNING
    assert job.status == JobStatus.DONE or job.error


# --- the simulated clock ------------------------------------------------------------------------------------


def test_simulated_single_agent_makespan_is_the_sum_of_costs() -> None:
    costs = [random.Random(1).uniform(0.5, 3.0) for _ in range(40)]
    result = simulate(costs, [1.0], latency=0.002)
    assert sum(costs) <= result.makespan <= sum(costs) * 1.01
    assert result.busy_s == {"agent0": pytest.approx(sum(costs))}


def test_simulated_equal_agents_are_efficient_with_many_similar_units() -> None:
    rng = random.Random(2)
    costs = [rng.uniform(0.9, 1.1) for _ in range(400)]
    t1 = sum(costs)
    for n in (2, 8):
        result = simulate(costs, [1.0] * n, latency=0.002, jitter=0.05)
        efficiency = t1 / (n * result.makespan)
        assert efficiency >= 0.9, (n, efficiency)


def test_simulated_mixed_speeds_give_fast_agents_more_work() -> None:
    costs = [1.0] * 200
    result = simulate(costs, [2.0, 1.0, 1.0, 0.5], latency=0.002)
    ideal = 200 / 4.5
    assert result.makespan <= ideal * 1.1
    assert result.busy_s["agent0"] > 0 and result.busy_s["agent3"] > 0


def test_simulate_needs_units_and_agents() -> None:
    with pytest.raises(ValueError):
        simulate([], [1.0])


# --- the earliest-finish-time look-ahead --------------------------------------------------------------------


def test_project_places_each_unit_where_it_finishes_first() -> None:
    agents = [au.PlanAgent("fast", 1.0, 0.5), au.PlanAgent("slow", 0.0, 2.0)]
    units = [au.ProjectedUnit(0, 10.0), au.ProjectedUnit(1, 1.0), au.ProjectedUnit(2, 1.0, frozenset({"slow"}))]
    plan = au.project(units, agents)
    assert plan[0] == au.Placement("fast", 1.0, 6.0)  # 6 s on fast, against 20 s on slow now
    assert plan[1] == au.Placement("slow", 0.0, 2.0)  # fast would end it at 6.5
    assert plan[2] == au.Placement("fast", 6.0, 6.5)  # it failed on slow
    assert au.project([au.ProjectedUnit(0, 1.0, frozenset({"fast", "slow"}))], agents) == {}


def test_refine_recovers_what_list_scheduling_misses() -> None:
    units = [au.ProjectedUnit(i, c) for i, c in enumerate([3.0, 3.0, 2.0, 2.0, 2.0])]
    agents = [au.PlanAgent("a", 0.0, 1.0), au.PlanAgent("b", 0.0, 1.0)]
    lpt = au.project(units, agents)
    assert max(p.finish for p in lpt.values()) == 7.0  # 3+2+2 against 3+2
    better = au.refine(lpt, units, agents)
    assert max(p.finish for p in better.values()) == 6.0 == au.fluid_finish([12.0], agents)
    assert sorted(better) == [0, 1, 2, 3, 4]
    for name in ("a", "b"):  # each agent's units back to back, most costly first
        mine = sorted((p for p in better.values() if p.agent == name), key=lambda p: p.start)
        assert mine[0].start == 0.0 and all(x.finish == y.start for x, y in itertools.pairwise(mine))


def two_jobs_fast_agent_busy(big_job_costs: list[float]) -> au.Auction:
    """'fast' (speed 4) renders job-0's unit of cost 4 from t=0 to t=1; job-1 waits; 'slow' (speed 1) is free."""
    a = au.Auction(rng=random.Random(3))
    submit(a, info("job-0"), specs([4.0]))
    register(a, "fast", 0.0, speed=4.0)
    cfp = sends(tick(a, 0.0), m.CallForProposal, to="fast")[0].message
    bid = m.Propose(conversation=cfp.conversation, job_id="job-0", estimates=(m.Estimate(index=0, seconds=1.0),))
    assert message(a, "fast", bid, 0.0) == []
    assert awards(tick(a, 0.0))[0].to == "fast"
    submit(a, info("job-1"), specs(big_job_costs))
    register(a, "slow", 0.0, speed=1.0)
    return a


def test_end_game_free_slow_agent_leaves_the_big_unit_to_a_fast_agent_about_to_be_free() -> None:
    a = two_jobs_fast_agent_busy([10.0])
    assert a.projection("job-1", 0.5)[0] == au.Placement("fast", 1.0, 3.5)  # 10.5 on slow
    assert sends(tick(a, 0.5), m.CallForProposal) == []  # slow is not called: it would be the tail
    # The slow agent gets a small unit that it finishes before the fast one would.
    a = two_jobs_fast_agent_busy([10.0, 1.0])
    cfps = sends(tick(a, 0.5), m.CallForProposal)
    assert [(s.to, [u.index for u in s.message.units]) for s in cfps] == [("slow", [1])]
    bid_all(a, cfps, 0.5)
    assert {i: s.to for i, s in awards(tick(a, 0.5)).items()} == {1: "slow"}


def test_fast_agent_freeing_up_takes_the_unit_held_for_it() -> None:
    a = two_jobs_fast_agent_busy([10.0])
    award = next(iter(a._jobs["job-0"].units.values()))
    msg = m.Inform(conversation=award.conversation, job_id="job-0", index=0, token=award.token, tile_hash=HASH,
                   depth=4, spp=8, band=2, seconds=1.0, nonfinite=0)
    out = informed(a, "fast", msg, 1.0) + tick(a, 1.0)
    assert [(s.to, [u.index for u in s.message.units]) for s in sends(out, m.CallForProposal)] == [("fast", [0])]


def test_lost_fast_agent_releases_its_projected_units() -> None:
    a = two_jobs_fast_agent_busy([10.0])
    assert tick(a, 0.5) == []
    t = a.config.heartbeat_timeout_s + 0.5
    message(a, "slow", m.Heartbeat(conversation="h", busy=()), t)
    out = tick(a, t)
    assert [e.agent for e in events(out, au.AgentLost)] == ["fast"]
    assert a.projection("job-1", t)[0].agent == "slow"
    # The lost agent's own unit (job-0, submitted first) is offered first; once slow refuses it, job-1's.
    cfp = sends(out, m.CallForProposal, to="slow")[0].message
    assert cfp.job.job_id == "job-0"
    message(a, "slow", m.Refuse(conversation=cfp.conversation, job_id="job-0", reason="no"), t)
    again = sends(tick(a, t), m.CallForProposal, to="slow")
    assert [(s.message.job.job_id, [u.index for u in s.message.units]) for s in again] == [("job-0", [0])]


def test_blocklisted_agent_gets_no_projected_units() -> None:
    a = make([5.0, 1.0], ["fast", "slow"])
    a._agents["fast"].speed = 10.0
    a._jobs["job-1"].blocklist.add("fast")  # as its failures would have made it
    a._jobs["job-1"].failures_by_agent["fast"] = a.config.blocklist_after
    assert {p.agent for p in a.projection("job-1", 0.0).values()} == {"slow"}
    assert {s.to for s in sends(tick(a, 0.0), m.CallForProposal)} == {"slow"}


def test_rates_are_learnt_from_bids_and_clamped() -> None:
    a = make([4.0, 2.0], ["A", "C"])
    cfps = {s.to: s.message for s in sends(tick(a, 0.0), m.CallForProposal)}
    register(a, "B", 0.0, speed=2.0)  # after the call: it only watches
    assert a.rate("A", "job-1") == 1.0 and a.rate("B", "job-1") == 0.5  # before any bid: 1 / speed
    assert [u.index for u in cfps["A"].units] == [0, 1] and [u.index for u in cfps["C"].units] == [0, 1]

    def propose(name: str, seconds: list[float]) -> None:
        est = tuple(m.Estimate(index=i, seconds=s) for i, s in enumerate(seconds))
        message(a, name, m.Propose(conversation=cfps[name].conversation, job_id="job-1", estimates=est), 0.0)

    propose("A", [8.0, 4.0])
    assert a.rate("A", "job-1") == 2.0
    assert a.rate("B", "job-1") == 1.0  # speed 2 against A's speed 1 x rate 2
    propose("C", [0.0, 0.0])  # absurd: clamped to a hundredth of the others' median rate
    assert a.rate("C", "job-1") == pytest.approx(2.0 / a.config.rate_clamp)
    got = awards(tick(a, 0.0))
    assert got[0].to == "C" and got[0].message.estimate_s == 0.0
    # It took 4 s on a unit of cost 4: projected at the rate it showed until it is on time again.
    informed(a, "C", inform(got[0], 4.0), 4.0)
    assert a.rate("C", "job-1") == 1.0


def test_equal_speeds_call_every_free_agent_on_the_costliest_units() -> None:
    a = make([1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0], ["A", "B", "C"])
    cfps = sends(tick(a, 0.0), m.CallForProposal)
    assert sorted(s.to for s in cfps) == ["A", "B", "C"]
    for s in cfps:  # each is offered the three costliest: all three agents contest them
        assert [u.index for u in s.message.units] == [6, 5, 4]


def test_simulated_mixed_speeds_end_near_the_lower_bound() -> None:
    costs = [12.0, 9.0, 8.0, 6.0, 5.0, 5.0, 4.0, 3.0, 3.0, 2.0, 2.0, 1.0, 1.0, 1.0]
    speeds = [2.0, 1.0, 0.5, 0.5]
    bound = max(sum(costs) / sum(speeds), max(costs) / max(speeds))
    result = simulate(costs, speeds, latency=0.002)
    assert result.makespan <= bound * 1.06, (result.makespan, bound)
    # Greedy awards without the look-ahead give a big unit to a slow agent (its 12 / 0.5 alone is 24 s).
    assert max(result.busy_s["agent2"], result.busy_s["agent3"]) <= bound * 1.06


def test_a_second_slot_awards_the_next_unit_while_one_renders() -> None:
    a = make([4.0, 3.0, 2.0], ["A"], au.Config(slots=2, queue_above=0))
    first = round_trip(a, 0.0)
    assert list(first) == [0]  # one unit per round
    second = round_trip(a, 0.5)  # still rendering unit 0: called again, for the next unit
    assert list(second) == [1]
    assert len(a._agents["A"].holding) == 2
    assert round_trip(a, 1.0) == {}  # both slots taken: not called
    unit = a._jobs["job-1"].units[1]
    # The queued unit starts when unit 0 should end (4 s), so its deadline counts from there.
    assert unit.deadline == pytest.approx(4.0 + 3.0 * a.config.render_factor + a.config.render_slack_s)
    assert a._available(a._agents["A"], 1.0) == pytest.approx(7.0)
def test_a_free_slot_does_not_win_over_an_idle_agent_that_finishes_sooner() -> None:
    a = make([4.0, 3.0, 3.0], ["A", "B"], au.Config(slots=2, queue_above=0))
    first = round_trip(a, 0.0)
    assert sorted(first) == [0, 1]
    informed(a, first[1].to, inform(first[1], 3.0), 3.0)
    idle = first[1].to
    # The idle agent finishes unit 2 at 6 s; the busy one would start it at 4 s and end at 7 s.
    assert {s.to for s in round_trip(a, 3.0).values()} == {idle}


def test_slots_hide_the_message_latency_in_the_simulation() -> None:
    costs = [1.0] * 12
    one = simulate(costs, [1.0], latency=0.2, config=au.Config(slots=1)).makespan
    two = simulate(costs, [1.0], latency=0.2, config=au.Config(slots=2, queue_above=0)).makespan
    assert two < one - 12 * 0.2  # one slot waits ~2 latencies a unit (inform, then CFP/award)
    assert two < 12.0 + 10 * 0.2  # the end game runs one unit at a time (no queueing), a few latencies


def test_slots_hide_the_tile_delivery_in_the_simulation() -> None:
    costs = [1.0] * 12
    one = simulate(costs, [1.0], latency=0.001, delivery=0.1, config=au.Config(slots=1)).makespan
    two = simulate(costs, [1.0], latency=0.001, delivery=0.1).makespan  # the default: 2 slots
    assert one >= 12 * 1.1  # each upload holds the agent's next render back
    # Queued while 4 or more units are open (Config.queue_above): 8 of the 12 deliveries overlap a render.
    assert two <= one - 8 * 0.1 + 0.05


def test_no_unit_is_queued_behind_another_in_the_end_game() -> None:
    a = make([6.0, 5.0, 4.0, 3.0, 2.0, 1.0], ["A"])  # defaults: 2 slots, queue_above 4
    first, second = round_trip(a, 0.0), round_trip(a, 0.1)
    assert list(first) == [0] and list(second) == [1]  # five open units for one agent: queue one
    assert round_trip(a, 0.2) == {}  # both slots taken
    informed(a, "A", inform(first[0], 6.0), 6.0)
    third = round_trip(a, 6.0)  # four open: still worth queueing one
    assert list(third) == [2]
    informed(a, "A", inform(second[1], 5.0), 11.0)
    assert round_trip(a, 11.0) == {}  # three open: the end game, nothing is queued behind unit 2
    informed(a, "A", inform(third[2], 4.0), 15.0)
    assert list(round_trip(a, 15.0)) == [3]


def test_an_adaptive_jobs_units_are_scheduled_by_their_share_of_samples() -> None:
    # cost is at 1 spp; a unit given 8x the samples of a costlier one is the job's biggest unit, and its
    # agent's rate is learnt per unit of work (seconds per cost x spp), not per cost.
    a = au.Auction(ONE_A_ROUND, rng=random.Random(7))
    units = [dataclasses.replace(u, spp=spp) for u, spp in zip(specs([4.0, 1.0, 1.0]), [8, 64, 8], strict=True)]
    submit(a, dataclasses.replace(info(), first_spp=4), units)
    register(a, "A", 0.0)
    register(a, "B", 0.0)
    cfps = sends(tick(a, 0.0), m.CallForProposal)
    assert [u.index for u in cfps[0].message.units] == [1, 0]  # work 64, 32, 8
    for send in cfps:
        est = tuple(m.Estimate(index=u.index, seconds=u.work / 100) for u in send.message.units)
        message(a, send.to, m.Propose(conversation=send.message.conversation, job_id="job-1", estimates=est), 0.0)
    assert a.rate("A", "job-1") == pytest.approx(0.01, rel=0.01)
    got = awards(tick(a, 0.0))
    assert sorted(got) == [0, 1]


def test_an_agent_known_from_heartbeats_only_is_asked_to_register_until_it_does() -> None:
    # A restarted master hears a heartbeat before any Register: the agent is live at speed 1.0, and asked.
    a = make([1.0], [])
    beat = m.Heartbeat(conversation="hb-1", busy=())
    out = message(a, "A", beat, 0.0)
    assert events(out, au.AgentJoined) == [au.AgentJoined("A", 1.0)] and a._agents["A"].speed == 1.0
    assert [type(s.message) for s in sends(out, to="A")] == [m.Introduce]
    assert sends(message(a, "A", beat, 2.0), m.Introduce, to="A")  # its Register may be lost: asked again
    reg = m.Register(conversation="register-s-1", speed=4.0, threads=2, rules="r.xml")
    message(a, "A", reg, 3.0)
    assert a._agents["A"].speed == 4.0 and not sends(message(a, "A", beat, 4.0), m.Introduce)
    message(a, "B", reg, 5.0)  # registered first: never asked
    assert not sends(message(a, "B", beat, 6.0), m.Introduce)


def test_every_register_is_answered_with_a_welcome_of_its_conversation() -> None:
    a = make([1.0], [])
    reg = m.Register(conversation="register-s-1", speed=2.0, threads=1, rules="r.xml")
    out = message(a, "A", reg, 0.0)
    assert events(out, au.AgentJoined) == [au.AgentJoined("A", 2.0)]
    assert [(s.to, s.message) for s in sends(out, m.Welcome)] == [("A", m.Welcome(conversation="register-s-1"))]
    again = message(a, "A", dataclasses.replace(reg, conversation="register-s-2", speed=3.0), 1.0)
    assert not events(again, au.AgentJoined) and a._agents["A"].speed == 3.0  # known: its speed updated
    assert [s.message.conversation for s in sends(again, m.Welcome, to="A")] == ["register-s-2"]


# ---- units won and rendered in batches (Config.slots 8: batches of 4) ---------------------------------


def test_with_eight_slots_a_free_agent_wins_a_batch_a_round_and_the_next_while_it_renders() -> None:
    a = make([1.0] * 40, ["A", "B"], au.Config(slots=8))
    first = round_trip(a, 0.0)
    by_agent = Counter(s.to for s in first.values())
    assert by_agent == {"A": 4, "B": 4}  # au.batch_size(8): four units each in one round
    second = round_trip(a, 0.1)  # 32 open units, at least 8 per agent: the next batch is queued
    assert Counter(s.to for s in second.values()) == {"A": 4, "B": 4}
    assert not set(first) & set(second)
    assert round_trip(a, 0.2) == {}  # eight held each: not called
    # Each agent's units follow one another: the last of its eight starts when the seven before it end.
    held = sorted((u for u in a._jobs["job-1"].units.values() if u.agent == "A"), key=lambda u: u.deadline)
    assert held[-1].deadline == pytest.approx(0.1 + 8 * 1.0 - 1.0 + 1.0 * a.config.render_factor
                                              + a.config.render_slack_s, abs=0.11)


def test_a_batch_round_offers_each_agent_the_units_projected_to_it_and_each_wins_them() -> None:
    a = make([1.0] * 40, ["A", "B"], au.Config(slots=8))
    cfps = sends(tick(a, 0.0), m.CallForProposal)
    offers = {s.to: {u.index for u in s.message.units} for s in cfps}
    assert sorted(len(units) for units in offers.values()) == [4, 4] and not offers["A"] & offers["B"]
    bid_all(a, cfps, 0.0)
    out = tick(a, 0.0)
    assert {i: s.to for i, s in awards(out).items()} == {i: name for name, units in offers.items() for i in units}
    assert not sends(out, m.Reject)


def test_units_won_in_one_round_share_the_deadline_of_the_last_one() -> None:
    # Long units: the batch ends after all four, later than 3 x the first's estimate + 30 s after its start.
    a = make([100.0] * 40, ["A", "B"], au.Config(slots=8))
    bid_all(a, tick(a, 0.0), 0.0)
    out = tick(a, 0.0)
    events = {e.index: e for e in out if isinstance(e, au.UnitAwarded)}
    for name in ("A", "B"):
        won = [i for i, e in events.items() if e.agent == name]
        assert len(won) == 4
        last = 3 * 100.0 + 100.0 * a.config.render_factor + a.config.render_slack_s  # the fourth's own
        assert all(a._jobs["job-1"].units[i].deadline == pytest.approx(last) for i in won)
        assert all(events[i].deadline == pytest.approx(last) for i in won)  # as the store records it


def test_an_agent_that_registered_fewer_slots_is_awarded_no_more() -> None:
    a = make([1.0] * 40, [], au.Config(slots=8))
    register(a, "A", 0.0, slots=2)
    assert len(round_trip(a, 0.0)) == 1  # batch_size(2): one a round
    assert len(round_trip(a, 0.1)) == 1
    assert round_trip(a, 0.2) == {}  # two held: full
    assert message(a, "A", m.Register(conversation="r", speed=1.0, threads=1, rules="", slots=8), 0.3)
    assert len(round_trip(a, 0.4)) == 4 and a._agents["A"].slots == 8


def test_agents_plan_alike_only_when_every_live_one_told_the_same_rules() -> None:
    """Whether the master's plan sees the rules every live agent plans with (MasterService._floors): the
    same rule file by sha256 where the job has none, and no defuzzifier of their own unless the job names
    one; never without live agents or with one that did not tell."""
    mine, other = "ab" * 32, "cd" * 32
    a = au.Auction(au.Config(), rng=random.Random(1))
    assert not a.plan_alike(mine, None)  # nobody to ask
    message(a, "A", m.Register(conversation="r", speed=1.0, threads=1, rules="x", rules_sha256=mine), 0.0)
    assert a.plan_alike(mine, None) and a.plan_alike(None, None) and a.plan_alike(mine, "centroid")
    message(a, "B", m.Register(conversation="r", speed=1.0, threads=1, rules="x", rules_sha256=mine,
                                 defuzzifier="centre-of-sums"), 0.0)
    assert not a.plan_alike(mine, None)  # B defuzzifies its own way where the job says nothing
    assert a.plan_alike(mine, "centroid")  # the job's defuzzifier is everyone's
    message(a, "B", m.Register(conversation="r", speed=1.0, threads=1, rules="x", rules_sha256=other), 1.0)
    assert not a.plan_alike(mine, None) and a.plan_alike(None, None)  # other rules; a job's own rules are all's
    message(a, "A", m.Heartbeat(conversation="h", busy=()), 20.0)
    assert [type(i) for i in tick(a, 20.0)] == [au.AgentLost]  # B, last heard from at 1.0
    assert a.plan_alike(mine, None)  # only live agents plan
    message(a, "C", m.Heartbeat(conversation="h", busy=()), 21.0)  # known from heartbeats alone
    assert not a.plan_alike(mine, None) and not a.plan_alike(None, None)


def test_an_idle_agent_in_the_end_game_wins_one_unit_of_a_level_off_job() -> None:
    a = au.Auction(au.Config(slots=8), rng=random.Random(7))
    submit(a, dataclasses.replace(info(), level="off"), specs([1.0] * 6))
    register(a, "A", 0.0)
    assert len(round_trip(a, 0.0)) == 1  # its units render one a call: nothing to batch


def test_in_the_end_game_an_agent_holding_units_is_not_called_and_an_idle_one_wins_one_batch() -> None:
    a = make([1.0] * 6, ["A"], au.Config(slots=8))  # 6 open units < 8 per agent: the end game from the start
    first = round_trip(a, 0.0)
    assert len(first) == 4  # one batch
    assert round_trip(a, 0.1) == {}  # it holds units: nothing is queued behind them
    for index, award in first.items():
        informed(a, "A", inform(award, 1.0), 1.0 + index * 0.01)
    assert sorted(round_trip(a, 2.0)) == sorted(set(range(6)) - set(first))


def test_two_slots_keep_one_unit_a_round() -> None:
    a = make([1.0] * 40, ["A", "B"], au.Config(slots=2))
    assert Counter(s.to for s in round_trip(a, 0.0).values()) == {"A": 1, "B": 1}


def test_a_units_story_names_the_stimuli_that_moved_it_and_each_instruction_its_stimulus() -> None:
    a = make([1.0], ["A"])
    [call] = sends(a.handle(au.Tick(stimulus_id="tick-1"), 0.0), m.CallForProposal)
    propose = m.Propose(conversation=call.message.conversation, job_id="job-1",
                        estimates=(m.Estimate(index=0, seconds=1.0),))
    assert a.handle(au.MessageReceived("A", propose, stimulus_id="propose-1"), 0.1) == []
    decided = a.handle(au.Tick(stimulus_id="tick-2"), 0.2)
    [award] = sends(decided, m.Award)
    assert {i.stimulus_id for i in decided} == {"tick-2"}
    done = a.handle(dataclasses.replace(stored(award.message, 1.0), stimulus_id="tile-1"), 1.5)
    assert [(type(i), i.stimulus_id) for i in done] == [(au.UnitDone, "tile-1"), (au.JobDone, "tile-1")]
    assert [(s.stimulus_id, s.start, s.finish, s.at) for s in a.story("job-1", 0)] == [
        ("tick-1", "pending", "announced", 0.0), ("tick-2", "announced", "awarded", 0.2),
        ("tile-1", "awarded", "done", 1.5)]
    assert a.story("job-1", 7) == [] and a.story("nope", 0) == []
    lost = tick(a, 50.0)  # an unnamed stimulus is numbered
    assert lost and all(i.stimulus_id.startswith("tick-") for i in lost)


def test_while_the_disk_is_full_nothing_times_out_and_the_clock_stands_still() -> None:
    a = make([1.0], ["A"])
    got = round_trip(a, 0.0)
    assert [type(i) for i in a.handle(au.DiskFull(free_bytes=10), 1.0)] == [au.JobsPaused]
    assert a.handle(au.DiskFull(free_bytes=9), 2.0) == [] and a.paused == "disk full on the master"
    assert tick(a, 1000.0) == [] and a.clock(1000.0) == 1.0  # no deadline, no loss while paused
    assert [type(i) for i in a.handle(au.DiskFreed(free_bytes=1 << 30), 1000.0)] == [au.JobsResumed]
    assert a.clock(1001.0) == pytest.approx(2.0) and a.paused is None
    assert a.award_for("job-1", 0, got[0].message.token) is not None  # still awarded: its deadline did not pass


def test_validate_names_the_invariant_a_state_breaks() -> None:
    a = make([1.0, 1.0], ["A", "B"])
    got = round_trip(a, 0.0)
    a.validate()
    unit = a._jobs["job-1"].units[0]
    a._agents[got[0].to].holding.clear()
    with pytest.raises(AssertionError, match=f"unit 0 of job job-1: awarded to {got[0].to}, which does not hold it"):
        a.validate()
    a._agents[got[0].to].holding.add(("job-1", 0))
    a._jobs["job-1"].units[1].token = "f" * 32  # a token left on a unit no longer awarded
    a._jobs["job-1"].units[1].status = UnitStatus.PENDING
    with pytest.raises(AssertionError, match="unit 1 of job job-1: pending with an award"):
        a.validate()
    assert unit.status == UnitStatus.AWARDED
