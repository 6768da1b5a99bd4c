"""The contract net and the life-cycle of work units, as a pure state machine (no I/O, no clock of its own).

`Auction.handle(stimulus, now)` is its one entry: stimuli in (`master.auction.stimuli`), instructions out
(`master.auction.instructions`), so the master only delivers messages and records facts, and the same code
runs under the simulated clock of `bench.simulate`. What the rest of the master may read of it is the
read API at the end of the class (frozen views, `master.auction.views`). docs/ARCHITECTURE.md walks a
job through it; the award rule and failure handling are described where they are decided (`_announce`,
`_pick`, `_fail_unit`).
"""

from __future__ import annotations

import dataclasses
import hmac
import itertools
import math
import random
import statistics
from collections import Counter, deque
from collections.abc import Callable, Collection, Iterable, Iterator

from core.errors import MessageError
from core.image.passes import WEIGHT
from core.model import messages as m
from core.model.seeds import unit_seed
from core.model.status import JobStatus, UnitStatus, job_transition, unit_transition
from core.model.units import WorkUnit, batch_size, batched
from master.auction.instructions import (
    AgentBack,
    AgentBlocklisted,
    AgentDrained,
    AgentForgotten,
    AgentJoined,
    AgentLost,
    AgentResumed,
    AgentSilent,
    BidRefused,
    Instruction,
    JobCancelled,
    JobDone,
    JobFailed,
    JobRequeued,
    JobsPaused,
    JobsResumed,
    MessageIgnored,
    PassesOrdered,
    PassesSettled,
    PassesWithdrawn,
    RefuseTile,
    SendToAgent,
    UnitAwarded,
    UnitDone,
    UnitFailed,
    UnitRequeued,
    UnitRetried,
)
from master.auction.passes import PassBook, ResumedPasses
from master.auction.schedule import (
    MAX_RATE,
    MIN_RATE,
    ListSchedule,
    Placement,
    PlanAgent,
    ProjectedUnit,
    refine,
    round_rate,
)
from master.auction.state import (
    NOT_TOLD,
    OPEN,
    Agent,
    Config,
    Job,
    PlansWith,
    ResumedJob,
    Round,
    Transition,
    UnitState,
    Watch,
)
from master.auction.stimuli import (
    AgentDrainRequested,
    AgentResumeRequested,
    DiskFreed,
    DiskFull,
    JobCancelRequested,
    JobRequeueRequested,
    JobSubmitted,
    MessageReceived,
    PassMerged,
    Stimulus,
    Tick,
    TileStored,
    UnitRetryRequested,
)
from master.auction.views import AgentView, AwardView, JobView
from planning.progressive import TIME, Finish, Goal, Idle, PassDone, PassLanded, PassOrder, RenderRound, Withdraw

END = (UnitStatus.DONE, UnitStatus.FAILED)  # a unit's statuses that no award leaves


def _batch_deadlines(job: Job, out: list[Instruction], wins: dict[str, list[UnitState]]) -> list[Instruction]:
    """Units one agent won in one round render in one call and end together, after the last of them would
    have ended one by one: each is given the last one's deadline (its own would pass before the batch ends
    when the others take more than twice its estimate plus the slack)."""
    deadlines = {}
    for won in wins.values():
        last = max(u.deadline for u in won)
        for unit in won:
            job.set_deadline(unit, last)
            deadlines[unit.spec.index] = last
    return [dataclasses.replace(c, deadline=deadlines[c.index]) if isinstance(c, UnitAwarded) else c
            for c in out]


def _origin(job: Job, index: int) -> tuple[int, int] | None:
    """(unit, pass) of a progressive job's unit row `index`, as its records name it; None for a whole unit."""
    return job.passes.origin(index) if job.passes is not None else None


def _own_first(units: tuple[int, ...], agent: str, plan: dict[int, Placement], room: int) -> tuple[int, ...]:
    """The units offered to `agent`, those the projection places on it first where it may win several."""
    if room <= 1:
        return units
    return tuple(sorted(units, key=lambda i: plan[i].agent != agent))


def _excluded(unit: UnitState, usable: Iterable[str]) -> frozenset[str]:
    """The agents not offered `unit`: those it failed on, while one of the `usable` agents (live, answering,
    not blocklisted for the job: `Auction._rates`'s keys) has not. Else none: the unit is retried where it
    failed (a render killed for memory, an agent briefly lost), bounded by `blocklist_after` and
    `max_unit_failures`, rather than failing or stalling its job on a one-agent farm."""
    if not unit.failed_on:
        return frozenset()
    failed = frozenset(unit.failed_on)
    return failed if any(name not in failed for name in usable) else frozenset()


_NONE: frozenset[str] = frozenset()


class _Offers:
    """What `Auction._offers` has read off the projection's placements so far (most costly unit first): each
    free agent's units worth offering, in that order, and whether a later placement could still change the
    offers. One could while a free agent is still `fresh` (the schedule may yet start a unit on it now, which
    others may contest), or while an agent has fewer than it may be offered (`need`) of the units no later
    one would precede in its offer: all of them, or, where it may win a batch (own units first), its own."""

    def __init__(self, room: dict[str, int], cap: int, fresh: set[str], now: float) -> None:
        self.room, self.fresh, self.now = room, fresh, now
        self.worth: dict[str, list[int]] = {name: [] for name in room}
        self.plan: dict[int, Placement] = {}
        self.need = {name: max(1, min(cap, max(len(room), r))) for name, r in room.items()}
        self.counted = dict.fromkeys(room, 0)  # units no later one would precede in the agent's offer
        self.wanting = set(room)  # agents with fewer counted than `need`

    def placed(self, unit: UnitState, place: Placement, bidders: list[str]) -> None:
        """`unit` is placed on one of the free agents (no other placement concerns the offers)."""
        index = unit.spec.index
        self.plan[index] = place
        if place.finish > self.now:
            self.fresh.discard(place.agent)
        for name in bidders:
            self.worth[name].append(index)
            self.counted[name] += self.room[name] <= 1 or place.agent == name
            if self.counted[name] >= self.need[name]:
                self.wanting.discard(name)

    def settled(self) -> bool:
        return not self.fresh and not self.wanting


class _LookAhead:
    """The projection of a job's open units, read most costly first (`Job.open_order`): the list schedule
    placed a unit at a time as it is read, or in the end game (`refined`) the refined schedule, whole. Read
    it before any unit's status changes: all of it, or (`next_placed`) the placements on `watched` agents."""

    def __init__(self, job: Job, agents: list[tuple[str, float, float]], usable: Collection[str],
                 refine_moves: int, watched: Collection[str] = ()) -> None:
        self.job, self.usable, self.watched = job, usable, watched
        self.read = 0  # units of the job's open_order read
        self.refined: dict[int, Placement] | None = None
        self.schedule: ListSchedule | None = None
        if refine_moves:
            self.refined = self._whole([PlanAgent(*a) for a in agents], refine_moves)
        else:
            self.schedule = ListSchedule(agents)

    def _whole(self, agents: list[PlanAgent], refine_moves: int) -> dict[int, Placement]:
        """`project` then `refine`, the units given in the list schedule's order."""
        units = [ProjectedUnit(i, -c, _excluded(self.job.units[i], self.usable)) for c, i in self.job.open_order]
        schedule, plan = ListSchedule(agents), {}
        for unit in units:
            place = schedule.place(unit.cost, unit.excluded)
            if place is not None:
                plan[unit.index] = place
        return refine(plan, units, agents, refine_moves)

    def __iter__(self) -> Iterator[tuple[UnitState, Placement]]:
        for _, index in self.job.open_order:
            unit = self.job.units[index]
            self.read += 1
            place = self._place(unit)
            if place is not None:
                yield unit, place

    def next_placed(self, stop: int) -> tuple[UnitState, Placement] | None:
        """The next unit placed on a watched agent, and its place, reading no further than position `stop`
        of the open units (None: none before it). Units that no agent may have failed on go through
        `ListSchedule.place_until`, a unit at a time but with nothing kept of them."""
        order, stop = self.job.open_order, min(stop, len(self.job.open_order))
        while self.read < stop:
            if self.schedule is not None and not self.job.open_failed:
                self.read = self.schedule.place_until(self.job.open_costs, self.read, stop, self.watched)
                if self.read == stop:
                    break
            unit = self.job.units[order[self.read][1]]
            self.read += 1
            place = self._place(unit)
            if place is not None and place.agent in self.watched:
                return unit, place
        return None

    @property
    def finished(self) -> bool:
        return self.read == len(self.job.open_order)

    def _place(self, unit: UnitState) -> Placement | None:
        if self.schedule is None:
            return self.refined.get(unit.spec.index)
        return self.schedule.place(unit.spec.work, _excluded(unit, self.usable) if unit.failed_on else _NONE)

    def places_none_on(self, names: Collection[str]) -> bool:
        """Whether no unit yet to read is placed on any of `names` (False where that cannot be told: in the
        refined schedule, or where one of them failed before and may exclude agents)."""
        order = self.job.open_order
        if self.read == len(order):
            return True
        if self.schedule is None or self.job.open_failed:
            return False
        return self.schedule.never_places(names, self.job.open_costs[self.read:])


