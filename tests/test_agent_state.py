"""The render agent's state machine (agents.state.AgentState), driven with stimuli and a fake clock: no network,
no render process, no Mitsuba. What tests/test_auction.py is to the master's auction. Every stimulus goes
through `CheckedState`, which validates the state's invariants after it.

Covered: slots (a second award queues, one render step at a time, a full agent refuses), batches (waiting
units of one job and depth in one StartRender, their shares of its time, a cancel within one, one kernel
per depth), duplicate awards and
re-awards, awards never bid on, cancel of a queued, a fetching, a rendering and an uploading unit and of a
whole job, heartbeats and registration, estimates and their calibration, Failure on every kind of error;
the units' statuses, their allowed changes, their stories, and what `validate` catches.
"""

from __future__ import annotations

import logging
import subprocess
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import get_args

import pytest

from agents import state as agent_state
from agents.state import (
    TRANSITIONS,
    AbortRender,
    AgentState,
    BundleFailed,
    BundleReady,
    Calibration,
    DiscardTile,
    FetchBundle,
    Instruction,
    Log,
    Measured,
    MessageReceived,
    RenderFailed,
    RenderFinished,
    SendToMaster,
    StartRender,
    Stimulus,
    Tick,
    Transition,
    Upload,
    UploadDone,
    UploadFailed,
    WorkStatus,
    describe,
    kernel_key,
)
from core.errors import QuekaroError
from core.model import messages as m
from core.model.geometry import Rect
from core.model.job import SceneSpec
from core.model.status import TransitionError
from core.model.units import WorkUnit

REPO = Path(__file__).resolve().parent.parent
SCENE = SceneSpec(Path("/bundles/cbox/scene.xml"), {})
SPEED = 2.0  # mega-rays/s; the fake estimator below reads it as cost units per second
COMPILE_S = 0.5


@dataclass(frozen=True)
class Params:
    depth: int
    spp: int
    band: int


@dataclass
class Rules:
    """A fake planner: spp 4 x the unit's index + 4, depth 6, band 2; counts its calls, fails on demand."""

    calls: list[tuple[int, ...]] = field(default_factory=list)
    fail: bool = False

    def __call__(self, job: m.JobInfo, units: tuple[WorkUnit, ...]) -> list[Params]:
        self.calls.append(tuple(u.index for u in units))
        if self.fail:
            raise ValueError("no rule fires")
        return [Params(depth=6, spp=4 * u.index + 4, band=2) for u in units]


def seconds(cost: float, spp: int, speed: float) -> float:
    return cost * spp / speed


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def advance(self, dt: float) -> float:
        self.now += dt
        return self.now


class CheckedState(AgentState):
    """An AgentState that validates its invariants after every stimulus it handles."""

    def handle(self, stimulus: Stimulus, now: float) -> list[Instruction]:
        out = super().handle(stimulus, now)
        self.validate()
        return out


class Agent:
    """A CheckedState, its fake clock, and the renders it has in flight (asserted never more than one). A
    message goes in as MessageReceived; a stimulus without an id gets one (`sid`, else a running number)."""

    def __init__(self, slots: int = 2, rules: Rules | None = None, refuse_url: str | None = None) -> None:
        self.rules = rules or Rules()
        self.steps = 0
        self.state = CheckedState(self.rules, seconds, slots=slots, threads=1, rules="test.xml", heartbeat_s=2.0,
                                session="s", check_url=lambda url: refuse_url and f"{refuse_url}: {url}",
                                rules_sha256="ab" * 32, defuzzifier="centroid")
        self.clock = Clock()
        self.in_flight: set[int] = set()  # tickets between FetchBundle and the render's end
        self.state.handle(Measured(SPEED, COMPILE_S, stimulus_id="measured"), self.clock.now)

    def __call__(self, event: Stimulus | m.Message, dt: float = 0.0, sid: str = "") -> list[Instruction]:
        self.steps += 1
        sid = sid or f"step-{self.steps}"
        if isinstance(event, m.Message):
            event = MessageReceived(event, stimulus_id=sid)
        elif not event.stimulus_id:
            event = replace(event, stimulus_id=sid)
        if isinstance(event, RenderFinished | RenderFailed | BundleFailed):
            self.in_flight.discard(event.ticket)
        out = self.state.handle(event, self.clock.advance(dt))
        if isinstance(event, BundleReady) and not any(isinstance(c, StartRender) for c in out):
            self.in_flight.discard(event.ticket)  # not rendered (cancelled, or no plan)
        self.in_flight |= {c.ticket for c in out if isinstance(c, FetchBundle)}
        assert len(self.in_flight) <= 1, f"renders in flight at once: {sorted(self.in_flight)}"
        return out

    def held(self) -> list[tuple[str, int]]:
        return [(h.job_id, h.index) for h in self.state.busy_units()]


def job(job_id: str = "job-1", rules_sha256: str | None = None) -> m.JobInfo:
    return m.JobInfo(job_id=job_id, scene_url=f"http://127.0.0.1:1/jobs/{job_id}/bundle", scene_hash="ab" * 32,
                     width=32, height=32, spp=16, depth=6, level="N", ranges={"C": (0.0, 1.0)},
                     rules_sha256=rules_sha256)


def unit(index: int, rect: Rect | None = None) -> WorkUnit:
    rect = rect or Rect(0, 0, 8, 8)
    return WorkUnit(index=index, rect=rect, C=0.5, S=rect.area, Nd=0.1, cost=10.0 * (index + 1))


def award(info: m.JobInfo, u: WorkUnit, token: str = "a1" * 16, conversation: str | None = None) -> m.Award:
    return m.Award(conversation=conversation or f"award-{info.job_id}-{u.index}", job=info, unit=u, token=token,
                   upload_url=f"http://127.0.0.1:1/jobs/{info.job_id}/units/{u.index}/tile", seed=u.index,
                   estimate_s=1.0)


def cfp(info: m.JobInfo, *units: WorkUnit, conversation: str = "cfp-1") -> m.CallForProposal:
    return m.CallForProposal(conversation=conversation, job=info, units=units, reply_within_s=2.0)


def sent(out: list[Instruction], kind: type[m.Message] = m.Message) -> list[m.Message]:
    return [c.message for c in out if isinstance(c, SendToMaster) and isinstance(c.message, kind)]


def only(out: list[Instruction], kind: type) -> object:
    found = [c for c in out if isinstance(c, kind)]
    assert len(found) == 1, f"expected one {kind.__name__} in {out}"
    return found[0]


def render(agent: Agent, fetch: FetchBundle, render_s: float = 1.0) -> Upload:
    """The fetched unit's bundle arrives, it renders for `render_s`: the Upload the agent asks for."""
    start = only(agent(BundleReady(fetch.ticket, SCENE)), StartRender)
    out = agent(RenderFinished(start.ticket, Path(f"/tiles/{start.ticket}.exr"), render_s, 0), dt=render_s)
    return only(out, Upload)


def deliver(agent: Agent, fetch: FetchBundle, wall: float = 1.0) -> m.Award:
    """A unit through render and upload, `wall` seconds in all: the award its tile was uploaded under. The
    upload is the answer (the master counts a unit done by its tile): nothing is sent after it."""
    upload = render(agent, fetch, wall / 2)
    assert sent(agent(UploadDone(upload.ticket), dt=wall / 2)) == []
    return upload.award


# ---- bids and slots --------------------------------------------------------------------------------------


def test_a_free_agent_proposes_its_estimates_and_remembers_the_plans() -> None:
    agent = Agent()
    info = job()
    out = agent(cfp(info, unit(0), unit(1, Rect(8, 0, 8, 8))))
    (propose,) = sent(out, m.Propose)
    assert (propose.conversation, propose.job_id) == ("cfp-1", "job-1")
    # cost x spp / speed, + a compilation: no kernel compiled yet.
    assert [(e.index, e.seconds) for e in propose.estimates] == [(0, 10 * 4 / SPEED + COMPILE_S),
                                                                 (1, 20 * 8 / SPEED + COMPILE_S)]
    assert set(agent.state.planned) == {("job-1", 0), ("job-1", 1)}
    assert any(isinstance(c, Log) and "proposing for job-1" in c.text for c in out)


def test_a_second_award_queues_and_renders_when_the_first_is_rendered() -> None:
    agent = Agent()
    info = job()
    first = only(agent(award(info, unit(0))), FetchBundle)
    assert agent(award(info, unit(1))) == []  # queued: the render process is busy
    assert agent.held() == [("job-1", 0), ("job-1", 1)]
    start = only(agent(BundleReady(first.ticket, SCENE)), StartRender)
    out = agent(RenderFinished(start.ticket, Path("/tiles/0.exr"), 1.0), dt=1.0)
    # The first tile uploads while the second unit goes to the render process.
    assert only(out, Upload).award.unit.index == 0
    assert only(out, FetchBundle).job.job_id == "job-1" and agent.state.rendering.key == ("job-1", 1)


def test_never_more_renders_than_one_and_units_render_in_award_order() -> None:
    agent = Agent(slots=3)
    info = job()
    outs = [agent(award(info, unit(i))) for i in (2, 0, 1)]
    assert [len(out) for out in outs] == [1, 0, 0]
    fetch: FetchBundle | None = outs[0][0]
    order = []
    while fetch is not None:
        start = only(agent(BundleReady(fetch.ticket, SCENE)), StartRender)
        order.append(start.award.unit.index)
        out = agent(RenderFinished(start.ticket, Path("/t.exr"), 1.0))
        fetch = next((c for c in out if isinstance(c, FetchBundle)), None)
    assert order == [2, 0, 1]
    assert agent.held() == [("job-1", 0), ("job-1", 1), ("job-1", 2)]  # all three uploading


def test_a_full_agent_refuses_and_frees_up_after_an_answer() -> None:
    agent = Agent()
    info = job()
    fetch = only(agent(award(info, unit(0))), FetchBundle)
    assert sent(agent(cfp(info, unit(2), conversation="cfp-a")), m.Propose)  # one slot left
    agent(award(info, unit(1)))
    (refuse,) = sent(agent(cfp(info, unit(2), conversation="cfp-b")), m.Refuse)
    assert refuse.conversation == "cfp-b" and refuse.reason == "busy rendering job-1/0, job-1/1"
    deliver(agent, fetch)
    assert sent(agent(cfp(info, unit(2), conversation="cfp-c")), m.Propose)


def test_one_slot_means_no_bid_while_any_render_runs_even_a_cancelled_one() -> None:
    agent = Agent(slots=1)
    info = job()
    fetch = only(agent(award(info, unit(0))), FetchBundle)
    start = only(agent(BundleReady(fetch.ticket, SCENE)), StartRender)
    agent(m.Cancel(conversation="c-1", job_id="job-1", index=0, reason="test"))
    assert agent.held() == []
    (refuse,) = sent(agent(cfp(info, unit(1))), m.Refuse)
    assert refuse.reason == "busy rendering a cancelled unit"
    agent(RenderFinished(start.ticket, Path("/tiles/0.exr"), 1.0))
    assert sent(agent(cfp(info, unit(1))), m.Propose)


def test_a_planner_that_fails_refuses_the_call() -> None:
    agent = Agent(rules=Rules(fail=True))
    (refuse,) = sent(agent(cfp(job(), unit(0))), m.Refuse)
    assert refuse.reason == "cannot plan units: ValueError: no rule fires"


def test_a_refused_data_plane_url_refuses_the_call_without_planning() -> None:
    agent = Agent(refuse_url="plain HTTP")
    (refuse,) = sent(agent(cfp(job(), unit(0))), m.Refuse)
    assert refuse.reason == f"plain HTTP: {job().scene_url}" and agent.rules.calls == []


# ---- awards ------------------------------------------------------------------------------------------


def test_a_duplicate_award_renders_once_also_after_the_unit_is_done() -> None:
    agent = Agent()
    info = job()
    the_award = award(info, unit(0))
    fetch = only(agent(the_award), FetchBundle)
    assert agent(the_award) == []
    assert agent.held() == [("job-1", 0)]
    uploaded_as = deliver(agent, fetch)
    assert uploaded_as.token == the_award.token and agent.state.units_done == 1
    out = agent(the_award)
    assert not [c for c in out if not isinstance(c, Log)]
    assert "unit 0 of job job-1: duplicate award ignored" in only(out, Log).text
    assert agent.held() == []