class Auction:
    """The master's state: jobs, units, agents, open auction rounds, and whether jobs are paused.

    Its clock is the master's wall time less the time spent paused (`clock`), so no deadline runs out while
    the disk is full. Every public method taking `now` takes wall time.
    """

    def __init__(
        self,
        config: Config | None = None,
        rng: random.Random | None = None,
        credits: dict[str, int] | None = None,
    ) -> None:
        self.config = config or Config()
        # Records of agents seen before (from the store): applied when each registers again.
        self.known_credits = dict(credits or {})
        # Tokens are secrets: the system source unless a test injects a seeded one.
        self.rng = rng or random.SystemRandom()
        self._jobs: dict[str, Job] = {}
        self._agents: dict[str, Agent] = {}
        self._rounds: dict[str, Round] = {}
        self._watch = Watch()  # the lost, silent and live agents, for the ticks (state.Watch)
        self._paused: tuple[str, float] | None = None  # why jobs stand still, since when (wall time)
        self._paused_s = 0.0  # wall seconds spent paused before that
        self._numbers = itertools.count(1)  # names stimuli that came without one
        self._stimulus_id = ""  # the stimulus being handled, and its auction time: for the units' stories
        self._now = 0.0

    @classmethod
    def restore(
        cls,
        jobs: Iterable[ResumedJob],
        describe: Callable[[str], m.JobInfo],
        credits: dict[str, int] | None = None,
        config: Config | None = None,
        rng: random.Random | None = None,
        now: float = 0.0,
    ) -> tuple[Auction, list[Instruction]]:
        """The auction after a master restart: every running job with its done units and past failures, and
        the agents' records (`credits`, applied as each registers again). `describe` gives a job's CFP
        description (its scene URL depends on where the master serves now); a job it cannot describe fails
        alone. A progressive job brings its goal and its passes so far. Returns the auction and the records of
        resuming (a job that was in fact complete, or failed), for the job store to apply."""
        auction = cls(config, rng, credits=credits)
        out: list[Instruction] = []
        for job in jobs:
            try:
                info = describe(job.job_id)
            except Exception as exc:  # one job the master cannot describe must not stop the others
                out.append(JobFailed(job.job_id, f"cannot resume the job: {type(exc).__name__}: {exc}"))
                continue
            out += auction.handle(JobSubmitted.taken_up(info, job, f"resume-{job.job_id}"), now)
        return auction, out

    # --- the one entry -----------------------------------------------------------------------------------

    def handle(self, stimulus: Stimulus, now: float) -> list[Instruction]:
        """Apply one stimulus at wall time `now`; the instructions to carry out, in order, each naming it."""
        sid = stimulus.stimulus_id or f"{type(stimulus).__name__.lower()}-{next(self._numbers)}"
        self._stimulus_id, self._now = sid, self.clock(now)
        out = self._dispatch(stimulus, now)
        return [i if i.stimulus_id else dataclasses.replace(i, stimulus_id=sid) for i in out]

    def _dispatch(self, stimulus: Stimulus, now: float) -> list[Instruction]:
        clock = self.clock(now)
        match stimulus:
            case MessageReceived():
                return self._on_message(stimulus.sender, stimulus.message, clock)
            case TileStored():
                return self._on_tile(stimulus, clock)
            case PassMerged():
                return self._on_pass_merged(stimulus, clock)
            case Tick():
                return [] if self._paused else self._tick(clock)
            case JobSubmitted():
                return self._add_job(stimulus)
            case JobCancelRequested():
                return self._cancel_job(stimulus.job_id, stimulus.reason)
            case JobRequeueRequested():
                return self._requeue_job(stimulus.job_id, stimulus.taken_up)
            case DiskFull():
                return self._pause("disk full on the master", stimulus.free_bytes, now)
            case DiskFreed():
                return self._resume("space on the master again", stimulus.free_bytes, now)
            case UnitRetryRequested():
                return self._retry_unit(stimulus.job_id, stimulus.index)
            case AgentDrainRequested() | AgentResumeRequested():
                return self._drain(stimulus.agent, isinstance(stimulus, AgentDrainRequested))
        raise TypeError(f"not a stimulus of the auction: {type(stimulus).__name__}")

    # --- the read API: what the master, its page and its job API may know --------------------------------

    def clock(self, now: float) -> float:
        """The auction's time at wall time `now`: less the time jobs stood paused."""
        paused = now - self._paused[1] if self._paused else 0.0
        return now - self._paused_s - paused

    @property
    def paused(self) -> str | None:
        """Why every job stands still (the disk is full), or None."""
        return self._paused[0] if self._paused else None

    def award_for(self, job_id: str, index: int, token: str) -> AwardView | None:
        """The unit's current award, if `token` is its token (compared in constant time); else None."""
        unit, _ = self._check_award(job_id, index, token)
        if unit is None:
            return None
        info = self._jobs[job_id].info
        return AwardView(job_id, index, unit.agent, unit.conversation, unit.spec.rect, (info.width, info.height))

    def holds_award(self, job_id: str, token: str) -> bool:
        """Whether `token` is the token of a current award of one of the job's units (a bundle's fetch)."""
        job = self._jobs.get(job_id)
        return job is not None and any(self._check_award(job_id, i, token)[0] is not None for i in job.units)

    def job_view(self, job_id: str) -> JobView | None:
        """A job the auction knows (running or ended since the master started), or None."""
        job = self._jobs.get(job_id)
        if job is None:
            return None
        return JobView(job_id, job.status.value, job.error, dict(self.counts(job_id)), tuple(sorted(job.blocklist)))

    def job_passes(self, job_id: str) -> int:
        """A progressive job's unit count (its passes' work units: master.auction.passes); 0 for any other."""
        job = self._jobs.get(job_id)
        return len(job.passes.units) if job is not None and job.passes is not None else 0

    def merges_passes(self, job_id: str) -> bool:
        """Whether the job's passes are merged as they land (PassMerged): a noise or time goal decides on
        their noise; a budget job only counts them."""
        job = self._jobs.get(job_id)
        return job is not None and job.passes is not None and job.passes.merges

    def job_status(self, job_id: str) -> str | None:
        """The job's status ('running', 'done', ...), or None for a job the auction does not know."""
        job = self._jobs.get(job_id)
        return None if job is None else job.status.value

    def counts(self, job_id: str) -> Counter[str]:
        """The job's units per status."""
        return Counter(u.status.value for u in self._jobs[job_id].units.values())

    def agent_views(self, now: float) -> list[AgentView]:
        """Every agent the master knows, in the order it first heard from them."""
        clock = self.clock(now)
        running = self._running()
        return [AgentView(a.name, a.lost, a.credits, a.speed, tuple(sorted(f"{j}/{i}" for j, i in a.holding)),
                          round(max(0.0, clock - a.last_seen), 1),
                          tuple(j.info.job_id for j in running if a.name in j.blocklist), a.threads, a.draining,
                          a.host)
                for a in self._agents.values()]

    def live_agents(self) -> int:
        """Agents heard from within the heartbeat timeout."""
        return sum(not a.lost for a in self._agents.values())

    def story(self, job_id: str, index: int) -> list[Transition]:
        """The unit's changes of status, oldest first (at most `state.STORY_LENGTH`), each with its stimulus;
        empty for a unit the auction does not know."""
        job = self._jobs.get(job_id)
        unit = job.units.get(index) if job else None
        return list(unit.story) if unit else []

    def validate(self) -> None:
        """AssertionError naming the first broken invariant between units, agents and rounds (tests run
        it after every stimulus)."""
        in_rounds = Counter((r.job_id, i) for r in self._rounds.values() for i in r.units)
        for job in self._jobs.values():
            for unit in job.units.values():
                _check_unit(self, job, unit, in_rounds[job.info.job_id, unit.spec.index])
            statuses = {u.status for u in job.units.values()}
            indexed = {i: status for status, indices in job.by_status.items() for i in indices}
            assert indexed == {i: u.status for i, u in job.units.items()}, f"job {job.info.job_id}: by_status is stale"
            _check_open(job)
            if job.passes is not None:  # a progressive job ends with the passes still out cancelled
                assert job.status == JobStatus.RUNNING or statuses <= {UnitStatus.DONE, UnitStatus.FAILED}, \
                    f"job {job.info.job_id}: {job.status.value} with units {sorted(statuses)}"
            elif job.status == JobStatus.DONE or (job.status == JobStatus.RUNNING and statuses == {UnitStatus.DONE}):
                assert statuses == {UnitStatus.DONE} and job.status == JobStatus.DONE, f"job {job.info.job_id}: " \
                    f"{job.status.value} with units {sorted(statuses)}"
            if job.status in (JobStatus.FAILED, JobStatus.CANCELLED):
                assert statuses <= {UnitStatus.DONE, UnitStatus.FAILED}, f"job {job.info.job_id} ended with " \
                    f"units {sorted(statuses)}"
            blocked = {a for a, n in job.failures_by_agent.items() if n >= self.config.blocklist_after}
            assert job.blocklist <= blocked, f"job {job.info.job_id}: blocklist {job.blocklist} beyond {blocked}"
        self._check_watch()
        for agent in self._agents.values():
            for job_id, index in agent.holding:
                unit = self._jobs[job_id].units[index]
                assert unit.status == UnitStatus.AWARDED and unit.agent == agent.name, \
                    f"agent {agent.name} holds unit {index} of job {job_id}, {unit.status.value} to {unit.agent}"
            if agent.invited is not None:
                round_ = self._rounds.get(agent.invited)
                assert round_ is not None and agent.name in round_.offered, \
                    f"agent {agent.name} invited to round {agent.invited}, which does not call it"

    def _check_watch(self) -> None:
        """The invariants of what the auction keeps of its agents for its ticks (`Watch`, `Agent.held_end`)."""
        agents, beats = self._agents.values(), set(self._watch.beats)
        assert self._watch.lost == {a.name for a in agents if a.lost}, "Watch.lost is stale"
        assert self._watch.silent == {a.name for a in agents if a.silent_until is not None}, "Watch.silent is stale"
        assert self._watch.callable == {a.name for a in agents if self._callable(a)}, "Watch.callable is stale"
        for agent in agents:
            assert agent.held_end == self._held_end(agent), f"agent {agent.name}: held_end is stale"
            assert agent.lost or (agent.last_seen, agent.name) in beats, f"agent {agent.name}: no current beat"

    # --- set-up --------------------------------------------------------------------------------------

    def _add_job(self, submitted: JobSubmitted) -> list[Instruction]:
        """Start auctioning a job's units (`JobSubmitted` says what a resumed job brings)."""
        info, units, done = submitted.info, submitted.units, set(submitted.done)
        if info.job_id in self._jobs:
            raise ValueError(f"job {info.job_id!r} already known")
        if len({u.index for u in units}) != len(units) or not units:
            raise ValueError(f"job {info.job_id!r}: unit indices must be unique and non-empty")
        if done - {u.index for u in units}:
            raise ValueError(f"job {info.job_id!r}: done units {sorted(done - {u.index for u in units})} unknown")
        # Units done before a restart start as done: a state, not a change of it.
        states = {u.index: UnitState(u, UnitStatus.DONE if u.index in done else UnitStatus.PENDING) for u in units}
        for index, agent, reason in submitted.failures:  # before the job indexes its units (Job.open_failed)
            unit = states[index]
            unit.failures += 1
            unit.failed_on.add(agent)
            unit.last_reason = reason
        job = Job(info, states, order=len(self._jobs), channels=submitted.channels)
        job.failures_by_agent.update(agent for _, agent, _ in submitted.failures)
        for index, agent in submitted.delivered_by.items():
            if index in done:
                job.units[index].delivered_by = agent
        job.blocklist = {a for a, n in job.failures_by_agent.items() if n >= self.config.blocklist_after}
        self._jobs[info.job_id] = job
        if submitted.goal is not None:
            return self._open_passes(job, submitted.goal, tuple(units), submitted.resumed)
        return self._finish_if_done(job) + self._fail_if_stuck(job)

    def _register(self, agent: str, now: float, speed: float = 1.0, credits: int = 0,
                 registered: bool = True, slots: int | None = None,
                 rules: PlansWith = NOT_TOLD) -> list[Instruction]:
        """An agent announces itself (or comes back); its record (credits) may come from the store.
        `registered` False: heard from by heartbeat only, at speed 1.0 until its Register comes. `slots`:
        the units it told it holds at once (None: the master's `Config.slots`); `rules`: its rule file's
        sha256 and defuzzifier (None: not told)."""
        known = self._agents.get(agent)
        if known is None:
            credits = self.known_credits.get(agent, credits)
            known = self._agents[agent] = Agent(agent, now, credits=credits, speed=speed, registered=registered,
                                               slots=slots, rules=rules)
            known.recent = deque(maxlen=self.config.recent_window)
            self._watch.beat(known)
            self._recheck(known)
            return [AgentJoined(agent, speed)]
        known.speed = speed
        known.registered = True
        known.slots = slots if registered else known.slots
        known.rules = rules if registered else known.rules
        out = self._seen(known, now)
        self._recheck(known)
        return out

    def plan_alike(self, rules_sha256: str | None, defuzzifier: str | None) -> bool:
        """Whether every live agent plans a job's units as the master's plan does: a job without rules of its
        own with the master's rules (`rules_sha256`; None: the job has its own, which every agent takes),
        and each agent its own defuzzifier where the job names none (`defuzzifier`). False without live
        agents, or with one that did not tell its rules (an agent known from heartbeats alone)."""
        live = [a for a in self._agents.values() if not a.lost]
        return bool(live) and all(
            a.rules.rules_sha256 is not None and (rules_sha256 is None or a.rules.rules_sha256 == rules_sha256)
            and (defuzzifier is not None or a.rules.defuzzifier is None) for a in live)

    # --- messages in ---------------------------------------------------------------------------------

    def _on_message(self, sender: str, msg: m.Message, now: float) -> list[Instruction]:
        """Dispatch a parsed message from `sender` (a JID the transport has already authenticated)."""
        match msg:
            case m.Register():
                welcome = SendToAgent(sender, m.Welcome(conversation=msg.conversation))  # the agent retries until it
                out = self._register(sender, now, speed=msg.speed, slots=msg.slots,
                                     rules=PlansWith(msg.rules_sha256, msg.defuzzifier))
                self._agents[sender].threads, self._agents[sender].host = msg.threads, msg.host
                return [*out, welcome]
            case m.Heartbeat():
                return self._on_heartbeat(sender, msg, now)
            case m.Propose():
                return self._on_propose(sender, msg, now)
            case m.Refuse():
                return self._on_refuse(sender, msg, now)
            case m.Inform():
                # A unit is done only once its tile is durable (TileStored).
                return [_ignored(sender, "an inform counts only through its tile's upload", msg.job_id, msg.index)]
            case m.Failure():
                # A local farm's agents write their tiles on the master's disk: a failure while it is full
                # may be the disk's, and is not held against the agent.
                return self._on_failure(sender, msg, blame=not self._paused)
        return [_ignored(sender, f"{msg.performative} is not a message the master accepts")]

    def _on_heartbeat(self, agent: str, msg: m.Heartbeat, now: float) -> list[Instruction]:
        """Agent alive; units it holds are reconciled with the awards (lost awards, stale work)."""
        known = self._agents.get(agent)
        out = self._register(agent, now, registered=False) if known is None else self._seen(known, now)
        state = self._agents[agent]
        if not state.registered:  # e.g. this master restarted while the agent stayed connected
            out.append(SendToAgent(agent, m.Introduce(conversation=self._new_id())))
        busy = {(b.job_id, b.index) for b in msg.busy}
        for key in sorted(state.holding - busy):
            unit = self._jobs[key[0]].units[key[1]]
            if now - unit.awarded_at > self.config.award_grace_s:
                out += self._requeue(key, "award not acknowledged by the agent")
        for job_id, index in sorted(busy - state.holding):
            if self._delivered(agent, job_id, index):
                continue  # a heartbeat sent while its tile's upload was ending: the unit is done, by it
            # Work the master did not award to it (revoked, or before a master restart): stop it.
            cancel = m.Cancel(
                conversation=self._new_id(), job_id=job_id, index=index, reason="not awarded to you"
            )
            out.append(SendToAgent(agent, cancel))
        return out

    def _on_propose(self, agent: str, msg: m.Propose, now: float) -> list[Instruction]:
        round_, why = self._round_for(agent, msg.conversation, msg.job_id)
        if round_ is None:
            return [_ignored(agent, why, msg.job_id)]
        offered = set(round_.offered[agent])
        bids = {e.index: e.seconds for e in msg.estimates if e.index in offered}
        round_.bids[agent] = bids
        self._answered(round_, agent)
        self._learn_rate(self._agents[agent], self._jobs[round_.job_id], bids)
        return (
            []
            if len(bids) == len(msg.estimates)
            else [_ignored(agent, "bid on units not offered", msg.job_id)]
        )

    def _on_refuse(self, agent: str, msg: m.Refuse, now: float) -> list[Instruction]:
        round_, why = self._round_for(agent, msg.conversation, msg.job_id)
        if round_ is None:
            return [_ignored(agent, why, msg.job_id)]
        self._answered(round_, agent)
        return [BidRefused(msg.job_id, agent, msg.reason)]

    def _answered(self, round_: Round, agent: str) -> None:
        round_.answered.add(agent)
        state = self._agents[agent]
        state.silences, state.silent_until = 0, None
        self._watch.silent.discard(agent)
        self._recheck(state)

    def _on_tile(self, tile: TileStored, now: float) -> list[Instruction]:
        """A tile of the unit's current award is stored: the unit is done, unless the tile claims what the plan
        forbids (then the upload is refused, and the agent's report of that failure fails the unit)."""
        unit, why = self._check_award(tile.job_id, tile.index, tile.token)
        if unit is None:
            return [_ignored(None, f"tile: {why}", tile.job_id, tile.index)]
        job = self._jobs[tile.job_id]
        refused = _tile_refusal(job, unit.spec, tile)
        if refused:
            return [RefuseTile(tile.job_id, tile.index, refused)]
        agent, seconds = unit.agent, tile.figures.seconds
        state = self._agents[agent]
        self._release(state, (tile.job_id, tile.index))
        on_time = seconds <= unit.estimate * (1 + self.config.credit_tolerance)
        state.credits += 1 if on_time else -1
        if on_time:
            state.late_rates.pop(tile.job_id, None)
        elif unit.spec.work > 0:
            state.late_rates[tile.job_id] = round_rate(min(seconds / unit.spec.work, MAX_RATE))
        state.recent.append(True)
        out: list[Instruction] = [
            UnitDone(tile.job_id, tile.index, agent, unit.token, seconds=seconds, estimate=unit.estimate,
                     tile_path=tile.tile_path, tile_hash=tile.sha256, report=tile.stored(agent),
                     credits=state.credits, on_time=on_time, origin=_origin(job, tile.index))]
        self._clear_award(job, unit, UnitStatus.DONE)
        unit.delivered_by = agent
        if job.passes is not None:
            out += self._follow(job, job.passes.machine.handle(PassLanded(*job.passes.origin(tile.index))),
                                "a pass landed")
        if job.passes is not None and not job.passes.merges:  # a budget job counts its passes, unmerged
            return [*out, *self._on_pass_merged(PassMerged(tile.job_id, tile.index, 0, 0.0, None), now)]
        return [*out, *self._finish_if_done(job)]  # a progressive job ends on its passes' decision instead

    def _delivered(self, agent: str, job_id: str, index: int) -> bool:
        """Whether the unit is done by this agent's tile."""
        job = self._jobs.get(job_id)
        unit = job.units.get(index) if job else None
        return unit is not None and unit.status == UnitStatus.DONE and unit.delivered_by == agent

    def _on_failure(self, agent: str, msg: m.Failure, blame: bool) -> list[Instruction]:
        """The agent could not render its unit: the unit fails on it (counted against it, toward its
        blocklisting), or without `blame` goes back to the auction (a failure the farm's own state may
        have caused, such as the master's disk being full)."""
        unit, why = self._check_award(msg.job_id, msg.index, msg.token, agent, msg.conversation)
        if unit is None:
            return [_ignored(agent, why, msg.job_id, msg.index)]
        if not blame:
            return self._requeue((msg.job_id, msg.index), f"failed on {agent}, not counted: {msg.reason}")
        return self._fail_unit((msg.job_id, msg.index), f"failed on {agent}: {msg.reason}")

    # --- time passes ---------------------------------------------------------------------------------

    def _tick(self, now: float) -> list[Instruction]:
        """Everything due at `now`: timeouts, then auctions to resolve, then new calls for proposals."""
        return self._expire(now) + self._decide(now) + self._announce(now)

    def _expire(self, now: float) -> list[Instruction]:
        """Lost agents give their units back; units past their render deadline are failed on their agent."""
        out: list[Instruction] = []
        oldest = self._watch.oldest_beat(self._agents)
        silent_long = oldest is not None and now - oldest > self.config.heartbeat_timeout_s
        for state in self._agents.values() if silent_long else ():
            if not state.lost and now - state.last_seen > self.config.heartbeat_timeout_s:
                state.lost = True
                self._watch.lost.add(state.name)
                out.append(AgentLost(state.name, "no heartbeat"))
                for key in sorted(state.holding):
                    out += self._requeue(key, f"agent {state.name} lost")
                if state.invited in self._rounds:
                    self._rounds[state.invited].offered.pop(state.name, None)
                state.invited = None
                self._recheck(state)
        out += self._forget_lost(now)
        for job in self._running():
            for unit in job.pop_late(now):
                if now > unit.deadline:  # a failure before may have stopped the job
                    holder = unit.agent
                    out.append(
                        SendToAgent(
                            holder,
                            m.Cancel(
                                conversation=unit.conversation,
                                job_id=job.info.job_id,
                                index=unit.spec.index,
                                reason="render deadline passed",
                            ),
                        )
                    )
                    out += self._fail_unit(
                        (job.info.job_id, unit.spec.index), f"render deadline passed on {holder}"
                    )
        for job in self._running():
            out += self._fail_if_stuck(job)
        return out

    def _decide(self, now: float) -> list[Instruction]:
        """Resolve rounds whose deadline passed or whose invited agents all answered."""
        out: list[Instruction] = []
        for conv, round_ in list(self._rounds.items()):
            if now >= round_.deadline or set(round_.offered) <= round_.answered:
                del self._rounds[conv]
                out += self._resolve(round_, now)
        return out

    def _announce(self, now: float) -> list[Instruction]:
        """Calls for proposals: each free agent is offered the pending units the projection gives it, and
        those it would finish about as soon as the free agent they are projected to (module docstring)."""
        out: list[Instruction] = []
        for name in sorted(self._watch.silent):
            agent = self._agents[name]
            if now >= agent.silent_until:
                agent.silent_until = None  # called again; its silences count on until it answers
                self._watch.silent.discard(name)
                self._recheck(agent)
        open_units = sum(len(j.by_status.get(UnitStatus.PENDING, ())) for j in self._running())
        free_when: dict[bool, list[Agent]] = {}  # the free agents, whether units may queue or not
        for job in self._running():
            queueing = self._queueing(job, open_units)
            if queueing not in free_when:
                free_when[queueing] = self._free(queueing)
            free = free_when[queueing]
            callable_now = {a.name for a in free if a.invited is None}  # earlier jobs' rounds took some
            agents = [a for a in free if a.name in callable_now and a.name not in job.blocklist]
            out += self._extra_passes(job, agents)
            if not agents or not job.by_status.get(UnitStatus.PENDING):
                continue
            offered, room = self._offers(job, agents, queueing, now)
            if not offered:
                continue
            conv = self._new_id()
            held = frozenset(i for indices in offered.values() for i in indices)
            self._rounds[conv] = Round(conv, job.info.job_id, offered, held, now + self.config.cfp_timeout_s, room)
            for index in sorted(held):
                self._set_unit(job, job.units[index], UnitStatus.ANNOUNCED)
            for name, indices in offered.items():
                self._agents[name].invited = conv
                self._recheck(self._agents[name])
                specs = tuple(job.units[i].spec for i in indices)
                cfp = m.CallForProposal(
                    conversation=conv, job=job.info, units=specs, reply_within_s=self.config.cfp_timeout_s
                )
                out.append(SendToAgent(name, cfp))
        return out

    def _offers(self, job: Job, agents: list[Agent], queueing: bool,
                now: float) -> tuple[dict[str, tuple[int, ...]], dict[str, int]]:
        """The pending units each of the free `agents` is called to bid on, and the units each may win: those
        the projection places on it, and those placed first on another of them that it would finish about as
        soon (`_worth_offering`). No agent is offered more units than the round calls agents or than it may
        win; one that may win a batch is offered the units projected to it first, so that the agents'
        batches differ. The placements are read most costly first, and only until no later one could change
        the offers (`_Offers.settled`)."""
        rates = self._rates(job)
        room = {a.name: self._room(a, queueing, job) for a in agents}
        fresh = {a.name for a in agents if self._available(a, now) <= now}
        scan = _Offers(room, self.config.max_cfp_units, fresh, now)
        look, check = self._look_ahead(job, now, rates, room.keys()), 2 * len(agents) + 32
        while not scan.settled():
            got = look.next_placed(check)  # on a free agent: the placements the offers read
            if got is not None:
                scan.placed(*got, self._bidders(*got, scan, rates, now))
            elif look.finished or (not scan.fresh and look.places_none_on(scan.wanting)):
                break  # the rest may never reach the agents still wanting
            else:
                check *= 2
        offered = {name: tuple(units) for name, units in scan.worth.items() if units}
        cap = {name: min(self.config.max_cfp_units, max(len(offered), room[name])) for name in offered}
        return {name: _own_first(units, name, scan.plan, room[name])[:cap[name]]
                for name, units in offered.items()}, {name: room[name] for name in offered}

    def _bidders(self, unit: UnitState, place: Placement, scan: _Offers, rates: dict[str, float],
                 now: float) -> list[str]:
        """The free agents `unit`, placed at `place` on a free agent, is worth offering to: that agent; and
        while it would start the unit now, any other that would finish it about as soon (records decide)."""
        if unit.status != UnitStatus.PENDING:
            return []
        excluded = _excluded(unit, rates.keys())
        names = [place.agent] if place.agent not in excluded else []
        if place.start <= now:
            names += [name for name in scan.worth if name != place.agent and name not in excluded
                      and self._worth_offering(name, unit, place, rates, now)]
        return names

    def projection(self, job_id: str, now: float) -> dict[int, Placement]:
        """Where the look-ahead would place each open (pending or announced) unit of the job at `now`."""
        job = self._jobs[job_id]
        return self._project(job, self.clock(now), self._rates(job))

    def rate(self, agent: str, job_id: str) -> float:
        """Seconds per unit of cost the projection assumes for `agent` on the job."""
        job = self._jobs[job_id]
        rates = self._rates(job)
        return rates[agent] if agent in rates else self._prior_rate(self._agents[agent], self._typical(rates))

    def next_deadline(self) -> float | None:
        """The earliest auction time (`clock`) at which a Tick has something to do without a new stimulus."""
        times = [r.deadline for r in self._rounds.values()]
        oldest = self._watch.oldest_beat(self._agents)  # + the timeout: the first live agent's
        times += [] if oldest is None else [oldest + self.config.heartbeat_timeout_s]
        times += [self._agents[n].last_seen + self.config.forget_lost_s for n in self._watch.lost]
        times += [self._agents[n].silent_until for n in self._watch.silent]
        times += [t for t in (job.next_due() for job in self._running()) if t is not None]
        return min(filter(math.isfinite, times), default=None)

    def _pause(self, reason: str, free_bytes: int, now: float) -> list[Instruction]:
        if self._paused:
            return []
        self._paused = (reason, now)
        return [JobsPaused(reason, free_bytes)]

    def _resume(self, reason: str, free_bytes: int, now: float) -> list[Instruction]:
        if not self._paused:
            return []
        self._paused_s += now - self._paused[1]
        self._paused = None
        return [JobsResumed(reason, free_bytes)]

    def _retry_unit(self, job_id: str, index: int) -> list[Instruction]:
        """A done unit back to the auction at the user's request; a done job runs again for it. Refused (an
        ignored record saying why) for a unit not done, a job ended otherwise, or a job in passes (its units
        are merged from passes, each decided on by its goal)."""
        job = self._jobs.get(job_id)
        unit = job.units.get(index) if job else None
        if job is None or unit is None:
            return [_ignored(None, "no such unit in a job the master auctions", job_id, index)]
        if job.passes is not None:
            why = "a job in passes renders its units in passes until its goal: a unit is not retried alone"
            return [_ignored(None, why, job_id, index)]
        if unit.status != UnitStatus.DONE or job.status not in (JobStatus.RUNNING, JobStatus.DONE):
            why = f"the unit is {unit.status.value} and its job {job.status.value}: only a done unit is retried"
            return [_ignored(None, why, job_id, index)]
        if job.status == JobStatus.DONE:
            self._set_job(job, JobStatus.RUNNING)
        self._set_unit(job, unit, UnitStatus.PENDING)
        unit.delivered_by = None
        return [UnitRetried(job_id, index, "asked by the user")]

    def _requeue_job(self, job_id: str, taken_up: JobSubmitted | None) -> list[Instruction]:
        """A failed or cancelled job runs again: its units not done back to pending, its done ones kept, its
        failures forgiven (else the unit that failed it would fail it again at once). A job the auction does
        not know comes `taken_up` from the store and is auctioned as a restart takes up a running one.
        Refused (an ignored record saying why) for a running or done job, and for a job with a time goal."""
        job = self._jobs.get(job_id)
        goal = job.passes.machine.goal if job is not None and job.passes else taken_up.goal if taken_up else None
        if job is None and (taken_up is None or taken_up.info.job_id != job_id):
            return [_ignored(None, "no job of that id the master auctions", job_id)]
        if job is not None and job.status in (JobStatus.RUNNING, JobStatus.DONE):
            why = "it is running" if job.status == JobStatus.RUNNING else \
                "it is done: render one of its units again (retry) instead"
            return [_ignored(None, f"only a failed or cancelled job is requeued: {why}", job_id)]
        if goal is not None and goal.kind == TIME:
            why = "a job with a time goal spends its seconds from its first pass: submit it again instead"
            return [_ignored(None, why, job_id)]
        if job is None:
            units = tuple(sorted({u.index for u in taken_up.units} - taken_up.done))
            requeued = JobRequeued(job_id, units, len(units), "asked by the user")
            return [requeued, *self._add_job(dataclasses.replace(taken_up, failures=()))]
        self._close_rounds(job_id)  # its units announced when it ended are announced afresh
        job.failures_by_agent.clear()
        job.blocklist.clear()
        units = [u for u in job.having(UnitStatus.FAILED) if not u.withdrawn]
        for unit in job.units.values():  # before they reopen (Job.open_failed)
            unit.failures, unit.last_reason = 0, ""
            unit.failed_on.clear()
        for unit in units:
            self._set_unit(job, unit, UnitStatus.PENDING)
        self._set_job(job, JobStatus.RUNNING)
        job.error = ""
        indices = tuple(u.spec.index for u in units)
        return [JobRequeued(job_id, indices, len(indices), "asked by the user")]

    def _close_rounds(self, job_id: str) -> None:
        """The ended job's open rounds close before their time: no award, and no agent called to them is
        held to an answer."""
        for conversation, round_ in list(self._rounds.items()):
            if round_.job_id == job_id:
                del self._rounds[conversation]
                self._uninvite(round_)

    def _drain(self, name: str, drain: bool) -> list[Instruction]:
        """Drain an agent (no new award; it finishes what it holds) or resume it; a change that changes
        nothing is ignored, saying why."""
        agent = self._agents.get(name)
        if agent is None:
            return [_ignored(None, f"no agent {name} is known")]
        if agent.draining == drain:
            return [_ignored(None, f"agent {name} is {'already draining' if drain else 'not draining'}")]
        agent.draining = drain
        self._recheck(agent)
        return [AgentDrained(name, len(agent.holding)) if drain else AgentResumed(name)]

    def _cancel_job(self, job_id: str, reason: str) -> list[Instruction]:
        job = self._jobs.get(job_id)
        if job is None or job.status != JobStatus.RUNNING:
            return [_ignored(None, "no running job of that id", job_id)]
        out = self._stop_job(job, JobStatus.CANCELLED, reason)
        return [*out, JobCancelled(job_id, reason)]

    # --- internals -----------------------------------------------------------------------------------

    def _new_id(self) -> str:
        return f"{self.rng.getrandbits(64):016x}"

    def _forget_lost(self, now: float) -> list[Instruction]:
        if not any(self._forgotten(self._agents[n], now) for n in self._watch.lost):
            return []
        stale = [a for a in self._agents.values() if self._forgotten(a, now)]
        for agent in stale:
            self.known_credits[agent.name] = agent.credits
            del self._agents[agent.name]
            self._watch.lost.discard(agent.name)
            self._watch.silent.discard(agent.name)
            self._watch.callable.discard(agent.name)
        return [AgentForgotten(a.name) for a in stale]

    def _forgotten(self, agent: Agent, now: float) -> bool:
        return agent.lost and not agent.holding and now - agent.last_seen > self.config.forget_lost_s

    def _running(self) -> list[Job]:
        return sorted((j for j in self._jobs.values() if j.status == JobStatus.RUNNING), key=lambda j: j.order)

    def _free(self, queueing: bool) -> list[Agent]:
        """The agents callable to an auction, best record first (then by name): live, not in one already, not
        silent, and holding nothing, or with a slot for another unit while the farm has plenty of work
        (`queueing`, from `_queueing`, decided per job at each call)."""
        free = [a for a in map(self._agents.__getitem__, self._watch.callable) if queueing or not a.holding]
        return sorted(free, key=lambda a: (-a.score, a.name))

    def _callable(self, agent: Agent) -> bool:
        """Live, not drained, not in an auction already, not silent, and holding nothing or fewer units than
        its slots."""
        return agent.invited is None and agent.silent_until is None and not agent.lost and not agent.draining \
            and (not agent.holding or len(agent.holding) < self._slots(agent))

    def _recheck(self, agent: Agent) -> None:
        """Keep `Watch.callable` after a change of what `_callable` reads of the agent."""
        (self._watch.callable.add if self._callable(agent) else self._watch.callable.discard)(agent.name)

    def _room(self, agent: Agent, queueing: bool, job: Job) -> int:
        """Units a free agent may win in one round of `job`: a batch (`_batch`), within its free slots while
        units may queue; in the end game one batch, and only when it holds nothing."""
        slots = self._slots(agent)
        batch = self._batch(job, slots)
        if agent.holding:
            return min(batch, slots - len(agent.holding)) if queueing else 0
        return batch

    def _slots(self, agent: Agent) -> int:
        """Units the agent may hold: the master's `Config.slots`, or fewer where its Register said so."""
        return min(self.config.slots, agent.slots or self.config.slots)

    @staticmethod
    def _batch(job: Job, slots: int) -> int:
        """Units of `job` an agent with `slots` renders in one call and wins in one round: `batch_size`, or
        one where its units render one a call (level off, two-pass units)."""
        return batch_size(slots) if batched(job.info.level, job.info.first_spp, job.info.passes, job.info.spill) else 1

    def _queueing(self, job: Job, open_units: int) -> bool:
        """Whether units of `job` may be queued behind others: only while the farm's `open_units` are at
        least max(two of its batches, `queue_above`) per live agent (see `Config.queue_above`)."""
        live = len(self._agents) - len(self._watch.lost)
        return open_units >= max(2 * self._batch(job, self.config.slots), self.config.queue_above) * live

    def _seen(self, agent: Agent, now: float) -> list[Instruction]:
        seen = agent.last_seen
        agent.last_seen = max(agent.last_seen, now)
        if agent.lost:
            # Back from an outage long enough to lose it: the calls it missed meanwhile are not held against it.
            agent.lost, agent.silences, agent.silent_until = False, 0, None
            self._watch.lost.discard(agent.name)
            self._watch.silent.discard(agent.name)
            self._watch.beat(agent)
            self._recheck(agent)
            return [AgentBack(agent.name)]
        if agent.last_seen != seen:
            self._watch.beat(agent)
        return []

    def _round_for(self, agent: str, conversation: str, job_id: str) -> tuple[Round | None, str]:
        round_ = self._rounds.get(conversation)
        if round_ is None:
            return None, "no open auction with that conversation id"
        if agent not in round_.offered:
            return None, "agent not called to this auction"
        if job_id != round_.job_id:
            return None, "job id does not match the auction"
        if agent in round_.answered:
            return None, "already answered this auction"
        return round_, ""

    def _check_award(self, job_id: str, index: int, token: str, agent: str | None = None,
                     conv: str | None = None) -> tuple[UnitState | None, str]:
        """The unit if it is awarded and `token` is its award's (and, where given, to `agent` in `conv`): the
        one check of an award, for messages, tiles and bundles. Else None and why."""
        job = self._jobs.get(job_id)
        unit = job.units.get(index) if job else None
        if unit is None:
            return None, "unknown job or unit"
        if unit.status == UnitStatus.DONE:
            return None, "unit already done"
        if job.status != JobStatus.RUNNING:
            return None, f"job is {job.status.value}"
        if unit.status != UnitStatus.AWARDED or agent not in (None, unit.agent):
            return None, "unit not awarded to this agent"
        if not hmac.compare_digest(unit.token.encode(), token.encode()):
            return None, "wrong token"
        if conv not in (None, unit.conversation):
            return None, "wrong conversation id"
        return unit, ""

    def _resolve(self, round_: Round, now: float) -> list[Instruction]:
        job = self._jobs.get(round_.job_id)
        self._uninvite(round_)
        out: list[Instruction] = self._silenced(round_, now)
        if job is None or job.status != JobStatus.RUNNING:
            return out
        wins: dict[str, list[UnitState]] = {}
        units = sorted((job.units[i] for i in round_.units), key=lambda u: (-u.spec.work, u.spec.index))
        usable = self._rates(job).keys() if any(u.failed_on for u in units) else ()  # for `_excluded`
        drained = {name for name in round_.offered if name in self._agents and self._agents[name].draining}
        for unit in units:
            if unit.status != UnitStatus.ANNOUNCED:
                continue
            full = drained | {name for name, won in wins.items() if len(won) >= round_.room.get(name, 1)}
            winner = self._pick(round_, unit, job, full, now, _excluded(unit, usable))
            if winner is None:
                self._set_unit(job, unit, UnitStatus.PENDING)
            else:
                wins.setdefault(winner, []).append(unit)
                out += self._award(job, unit, winner, round_.bids[winner][unit.spec.index], now)
        out = _batch_deadlines(job, out, wins)
        for name in sorted(set(round_.bids) - set(wins)):
            if name in self._agents and round_.bids[name]:
                reject = m.Reject(
                    conversation=round_.conversation,
                    job_id=job.info.job_id,
                    reason="units awarded to other agents",
                )
                out.append(SendToAgent(name, reject))
        return out

    def _uninvite(self, round_: Round) -> None:
        """The agents called to `round_`, which has closed, may be called to another."""
        for name in round_.offered:
            if name in self._agents and self._agents[name].invited == round_.conversation:
                self._agents[name].invited = None
                self._recheck(self._agents[name])

    def _silenced(self, round_: Round, now: float) -> list[Instruction]:
        """The agents called to `round_` that never answered, each left out of auctions for a while."""
        out: list[Instruction] = []
        for name in sorted(set(round_.offered) - round_.answered):
            agent = self._agents.get(name)
            if agent is None or agent.lost:
                continue
            agent.silences += 1
            pause = min(self.config.silence_max_s, self.config.cfp_timeout_s * 2 ** (agent.silences - 1))
            agent.silent_until = now + pause
            self._watch.silent.add(name)
            self._recheck(agent)
            out.append(AgentSilent(name, pause))
        return out

    # --- the look-ahead --------------------------------------------------------------------------------

    def _project(self, job: Job, now: float, rates: dict[str, float]) -> dict[int, Placement]:
        """The list schedule of the job's pending and announced units on `rates`' agents, refined in the end
        game."""
        return {unit.spec.index: place for unit, place in self._look_ahead(job, now, rates)}

    def _look_ahead(self, job: Job, now: float, rates: dict[str, float],
                    watched: Collection[str] = ()) -> _LookAhead:
        agents = [(name, self._available(self._agents[name], now), rate) for name, rate in rates.items()]
        # Refining pays in the end game, where the last units decide the makespan; earlier the next
        # projection (at the next inform) corrects the list schedule anyway.
        end_game = job.open_count() <= self.config.refine_below * max(1, len(agents))
        return _LookAhead(job, agents, rates.keys(), self.config.refine_moves if end_game else 0, watched)

    def _rates(self, job: Job) -> dict[str, float]:
        """Seconds per unit of cost of every live agent the job may use: learnt, or derived from speeds. A
        drained agent is left out: projected units it will never take would be kept from the others."""
        live = [a for a in self._agents.values()
                if not a.lost and a.silent_until is None and not a.draining and a.name not in job.blocklist]
        job_id = job.info.job_id
        known = {
            a.name: max(a.rates.get(job_id, 0.0), a.late_rates.get(job_id, 0.0))
            for a in live
            if job_id in a.rates or job_id in a.late_rates
        }
        rates = dict(known)
        if len(known) < len(live):
            typical = self._typical(known)
            rates.update((a.name, self._prior_rate(a, typical)) for a in live if a.name not in known)
        return rates

    def _typical(self, known: dict[str, float]) -> float | None:
        """The job's cost in speed-seconds, rate x speed, alike for all agents if speeds are right: the median
        over the `known` rates (None: none)."""
        return statistics.median(r * self._agents[n].speed for n, r in known.items()) if known else None

    @staticmethod
    def _prior_rate(agent: Agent, typical: float | None) -> float:
        """Before it bids: its registered speed relative to agents whose rate is known (`_typical`; else
        1 / speed)."""
        return round_rate((1.0 if typical is None else typical) / max(agent.speed, 1e-9))

    def _learn_rate(self, agent: Agent, job: Job, bids: dict[int, float]) -> None:
        """The agent's rate on the job from its bids: seconds over cost, summed (big units weigh most)."""
        costs = {i: job.units[i].spec.work for i in bids if i in job.units and job.units[i].spec.work > 0}
        if not costs:
            return
        seconds = sum(max(bids[i], self.config.min_estimate_s) for i in costs)
        rate = min(max(seconds / sum(costs.values()), MIN_RATE), MAX_RATE)
        job_id = job.info.job_id
        others = [
            a.rates[job_id]
            for a in self._agents.values()
            if a is not agent and not a.lost and job_id in a.rates
        ]
        if others:
            median, clamp = statistics.median(others), self.config.rate_clamp
            rate = min(max(rate, median / clamp), median * clamp)
        agent.rates[job_id] = round_rate(rate)

    def _available(self, agent: Agent, now: float) -> float:
        """When the agent should be free: now, or when the units it holds should end (`Agent.held_end`). An
        agent past that time is assumed to need as long again as it has overrun (a late agent looks ever
        later)."""
        end = agent.held_end
        if end == -math.inf:
            return now
        return end if end >= now else 2 * now - end

    def _hold(self, agent: Agent, key: tuple[str, int]) -> None:
        """The agent holds the unit `key` (job, index), just awarded to it."""
        agent.holding.add(key)
        agent.held_end = self._held_end(agent)
        self._recheck(agent)

    def _release(self, agent: Agent, key: tuple[str, int]) -> None:
        """The agent no longer holds the unit `key` (done, failed, taken back or cancelled)."""
        agent.holding.discard(key)
        agent.held_end = self._held_end(agent)
        self._recheck(agent)

    def _held_end(self, agent: Agent) -> float:
        """When the units the agent holds should end, one after the other in award order (-inf: none)."""
        held = [self._jobs[j].units[i] for j, i in agent.holding if j in self._jobs and i in self._jobs[j].units]
        end = -math.inf
        for unit in sorted(held, key=lambda u: u.awarded_at):
            end = max(end, unit.awarded_at) + unit.estimate
        return end

    def _worth_offering(self, name: str, unit: UnitState, place: Placement, rates: dict[str, float],
                        now: float) -> bool:
        """Whether free agent `name` would finish `unit`, placed first on another free agent, about as soon."""
        duration = rates[name] * unit.spec.work
        return duration <= (place.finish - now) * (1 + self.config.finish_tolerance) + 1e-9

    def _pick(self, round_: Round, unit: UnitState, job: Job, full: set[str], now: float,
              excluded: frozenset[str]) -> str | None:
        bids = {
            name: bids[unit.spec.index]
            for name, bids in round_.bids.items()
            if unit.spec.index in bids
            and name not in full
            and name in self._agents
            and not self._agents[name].lost
            and name not in job.blocklist
            and name not in excluded
        }
        if not bids:
            return None
        # A bidder still rendering a unit (a free slot) starts this one when that ends.
        finish = {n: self._available(self._agents[n], now) - now + e for n, e in bids.items()}
        fastest = min(finish.values())
        near = {n: f for n, f in finish.items() if f <= fastest * (1 + self.config.finish_tolerance) + 1e-9}
        # Best record first (MAgArRO), then the earlier finish, then the name for determinism.
        return min(near, key=lambda n: (-self._agents[n].score, near[n], n))

    def _award(self, job: Job, unit: UnitState, agent: str, estimate: float, now: float) -> list[Instruction]:
        self._set_unit(job, unit, UnitStatus.AWARDED)
        unit.agent, unit.token, unit.conversation = agent, f"{self.rng.getrandbits(128):032x}", self._new_id()
        unit.attempts += 1
        if job.passes is not None and job.passes.started is None:
            job.passes.started = now  # its time goal's clock starts
        start = self._available(self._agents[agent], now)  # after the units it holds already
        unit.awarded_at, unit.estimate = now, estimate
        job.set_deadline(unit, start + estimate * self.config.render_factor + self.config.render_slack_s)
        self._hold(self._agents[agent], (job.info.job_id, unit.spec.index))
        url = self.config.upload_url.format(job=job.info.job_id, index=unit.spec.index)
        # The seed depends on the unit only, so a retried unit rendered alone renders the same samples as the
        # first try and as `quekaro render` of the same job (a batch draws from its first unit's seed).
        award = m.Award(
            conversation=unit.conversation,
            job=job.info,
            unit=unit.spec,
            token=unit.token,
            upload_url=url,
            seed=unit_seed(job.info.job_id, unit.spec.index, 0),
            estimate_s=estimate,
        )
        record = UnitAwarded(job.info.job_id, unit.spec.index, agent, unit.token, estimate, unit.attempts,
                             unit.deadline, origin=_origin(job, unit.spec.index))
        return [SendToAgent(agent, award), record]

    # --- progressive jobs: passes as units (master.auction.passes) ---------------------------------------

    def _open_passes(self, job: Job, goal: Goal, units: tuple[WorkUnit, ...],
                     resumed: ResumedPasses | None = None) -> list[Instruction]:
        """A progressive job: its units become templates, and its first round of passes is auctioned. A job
        `resumed` after a restart: its units are its passes so far, and its decisions go on from them."""
        if resumed is not None:
            job.passes = PassBook.open(goal, resumed.templates, self._now - resumed.elapsed, self.config.pass_samples)
            return self._follow(job, job.passes.machine.resume(list(resumed.so_far), resumed.elapsed), "a round")
        job.clear()
        job.passes = PassBook.open(goal, units, None, self.config.pass_samples)
        return self._follow(job, job.passes.machine.start(), "a round")

    def _on_pass_merged(self, merged: PassMerged, now: float) -> list[Instruction]:
        """A pass merged into its unit: the decisions it leads to (more passes, or the job's end)."""
        job = self._jobs.get(merged.job_id)
        if job is None or job.passes is None or job.status != JobStatus.RUNNING:
            return [_ignored(None, "no running progressive job of that id", merged.job_id, merged.index)]
        book = job.passes
        unit, pass_index = book.origin(merged.index)
        elapsed = 0.0 if book.started is None else now - book.started
        done = PassDone(unit, pass_index, merged.spp, merged.seconds, merged.relmse, elapsed,
                        max(1, self.live_agents()))
        return self._follow(job, book.machine.handle(done), "a round")

    def _extra_passes(self, job: Job, agents: list[Agent]) -> list[Instruction]:
        """Idle agents and nothing of the job pending: extra passes of the units its round waits for."""
        idle = [a for a in agents if not a.holding]
        if job.passes is None or not idle or job.by_status.get(UnitStatus.PENDING):
            return []
        return self._follow(job, job.passes.machine.handle(Idle(len(idle))), "extra passes for idle agents")

    def _follow(self, job: Job, decided: list[RenderRound | Withdraw | Finish], why: str) -> list[Instruction]:
        out: list[Instruction] = []
        for step in decided:
            if isinstance(step, RenderRound):
                out += self._add_passes(job, step.orders, why)
            elif isinstance(step, Withdraw):
                out += self._withdraw(job, step.orders)
            else:
                out += self._settle(job, step)
        return out

    def _withdraw(self, job: Job, orders: tuple[PassOrder, ...]) -> list[Instruction]:
        """Passes still out that their unit no longer needs: called off, so that none lands past its cap."""
        return self._withdraw_passes(job, [job.passes.pass_index(o) for o in orders],
                                     "its unit has the samples its round asks from another pass")

    def _withdraw_passes(self, job: Job, indices: list[int], reason: str) -> list[Instruction]:
        """Passes not done that the job no longer needs: called off, never requeued, gone from the store."""
        units = [job.units[i] for i in indices if i in job.units and job.units[i].status not in END]
        out: list[Instruction] = []
        for unit in units:
            out += self._call_off(job, unit, reason)
            unit.withdrawn = True
        if not units:
            return out
        gone = tuple(u.spec.index for u in units)
        return [PassesWithdrawn(job.info.job_id, gone, len(gone), reason), *out]

    def _add_passes(self, job: Job, orders: tuple[PassOrder, ...], why: str) -> list[Instruction]:
        units = tuple(job.passes.pass_unit(o) for o in orders)
        for unit in units:
            job.add(UnitState(unit, UnitStatus.PENDING))
        return [PassesOrdered(job.info.job_id, units, len(units), why)]

    def _settle(self, job: Job, finish: Finish) -> list[Instruction]:
        """The job's passes reached its goal: those still out are withdrawn; the job is done."""
        out: list[Instruction] = [PassesSettled(job.info.job_id, finish.reason, dict(finish.units))]
        out += self._withdraw_passes(job, list(job.units), "the job's passes reached its goal")
        self._set_job(job, JobStatus.DONE)
        return [*out, JobDone(job.info.job_id)]

    def _set_unit(self, job: Job, unit: UnitState, status: UnitStatus) -> None:
        """The one place a unit's status changes: checked against `core.model.status.UNIT_TRANSITIONS`."""
        where = f"job {job.info.job_id!r} unit {unit.spec.index}"
        start = unit.status
        unit.status = unit_transition(where, start, status)
        job.moved(unit.spec.index, start, unit.status)
        unit.story.append(Transition(self._stimulus_id, start.value, status.value, self._now))

    def _set_job(self, job: Job, status: JobStatus) -> None:
        """The one place a job's status changes: checked against `core.model.status.JOB_TRANSITIONS`."""
        job.status = job_transition(f"job {job.info.job_id!r}", job.status, status)

    def _clear_award(self, job: Job, unit: UnitState, status: UnitStatus) -> None:
        self._set_unit(job, unit, status)
        unit.agent = unit.token = unit.conversation = None
        unit.deadline = math.inf

    def _requeue(self, key: tuple[str, int], reason: str) -> list[Instruction]:
        """Unit back to the auction without blaming its agent (the agent vanished, not the unit)."""
        job = self._jobs[key[0]]
        unit = job.units[key[1]]
        if unit.agent in self._agents:
            self._release(self._agents[unit.agent], key)
        record = UnitRequeued(key[0], key[1], unit.agent, unit.token, reason, origin=_origin(job, key[1]))
        self._clear_award(job, unit, UnitStatus.PENDING)
        return [record]

    def _fail_unit(self, key: tuple[str, int], reason: str) -> list[Instruction]:
        """The unit failed on its agent: retry elsewhere; blocklist the agent after repeated failures."""
        job = self._jobs[key[0]]
        unit = job.units[key[1]]
        agent = unit.agent
        state = self._agents[agent]
        self._release(state, key)
        state.credits -= 1
        state.recent.append(False)
        unit.failures += 1
        unit.failed_on.add(agent)
        unit.last_reason = reason
        out: list[Instruction] = [UnitFailed(key[0], key[1], agent, unit.token, reason, state.credits,
                                             origin=_origin(job, key[1]))]
        self._clear_award(job, unit, UnitStatus.PENDING)
        job.failures_by_agent[agent] += 1
        if job.failures_by_agent[agent] >= self.config.blocklist_after and agent not in job.blocklist:
            job.blocklist.add(agent)
            why = f"{job.failures_by_agent[agent]} failed units of this job"
            out.append(AgentBlocklisted(key[0], agent, why))
        return out + self._fail_if_stuck(job)

    def _fail_if_stuck(self, job: Job) -> list[Instruction]:
        """Fail the job when a remaining unit failed too often, or every agent the farm knows (lost ones
        may come back until they are forgotten) is blocklisted for it."""
        if not job.failures_by_agent and self.config.max_unit_failures > 0:  # no unit of it ever failed
            return []
        for unit in job.having(UnitStatus.PENDING):
            if unit.failures >= self.config.max_unit_failures:
                why = f"unit {unit.spec.index} failed {unit.failures} times; last: {unit.last_reason}"
            elif self._agents and unit.failures and not set(self._agents) - job.blocklist:
                why = (
                    f"no agent can take unit {unit.spec.index}: it failed on "
                    f"{', '.join(sorted(unit.failed_on))} (last: {unit.last_reason}); every agent is "
                    f"blocklisted for the job: {', '.join(sorted(job.blocklist))}"
                )
            else:
                continue
            return [
                *self._stop_job(job, JobStatus.FAILED, why),
                JobFailed(job.info.job_id, why),
            ]
        return []

    def _stop_job(self, job: Job, status: JobStatus, reason: str) -> list[Instruction]:
        out: list[Instruction] = []
        self._set_job(job, status)
        job.error = reason
        for unit in job.units.values():
            if unit.status not in END:
                out += self._call_off(job, unit, reason)
        return out

    def _call_off(self, job: Job, unit: UnitState, reason: str) -> list[Instruction]:
        """A unit not done that its job no longer wants: its agent (if it holds it) told to stop; failed."""
        out: list[Instruction] = []
        if unit.status == UnitStatus.AWARDED:
            self._release(self._agents[unit.agent], (job.info.job_id, unit.spec.index))
            cancel = m.Cancel(conversation=unit.conversation, job_id=job.info.job_id, index=unit.spec.index,
                              reason=reason[:1024])
            out.append(SendToAgent(unit.agent, cancel))
        self._clear_award(job, unit, UnitStatus.FAILED)
        return out

    def _finish_if_done(self, job: Job) -> list[Instruction]:
        done = len(job.by_status.get(UnitStatus.DONE, ())) == len(job.units)
        if job.passes is None and job.status == JobStatus.RUNNING and done:
            self._set_job(job, JobStatus.DONE)
            return [JobDone(job.info.job_id)]
        return []