def test_the_inform_gives_the_spp_mitsuba_rendered_not_the_rules_count() -> None:
    """A stratified sampler rounds the rules' count to a square: the agent says what was rendered."""
    agent = Agent()
    fetch = only(agent(award(job(), unit(0))), FetchBundle)
    start = only(agent(BundleReady(fetch.ticket, SCENE)), StartRender)
    rendered = start.params.spp + 7  # any other count
    upload = only(agent(RenderFinished(start.ticket, Path("/t.exr"), 1.0, 0, rendered), dt=1.0), Upload)
    out = agent(UploadDone(upload.ticket))
    assert rendered != start.params.spp
    assert any(f"spp {rendered}," in c.text for c in out if isinstance(c, Log))


def test_a_re_award_with_a_new_token_is_answered_under_the_new_award() -> None:
    agent = Agent()
    info = job()
    fetch = only(agent(award(info, unit(0), token="a1" * 16)), FetchBundle)
    out = agent(award(info, unit(0), token="b2" * 16, conversation="award-2"))
    assert not [c for c in out if not isinstance(c, Log)]  # no second render
    uploaded_as = deliver(agent, fetch)
    assert (uploaded_as.token, uploaded_as.conversation) == ("b2" * 16, "award-2")


@pytest.mark.parametrize("upload_ok", [True, False])
def test_a_re_award_during_the_upload(upload_ok: bool) -> None:
    """The tile went under the award it was uploaded with (nothing more is sent); a Failure goes under the
    latest award."""
    agent = Agent()
    info = job()
    fetch = only(agent(award(info, unit(0), token="a1" * 16)), FetchBundle)
    upload = render(agent, fetch)
    assert upload.award.token == "a1" * 16
    agent(award(info, unit(0), token="b2" * 16, conversation="award-2"))
    result = UploadDone(upload.ticket) if upload_ok else UploadFailed(upload.ticket, "refused")
    answers = sent(agent(result))
    if upload_ok:
        assert answers == []
    else:
        (answer,) = answers
        assert type(answer) is m.Failure and answer.token == "b2" * 16


def test_an_award_never_bid_on_is_planned_afresh_a_bid_on_one_is_not() -> None:
    rules = Rules()
    agent = Agent(rules=rules)
    info = job()
    agent(cfp(info, unit(0)))
    assert rules.calls == [(0,)]
    fetch = only(agent(award(info, unit(0))), FetchBundle)
    start = only(agent(BundleReady(fetch.ticket, SCENE)), StartRender)
    assert rules.calls == [(0,)] and start.params == Params(6, 4, 2)  # the bid's plan
    agent(RenderFinished(start.ticket, Path("/t.exr"), 1.0))
    fetch = only(agent(award(info, unit(3, Rect(8, 8, 8, 8)))), FetchBundle)  # never called for
    start = only(agent(BundleReady(fetch.ticket, SCENE)), StartRender)
    assert rules.calls == [(0,), (3,)] and start.params == Params(6, 16, 2)
    assert start.timeout_s == pytest.approx(120.0 + 10.0 * 40 * 16 / SPEED)


def test_a_job_with_its_own_rules_is_planned_again_once_its_bundle_is_here() -> None:
    rules = Rules()
    agent = Agent(rules=rules)
    info = job(rules_sha256="ef" * 32)
    agent(cfp(info, unit(0)))
    fetch = only(agent(award(info, unit(0))), FetchBundle)
    agent(BundleReady(fetch.ticket, SCENE))
    assert rules.calls == [(0,), (0,)]


def test_an_award_that_cannot_be_planned_fails() -> None:
    rules = Rules()
    agent = Agent(rules=rules)
    info = job()
    the_award = award(info, unit(0))
    fetch = only(agent(the_award), FetchBundle)
    rules.fail = True
    out = agent(BundleReady(fetch.ticket, SCENE))
    (failure,) = sent(out, m.Failure)
    assert failure.reason == "ValueError: no rule fires" and failure.token == the_award.token
    assert not [c for c in out if isinstance(c, StartRender)] and agent.held() == []


# ---- failures ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("stage", ["bundle", "render", "upload"])
def test_a_failure_sends_failure_and_the_agent_goes_on(stage: str) -> None:
    agent = Agent()
    info = job("job-9")
    the_award = award(info, unit(2))
    fetch = only(agent(the_award), FetchBundle)
    agent(award(info, unit(3)))
    reason = f"{stage} broke"
    if stage == "bundle":
        out = agent(BundleFailed(fetch.ticket, reason))
    elif stage == "render":
        start = only(agent(BundleReady(fetch.ticket, SCENE)), StartRender)
        out = agent(RenderFailed(start.ticket, reason))
    else:
        upload = render(agent, fetch)
        out = agent(UploadFailed(upload.ticket, reason))
    (failure,) = sent(out, m.Failure)
    assert (failure.conversation, failure.job_id, failure.index, failure.token, failure.reason) == \
        (the_award.conversation, "job-9", 2, the_award.token, reason)
    assert DiscardTile("job-9", 2) in out
    assert agent.state.units_failed == 1 and agent.held() == [("job-9", 3)]
    assert agent.state.rendering is not None and agent.state.rendering.key == ("job-9", 3)  # it goes on


def test_failure_reasons_are_cut_to_the_message_limit() -> None:
    agent = Agent()
    fetch = only(agent(award(job(), unit(0))), FetchBundle)
    (failure,) = sent(agent(BundleFailed(fetch.ticket, "x" * 5000)), m.Failure)
    assert failure.reason == "x" * 1024


def test_describe_names_foreign_errors_by_type() -> None:
    assert describe(QuekaroError("scene not found")) == "scene not found"
    assert describe(OSError("disk full")) == "OSError: disk full"
    assert describe(RuntimeError()) == "RuntimeError: "
    assert describe(QuekaroError()) == "QuekaroError"


def test_stimuli_of_unknown_tickets_change_nothing() -> None:
    agent = Agent()
    agent(award(job(), unit(0)))
    for event in (BundleReady(99, SCENE), RenderFinished(99, Path("/t.exr"), 1.0), UploadDone(99),
                  UploadFailed(99, "x"), RenderFailed(99, "x")):
        assert all(isinstance(c, Log) for c in agent(event))
    assert agent.held() == [("job-1", 0)] and agent.state.units_failed == 0
    with pytest.raises(TypeError):
        agent.state.handle("not a stimulus", 0.0)  # type: ignore[arg-type]
    with pytest.raises(TypeError):  # a message goes in as MessageReceived
        agent.state.handle(m.Reject(conversation="c", job_id="job-1", reason="x"), 0.0)  # type: ignore[arg-type]


# ---- cancel ------------------------------------------------------------------------------------------


def test_cancel_of_a_queued_unit_drops_it() -> None:
    agent = Agent()
    info = job()
    fetch = only(agent(award(info, unit(0))), FetchBundle)
    agent(award(info, unit(1)))
    out = agent(m.Cancel(conversation="c-1", job_id="job-1", index=1, reason="gone"))
    assert "unit 1 of job job-1: cancelled by the master: gone" in only(out, Log).text
    assert not [c for c in out if isinstance(c, AbortRender)]  # unit 0 renders on
    assert agent.held() == [("job-1", 0)]
    upload = render(agent, fetch)
    assert agent.state.rendering is None  # the cancelled unit never starts
    assert sent(agent(UploadDone(upload.ticket))) == []
    assert agent.held() == []


def test_cancel_of_a_rendering_unit_discards_its_tile_and_answers_nothing() -> None:
    agent = Agent()
    info = job()
    fetch = only(agent(award(info, unit(0))), FetchBundle)
    agent(award(info, unit(1)))
    start = only(agent(BundleReady(fetch.ticket, SCENE)), StartRender)
    out = agent(m.Cancel(conversation="c-1", job_id="job-1", index=0, reason="x"))
    assert only(out, AbortRender) == AbortRender(start.ticket)  # not left to hold the agent, looking free
    assert agent.held() == [("job-1", 1)]
    out = agent(RenderFinished(start.ticket, Path("/tiles/0.exr"), 1.0))
    assert DiscardTile("job-1", 0) in out and not sent(out) and not [c for c in out if isinstance(c, Upload)]
    assert only(out, FetchBundle).ticket != fetch.ticket  # the next unit renders
    assert agent.state.units_done == agent.state.units_failed == 0


def test_a_failure_of_a_cancelled_render_is_not_reported() -> None:
    agent = Agent()
    fetch = only(agent(award(job(), unit(0))), FetchBundle)
    start = only(agent(BundleReady(fetch.ticket, SCENE)), StartRender)
    agent(m.Cancel(conversation="c-1", job_id="job-1", index=None, reason="x"))
    out = agent(RenderFailed(start.ticket, "crashed"))
    assert not sent(out) and DiscardTile("job-1", 0) in out and agent.state.units_failed == 0


def test_a_unit_cancelled_while_its_bundle_is_fetched_is_not_rendered() -> None:
    agent = Agent()
    fetch = only(agent(award(job(), unit(0))), FetchBundle)
    out = agent(m.Cancel(conversation="c-1", job_id="job-1", index=0, reason="x"))
    assert not [c for c in out if isinstance(c, AbortRender)]  # nothing renders yet
    out = agent(BundleReady(fetch.ticket, SCENE))
    assert not [c for c in out if isinstance(c, StartRender)] and agent.state.rendering is None


def test_cancel_of_an_uploading_unit_is_not_counted_done() -> None:
    agent = Agent()
    fetch = only(agent(award(job(), unit(0))), FetchBundle)
    upload = render(agent, fetch)
    assert agent.held() == [("job-1", 0)]  # held while its tile uploads
    agent(m.Cancel(conversation="c-1", job_id="job-1", index=0, reason="x"))
    out = agent(UploadDone(upload.ticket))
    assert not sent(out) and agent.state.units_done == 0 and not agent.state.finished


def test_cancel_of_a_whole_job_leaves_the_other_jobs_units() -> None:
    agent = Agent(slots=4)
    one, two = job("job-1"), job("job-2")
    rendered_here(agent, one)
    fetch = only(agent(award(one, unit(0))), FetchBundle)
    agent(award(two, unit(0)))
    agent(award(one, unit(1)))
    start = only(agent(BundleReady(fetch.ticket, SCENE)), StartRender)
    assert [b.award.unit.index for b in start.more] == [1]  # job-1's two units render in one call
    agent(m.Cancel(conversation="c-1", job_id="job-1", index=5, reason="x"))  # not one it holds
    assert agent.held() == [("job-1", 0), ("job-1", 1), ("job-2", 0)]
    out = agent(m.Cancel(conversation="c-2", job_id="job-1", index=None, reason="job cancelled"))
    assert len([c for c in out if isinstance(c, Log)]) == 2 and only(out, AbortRender) == AbortRender(start.ticket)
    assert agent.held() == [("job-2", 0)]
    out = agent(RenderFinished(start.ticket, Path("/t.exr"), 1.0))  # the abandoned render ends: discarded
    assert DiscardTile("job-1", 0) in out and not sent(out) and not [c for c in out if isinstance(c, FetchBundle)]
    out = agent(RenderFailed(start.more[0].ticket, "interrupted"))  # its batch's end: not reported
    assert DiscardTile("job-1", 1) in out and not sent(out)
    assert only(out, FetchBundle).job.job_id == "job-2"  # job-2 waited for the whole batch


def test_a_unit_awarded_again_after_its_cancel_renders_again() -> None:
    agent = Agent()
    info = job()
    fetch = only(agent(award(info, unit(0))), FetchBundle)
    start = only(agent(BundleReady(fetch.ticket, SCENE)), StartRender)
    agent(m.Cancel(conversation="c-1", job_id="job-1", index=0, reason="x"))
    assert agent(award(info, unit(0), token="b2" * 16)) == []  # waits for the abandoned render
    out = agent(RenderFinished(start.ticket, Path("/t.exr"), 1.0))
    again = only(out, FetchBundle)
    assert again.ticket != fetch.ticket and agent.held() == [("job-1", 0)]
    assert deliver(agent, again).token == "b2" * 16


# ---- heartbeats and registration -----------------------------------------------------------------------