def _ignored(
    agent: str | None, reason: str, job_id: str | None = None, index: int | None = None
) -> MessageIgnored:
    return MessageIgnored(agent, reason, job_id, index)


def _tile_refusal(job: Job, unit: WorkUnit, tile: TileStored) -> str:
    """Why the tile cannot be the unit's result, or "": it must carry the job's channels (else it could never
    be composed with the others), hold figures an inform may hold, render no shallower than the unit's depth
    floor (it would lack the light of the paths cut), a pass at its unit's depth (merged, passes of two depths
    would estimate neither image), and in an adaptive job the unit's planned share in two
    passes (its image is averaged with the others' as if it had)."""
    where = f"unit {unit.index} of job {job.info.job_id}"
    if job.passes is not None and tile.channels[-1:] != (WEIGHT,):
        return f"{where}: a pass's tile ends with channel {WEIGHT}, this one with {list(tile.channels)[-1:]}"
    if job.channels is not None and tile.channels != job.channels:
        return f"{where}: tile channels {list(tile.channels)[:8]} differ from the job's {list(job.channels)[:8]}"
    try:
        m.check(tile.figures)
    except MessageError as exc:
        return f"tile header's render parameters: {exc}"
    said = tile.figures
    if job.passes is not None and said.depth != (job.info.depth if unit.depth is None else unit.depth):
        return f"{where}: a pass's tile header says depth {said.depth}; its unit's passes render at depth " \
               f"{job.info.depth if unit.depth is None else unit.depth}"
    if unit.depth_floor is not None and job.info.depth >= 1 and said.depth < unit.depth_floor:
        return f"{where}: tile header says depth {said.depth}; the plan allows no less than {unit.depth_floor} " \
               "(shallower paths lose its light)"
    first = job.info.first_spp
    if first is not None and (said.spp, said.first_spp) != (unit.spp, first):
        return f"{where} (adaptive): tile header says spp {said.spp}, first pass {said.first_spp}; the plan " \
               f"gives spp {unit.spp}, first pass {first}"
    return ""