def test_registers_on_every_connection_and_beats_the_held_units() -> None:
    agent = Agent()
    assert agent(Tick(online=False)) == []
    reg, beat = sent(agent(Tick(connection=0)))
    assert isinstance(reg, m.Register) and (reg.speed, reg.threads, reg.rules) == (SPEED, 1, "test.xml")
    assert (reg.rules_sha256, reg.defuzzifier) == ("ab" * 32, "centroid")
    assert isinstance(beat, m.Heartbeat) and beat.busy == ()
    assert agent(m.Welcome(conversation=reg.conversation)) == []  # the master heard it
    assert agent(Tick(), dt=1.0) == []  # the next beat is due 2 s later
    info = job()
    fetch = only(agent(award(info, unit(1))), FetchBundle)
    agent(award(info, unit(0)))
    (beat,) = sent(agent(Tick(), dt=1.0))
    assert [(h.job_id, h.index) for h in beat.busy] == [("job-1", 0), ("job-1", 1)]
    deliver(agent, fetch)
    agent(m.Cancel(conversation="c-1", job_id="job-1", index=0, reason="x"))
    (beat,) = sent(agent(Tick(), dt=2.0))
    assert beat.busy == ()
    reg, beat = sent(agent(Tick(connection=1)))  # reconnected: at once, both
    assert isinstance(reg, m.Register) and isinstance(beat, m.Heartbeat)
    assert len({reg.conversation, beat.conversation}) == 2


def test_registers_again_with_each_beat_until_a_welcome_of_this_connection_answers() -> None:
    agent = Agent()
    first, _ = sent(agent(Tick(connection=0)))
    again, beat = sent(agent(Tick(), dt=2.0))  # no Welcome: the master may have been offline
    assert isinstance(again, m.Register) and isinstance(beat, m.Heartbeat)
    assert again.conversation != first.conversation
    assert agent(Tick(), dt=1.0) == []  # only with a beat, not at every tick
    agent(m.Welcome(conversation="register-of-someone-else"))  # not one of its Registers: ignored
    assert [type(s) for s in sent(agent(Tick(), dt=1.0))] == [m.Register, m.Heartbeat]
    agent(m.Welcome(conversation=first.conversation))  # an earlier one's answer counts as well
    assert [type(s) for s in sent(agent(Tick(), dt=2.0))] == [m.Heartbeat]
    assert [type(s) for s in sent(agent(Tick(connection=1)))] == [m.Register, m.Heartbeat]  # unwelcomed again
    old_welcome = agent(m.Welcome(conversation=again.conversation))  # a Welcome from the last connection
    assert old_welcome and isinstance(old_welcome[0], Log)
    assert [type(s) for s in sent(agent(Tick(), dt=2.0))] == [m.Register, m.Heartbeat]


def test_an_introduce_asks_for_a_register_until_a_welcome_answers() -> None:
    agent = Agent()
    first, _ = sent(agent(Tick(connection=0)))
    agent(m.Welcome(conversation=first.conversation))
    assert [type(s) for s in sent(agent(Tick(), dt=2.0))] == [m.Heartbeat]  # welcomed: beats only
    (again,) = sent(agent(m.Introduce(conversation="c-9")))  # the master restarted and knows it by beats only
    assert isinstance(again, m.Register) and again.speed == SPEED and again.conversation != first.conversation
    assert [type(s) for s in sent(agent(Tick(), dt=2.0))] == [m.Register, m.Heartbeat]  # lost? again, with a beat
    agent(m.Welcome(conversation=again.conversation))
    assert [type(s) for s in sent(agent(Tick(), dt=2.0))] == [m.Heartbeat]
    early = CheckedState(Rules(), seconds)  # no speed yet, never registered: it registers when it can
    said = early.handle(MessageReceived(m.Introduce(conversation="c-1"), stimulus_id="introduce-1"), 0.0)
    assert said and all(isinstance(c, Log) for c in said)


def test_no_registration_before_the_speed_is_known() -> None:
    state = CheckedState(Rules(), seconds)
    assert state.handle(Tick(stimulus_id="tick-1"), 0.0) == []
    state.handle(Measured(3.0, stimulus_id="measured"), 0.1)
    assert [type(c.message) for c in state.handle(Tick(stimulus_id="tick-2"), 0.2)
            if isinstance(c, SendToMaster)] == [m.Register, m.Heartbeat]


def test_a_heartbeat_lists_at_most_256_units() -> None:
    agent = Agent(slots=300)
    info = job()
    for i in range(300):
        agent(award(info, unit(i)))
    beats = sent(agent(Tick()), m.Heartbeat)
    assert len(beats[0].busy) == 256


# ---- estimates and calibration -----------------------------------------------------------------------------


def test_calibration_moves_estimates_toward_measured_times() -> None:
    agent = Agent()
    info, other = job("job-1"), job("job-2")
    u = unit(1)
    (first,) = sent(agent(cfp(info, u)), m.Propose)
    assert first.estimates[0].seconds == pytest.approx(20 * 8 / SPEED + COMPILE_S)
    fetch = only(agent(award(info, u)), FetchBundle)
    predicted = 20 * 8 / SPEED + COMPILE_S  # uncorrected, the kernel not compiled yet
    deliver(agent, fetch, wall=3 * predicted)  # three times slower than estimated
    assert agent.state.calibration.factor("job-1") == pytest.approx(3.0)
    (second,) = sent(agent(cfp(info, u, conversation="cfp-2")), m.Propose)
    # The same window: compiled now; and corrected by what the job showed.
    assert second.estimates[0].seconds == pytest.approx(3.0 * 20 * 8 / SPEED)
    (elsewhere,) = sent(agent(cfp(other, u, conversation="cfp-3")), m.Propose)
    assert elsewhere.estimates[0].seconds == pytest.approx(20 * 8 / SPEED)  # same kernel, no correction


def test_a_kernel_is_compiled_once_per_window_size_and_depth() -> None:
    info = job()
    small, big = unit(0, Rect(0, 0, 8, 8)), unit(1, Rect(0, 0, 16, 16))
    moved = unit(2, Rect(8, 8, 8, 8))  # same size elsewhere: the band widens it the same
    inner = unit(3, Rect(4, 4, 8, 8))
    p = Params(6, 4, 2)
    # at the image's corner the window is shifted inside, not clipped: one size, one kernel
    assert kernel_key(info, moved, p) == kernel_key(info, inner, p) == kernel_key(info, small, p)
    assert kernel_key(info, small, p) != kernel_key(info, small, Params(6, 4, 3))  # another band
    assert kernel_key(info, small, p) != kernel_key(info, big, p) != kernel_key(info, big, Params(3, 4, 2))


def test_calibration_is_a_moving_average_that_forgets_old_jobs() -> None:
    cal = Calibration(alpha=0.5, max_jobs=2)
    cal.learn("a", 1.0, 3.0)
    cal.learn("a", 1.0, 1.0)
    assert cal.factor("a") == pytest.approx(2.0)
    cal.learn("b", 2.0, 1.0)
    cal.learn("c", 1.0, 0.0)  # nothing measured: ignored
    cal.learn("d", 1.0, 4.0)
    assert cal.factor("a") == 1.0 and cal.factor("b") == 0.5 and cal.factor("d") == 4.0


# ---- the module itself -------------------------------------------------------------------------------------


def test_the_state_machine_imports_no_io() -> None:
    code = ("import sys, agents.state\n"
            "heavy = {'mitsuba', 'drjit', 'spade', 'aiohttp', 'asyncio', 'core.render', 'core.transport'}\n"
            "print(sorted(heavy & set(sys.modules)))")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_logs_go_out_as_instructions_with_levels() -> None:
    agent = Agent()
    out = agent(m.Reject(conversation="cfp-1", job_id="job-1", reason="lost"))
    assert out == [Log(logging.DEBUG, "rejected in cfp-1: lost")]


# ---- units rendered together (a batch: half the slots) --------------------------------------------------


class DepthRules(Rules):
    """Depth 6 for units below 10, depth 4 for the others."""

    def __call__(self, job: m.JobInfo, units: tuple[WorkUnit, ...]) -> list[Params]:
        return [Params(depth=p.depth if u.index < 10 else 4, spp=p.spp, band=p.band)
                for u, p in zip(units, super().__call__(job, units), strict=True)]


def rendered_here(agent: Agent, *infos: m.JobInfo) -> None:
    """A unit of each job (unit 63) rendered and delivered: the job's next calls batch (a job's first call
    renders its first unit alone, AgentState._first_call)."""
    for info in infos:
        deliver(agent, only(agent(award(info, unit(63))), FetchBundle))


def two_in_one_call(agent: Agent, info: m.JobInfo) -> StartRender:
    """Units 0 and 1 of the job awarded back to back, after one of its units rendered here: the first one's
    StartRender (the second in it, if batched)."""
    rendered_here(agent, info)
    fetch = only(agent(award(info, unit(0))), FetchBundle)
    agent(award(info, unit(1)))
    return only(agent(BundleReady(fetch.ticket, SCENE)), StartRender)


def test_waiting_units_of_the_job_and_depth_render_in_one_call_up_to_half_the_slots() -> None:
    agent = Agent(slots=8, rules=DepthRules())
    assert agent.state.batch == 4
    info, other = job("job-1"), job("job-2")
    rendered_here(agent, info)
    fetch = only(agent(award(info, unit(0))), FetchBundle)
    for u in (10, 1, 2, 3, 4):  # unit 10 has another depth
        agent(award(info, unit(u)))
    agent(award(other, unit(5)))
    start = only(agent(BundleReady(fetch.ticket, SCENE)), StartRender)
    assert [b.award.unit.index for b in start.more] == [1, 2, 3]  # oldest first, four in all
    assert {b.params.depth for b in start.more} == {6} and len(set(start.tickets)) == 4
    assert agent.state.rendering.key == ("job-1", 0) and [w.key[1] for w in agent.state.queue] == [10, 4, 5]
    uploads = []
    for ticket in start.tickets[:-1]:
        out = agent(RenderFinished(ticket, Path(f"/tiles/{ticket}.exr"), 0.25), dt=0.1)
        uploads.append(only(out, Upload))
        assert not [c for c in out if isinstance(c, FetchBundle)]  # the render process is still busy
    out = agent(RenderFinished(start.tickets[-1], Path("/tiles/last.exr"), 0.25), dt=0.1)
    assert only(out, Upload) and only(out, FetchBundle).ticket not in start.tickets  # the next one: unit 10
    assert sorted(u.award.unit.index for u in uploads) == [0, 1, 2]


def test_a_batch_is_timed_by_shares_of_its_estimate_for_the_calibration() -> None:
    agent = Agent(slots=4)
    info = job()
    start = two_in_one_call(agent, info)
    warm = agent.state.calibration.factor("job-1")  # learned from the unit rendered first
    shares = [w.share for w in agent.state.step]
    # unit i costs 10 (i + 1) at 4 i + 4 spp: 40 and 160 units of work
    assert shares == pytest.approx([0.2, 0.8])
    for ticket in start.tickets:
        agent(RenderFinished(ticket, Path(f"/tiles/{ticket}.exr"), 1.0))
    assert sent(agent(UploadDone(start.tickets[0]), dt=2.0)) == []
    # unit 0 took its share of the 2 s since the batch began, against its estimate of 20 s (the film's
    # kernel compiled by the unit rendered first), averaged with what that unit taught
    ratio = 2.0 * 0.2 / seconds(10.0, 4, SPEED)
    assert agent.state.calibration.factor("job-1") == pytest.approx(warm + 0.5 * (ratio - warm))


@pytest.mark.parametrize("kind", ["off", "adaptive"])
def test_level_off_and_two_pass_units_render_one_a_call(kind: str) -> None:
    agent = Agent(slots=8)
    info = job()
    info = replace(info, level="off") if kind == "off" else replace(info, first_spp=4)
    assert two_in_one_call(agent, info).more == ()


def test_cancel_of_one_unit_of_a_batch_lets_the_others_render() -> None:
    agent = Agent(slots=4)
    start = two_in_one_call(agent, job())
    assert len(start.tickets) == 2
    out = agent(m.Cancel(conversation="c-1", job_id="job-1", index=0, reason="x"))
    assert not [c for c in out if isinstance(c, AbortRender)]  # unit 1 is still wanted
    out = agent(RenderFinished(start.ticket, Path("/tiles/0.exr"), 1.0))
    assert DiscardTile("job-1", 0) in out and not [c for c in out if isinstance(c, Upload)]
    out = agent(RenderFinished(start.more[0].ticket, Path("/tiles/1.exr"), 1.0))
    assert only(out, Upload).award.unit.index == 1