def _check_open(job: Job) -> None:
    """The invariants of the job's indexes of open units (`Job.open_order`, `open_costs`, `open_failed`) and
    of deadlines (`Job.due`)."""
    opened = [u for u in job.units.values() if u.status in OPEN]
    assert job.open_order == sorted((-u.spec.work, u.spec.index) for u in opened), \
        f"job {job.info.job_id}: open_order is stale"
    assert job.open_costs == [-c for c, _ in job.open_order], f"job {job.info.job_id}: open_costs is stale"
    assert job.open_failed == {u.spec.index for u in opened if u.failed_on}, \
        f"job {job.info.job_id}: open_failed is stale"
    due = set(job.due)
    assert all((u.deadline, u.spec.index, u.attempts) in due for u in job.having(UnitStatus.AWARDED)
               if math.isfinite(u.deadline)), f"job {job.info.job_id}: a deadline missing from due"


def _check_unit(auction: Auction, job: Job, unit: UnitState, rounds: int) -> None:
    """The invariants of one unit: an award's holder holds it, and an announced unit is in one open round
    (`rounds`: the open rounds that hold it)."""
    where = f"unit {unit.spec.index} of job {job.info.job_id}"
    if unit.status == UnitStatus.AWARDED:
        assert None not in (unit.agent, unit.token, unit.conversation), f"{where}: awarded without its award"
        holder = auction._agents.get(unit.agent)
        assert holder is not None and (job.info.job_id, unit.spec.index) in holder.holding, \
            f"{where}: awarded to {unit.agent}, which does not hold it"
    else:
        assert unit.token is None and unit.agent is None, f"{where}: {unit.status.value} with an award"
    if unit.status == UnitStatus.ANNOUNCED:
        assert rounds == 1, f"{where}: announced in {rounds} open rounds"