def test_a_batch_cancelled_unit_by_unit_is_ended_at_the_last_cancel() -> None:
    agent = Agent(slots=4)
    start = two_in_one_call(agent, job())
    assert not [c for c in agent(m.Cancel(conversation="c-1", job_id="job-1", index=1, reason="x"))
                if isinstance(c, AbortRender)]
    out = agent(m.Cancel(conversation="c-2", job_id="job-1", index=0, reason="x"))
    assert only(out, AbortRender) == AbortRender(start.ticket)  # the first unit's ticket: the render's
    for ticket in start.tickets:
        out = agent(RenderFailed(ticket, "interrupted"))
        assert not sent(out)
    assert agent.held() == [] and agent.state.step == [] and agent.state.units_failed == 0


def test_a_batched_unit_re_awarded_during_its_render_uploads_under_the_new_award() -> None:
    agent = Agent(slots=4)
    info = job()
    start = two_in_one_call(agent, info)
    agent(award(info, unit(1), token="b2" * 16, conversation="again"))
    out = agent(RenderFinished(start.more[0].ticket, Path("/tiles/1.exr"), 1.0))
    upload = only(out, Upload)
    assert upload.award.token == "b2" * 16
    assert upload.award.conversation == "again"
    assert sent(agent(UploadDone(upload.ticket))) == []


def test_a_waiting_unit_that_cannot_be_planned_stays_out_of_the_batch_and_fails_alone() -> None:
    rules = Rules()
    agent = Agent(slots=4, rules=rules)
    info = job(rules_sha256="ef" * 32)  # its own rules: planned afresh, here failing for unit 1 only
    fetch = only(agent(award(info, unit(0))), FetchBundle)
    agent(award(info, unit(1)))
    original = rules.__class__.__call__

    def failing_for_one(self: Rules, job_: m.JobInfo, units: tuple[WorkUnit, ...]) -> list[Params]:
        if any(u.index == 1 for u in units):
            raise ValueError("no rule fires")
        return original(self, job_, units)

    agent.state.plan = lambda job_, units: failing_for_one(rules, job_, units)
    start = only(agent(BundleReady(fetch.ticket, SCENE)), StartRender)
    assert start.more == () and [w.key for w in agent.state.queue] == [("job-1", 1)]
    out = agent(RenderFinished(start.ticket, Path("/tiles/0.exr"), 1.0))
    fetch = only(out, FetchBundle)
    (failure,) = sent(agent(BundleReady(fetch.ticket, SCENE)), m.Failure)
    assert failure.index == 1 and "no rule fires" in failure.reason


def test_register_tells_the_master_its_slots() -> None:
    agent = Agent(slots=6)
    (register,) = sent(agent(Tick(online=True, connection=1)), m.Register)
    assert register.slots == 6


def test_batch_must_fit_the_slots() -> None:
    with pytest.raises(ValueError, match="batch must be from 1 to slots"):
        AgentState(Rules(), seconds, slots=2, batch=3)


def test_units_rendered_in_batches_compile_one_kernel_per_depth_whatever_their_size() -> None:
    agent = Agent(slots=8)
    info = job()
    small, big = unit(0, Rect(0, 0, 8, 8)), unit(1, Rect(0, 0, 16, 16))
    p = Params(6, 4, 2)
    assert agent.state.uncorrected(info, big, p) == pytest.approx(seconds(big.cost, 4, SPEED) + COMPILE_S)
    deliver(agent, only(agent(award(info, small)), FetchBundle))
    assert agent.state.uncorrected(info, big, p) == pytest.approx(seconds(big.cost, 4, SPEED))  # the film's
    assert agent.state.uncorrected(info, big, Params(3, 4, 2)) > seconds(big.cost, 4, SPEED)  # another depth
    assert agent.state.uncorrected(replace(info, level="off"), big, p) > seconds(big.cost, 4, SPEED)


# ---- statuses, stories, invariants ----------------------------------------------------------------------


def statuses(story: list[Transition]) -> list[tuple[str, str | None, str]]:
    return [(t.stimulus_id, t.start, t.finish) for t in story]


def test_the_story_of_a_unit_awarded_fetched_rendered_and_uploaded() -> None:
    agent = Agent()
    t0 = agent.clock.now
    fetch = only(agent(award(job(), unit(0)), sid="award-0"), FetchBundle)
    start = only(agent(BundleReady(fetch.ticket, SCENE), dt=0.5, sid="bundle-1"), StartRender)
    upload = only(agent(RenderFinished(start.ticket, Path("/t.exr"), 1.0), dt=1.0, sid="render-1"), Upload)
    agent(UploadDone(upload.ticket), dt=0.25, sid="upload-1")
    assert agent.state.story("job-1", 0) == [
        Transition("award-0", None, "queued", t0), Transition("award-0", "queued", "fetching", t0),
        Transition("bundle-1", "fetching", "rendering", t0 + 0.5),
        Transition("render-1", "rendering", "uploading", t0 + 1.5),
        Transition("upload-1", "uploading", "done", t0 + 1.75)]
    assert agent.state.story("job-1", 1) == []


def test_the_stories_of_a_batched_a_failed_and_a_cancelled_unit() -> None:
    agent = Agent(slots=6)
    info = job()
    rendered_here(agent, info)
    fetch = only(agent(award(info, unit(0)), sid="award-0"), FetchBundle)
    agent(award(info, unit(1)), sid="award-1")
    agent(award(info, unit(2)), sid="award-2")
    start = only(agent(BundleReady(fetch.ticket, SCENE), sid="bundle"), StartRender)
    assert start.more and start.more[0].award.unit.index == 1
    agent(RenderFailed(start.more[0].ticket, "broke"), sid="render-1")
    agent(m.Cancel(conversation="c-1", job_id="job-1", index=2, reason="x"), sid="cancel-2")
    assert statuses(agent.state.story("job-1", 1)) == [
        ("award-1", None, "queued"), ("bundle", "queued", "rendering"), ("render-1", "rendering", "failed")]
    assert statuses(agent.state.story("job-1", 2))[-1] == ("cancel-2", "rendering", "cancelled")
    assert agent.state.step[-1].status == "cancelled"  # in its step until its render ends


def test_stories_are_bounded_per_unit_and_in_units(monkeypatch: pytest.MonkeyPatch) -> None:
    agent = Agent()
    info = job()
    for n in range(12):  # awarded again after each cancel: three changes a round
        fetch = only(agent(award(info, unit(0), token=f"{n:02d}" * 16), sid=f"award-{n}"), FetchBundle)
        agent(m.Cancel(conversation=f"c-{n}", job_id="job-1", index=0, reason="x"))
        agent(BundleReady(fetch.ticket, SCENE))
    story = agent.state.story("job-1", 0)
    assert len(story) == agent_state.STORY_LENGTH and story[-1].finish == "cancelled"
    monkeypatch.setattr(agent_state, "FINISHED_MEMORY", 2)
    for index in (1, 2):
        deliver(agent, only(agent(award(info, unit(index))), FetchBundle))
    assert agent.state.story("job-1", 0) == [] and agent.state.story("job-1", 2)


def test_the_transitions_table_knows_only_statuses_and_ends_in_done_failed_or_cancelled() -> None:
    known = set(get_args(WorkStatus))
    assert {s for pair in TRANSITIONS for s in pair} == known
    assert not {start for start, _ in TRANSITIONS} & {"done", "failed", "cancelled"}


def test_an_illegal_status_change_raises_naming_the_unit() -> None:
    agent = Agent()
    fetch = only(agent(award(job(), unit(0))), FetchBundle)
    work = agent.state.rendering
    with pytest.raises(TransitionError, match=r"unit 0 of job job-1 .*fetching -> done"):
        agent.state._move(work, "done")
    # A render that never started cannot finish: the stimulus raises before anything changes.
    with pytest.raises(TransitionError, match="fetching -> uploading"):
        agent(RenderFinished(fetch.ticket, Path("/t.exr"), 1.0))
    assert work.status == "fetching" and agent.state.step == [work]
    agent.state.validate()


def test_validate_catches_a_held_unit_missing_from_the_queue() -> None:
    agent = Agent()
    info = job()
    agent(award(info, unit(0)))
    agent(award(info, unit(1)))
    agent.state.queue.clear()
    with pytest.raises(AssertionError, match=r"unit 1 of job job-1 .*not in exactly the collection"):
        agent.state.validate()


def test_validate_catches_a_cancelled_unit_still_held() -> None:
    agent = Agent()
    agent(award(job(), unit(0)))
    agent(m.Cancel(conversation="c-1", job_id="job-1", index=0, reason="x"))
    work = agent.state.step[0]
    agent.state.works[work.key] = work
    with pytest.raises(AssertionError, match=r"unit 0 of job job-1 \(ticket 1, cancelled\): held under"):
        agent.state.validate()


def test_validate_catches_a_step_out_of_step_with_its_statuses() -> None:
    agent = Agent(slots=4)
    start = two_in_one_call(agent, job())
    agent.state.step[1].status = "fetching"
    with pytest.raises(AssertionError, match=r"unit 1 of job job-1 .*fetching, with others in its step"):
        agent.state.validate()
    agent.state.step[1].status = "rendering"
    agent.state.validate()
    agent(RenderFinished(start.ticket, Path("/t.exr"), 1.0))
    agent.state.delivering.clear()  # a tile uploading, forgotten
    with pytest.raises(AssertionError, match=r"unit 0 of job job-1 .*not in exactly the collection"):
        agent.state.validate()


def test_validate_catches_an_idle_render_process_with_units_waiting() -> None:
    agent = Agent()
    info = job()
    agent(award(info, unit(0)))
    agent(award(info, unit(1)))
    agent.state.step.clear()
    agent.state.works.pop(("job-1", 0))
    with pytest.raises(AssertionError, match="no render step, but unit 1 of job job-1"):
        agent.state.validate()


@pytest.mark.parametrize("kind", ["rules", "passes"])
def test_a_jobs_first_unit_here_renders_alone_then_units_batch(kind: str) -> None:
    """Its first call compiles the film's kernel and returns one unit (or pass) soonest: the page's first
    tile; the units waiting meanwhile then render together in the next call."""
    agent = Agent(slots=8)
    info = replace(job(), passes=True, level="off") if kind == "passes" else job()
    passes = [replace(unit(i), spp=4, depth=6) if kind == "passes" else unit(i) for i in range(4)]
    fetch = only(agent(award(info, passes[0])), FetchBundle)
    for p in passes[1:]:
        agent(award(info, p))
    first = only(agent(BundleReady(fetch.ticket, SCENE)), StartRender)
    assert first.more == ()
    out = agent(RenderFinished(first.ticket, Path("/tiles/first.exr"), 0.25), dt=0.25)
    fetch = only(out, FetchBundle)
    second = only(agent(BundleReady(fetch.ticket, SCENE)), StartRender)
    assert [b.award.unit.index for b in second.more] == [2, 3]


def test_each_progressive_job_renders_its_first_pass_here_alone_though_its_kernel_is_compiled() -> None:
    agent = Agent(slots=8)
    for name in ("job-1", "job-2"):  # one scene, one film: job-2's kernel is job-1's
        info = replace(job(name), passes=True, level="off")
        fetch = only(agent(award(info, replace(unit(0), spp=4, depth=6))), FetchBundle)
        agent(award(info, replace(unit(1), spp=4, depth=6)))
        start = only(agent(BundleReady(fetch.ticket, SCENE)), StartRender)
        assert start.more == (), name
        out = agent(RenderFinished(start.ticket, Path(f"/tiles/{name}.exr"), 0.25), dt=0.25)
        rest = only(agent(BundleReady(only(out, FetchBundle).ticket, SCENE)), StartRender)
        out = agent(RenderFinished(rest.ticket, Path(f"/tiles/{name}-1.exr"), 0.25), dt=0.25)
    assert list(agent.state.jobs_rendered) == ["job-1", "job-2"]
