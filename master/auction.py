"""The contract net and the life-cycle of work units, as a pure state machine (no I/O, no clock).

Units go PENDING -> ANNOUNCED -> AWARDED -> DONE, or back to PENDING when an auction leaves them
unsold, an agent fails them, misses their render deadline or is lost; a job with a unit that failed
`max_unit_failures` times, or that every agent the farm knows is blocklisted for, is FAILED with the
reason. Every call takes `now` (seconds, any epoch) and returns plain commands, `Send(to, message)` for
the transport to deliver and events (one dataclass per kind, `Event`) for the job store and the logs, so
the SPADE layer only delivers messages and the same code runs under the simulated clock of
`bench.simulate` (the scaling benchmark). Every status change goes through the transition table of
`core.model.status`, which the job store checks too.

The award rule is MAgArRO's (design.md section 2) with an earliest-finish-time look-ahead. Before each
call for proposals the master projects a list schedule of the job's open units, most costly first, over
its live agents, each available now or when the unit it holds should end, each unit on the agent where
it would finish earliest (`project`, at the agent's seconds per unit of work, `WorkUnit.work`, learnt
from its bids). A free agent is called only to the units the projection gives it, plus those given to
another agent free now that it would finish about as soon (so that records still decide among equals); a
free agent given nothing is not called, since any unit it took would end later than on an agent about to
be free: with agents of mixed speeds, a slow agent that happens to be free would otherwise take a big unit
at the end and become the job's tail. The projection is made afresh at every tick, so a unit projected to an agent
that is lost, blocklisted or late moves on. A contested unit goes to the agent with the best record,
credits plus recent successes, among the bidders that would finish within `finish_tolerance` of the
fastest, and an agent that finishes within 10 % of its estimate gains a credit, else loses one.

Estimates are clamped where they steer the projection: a bid below `min_estimate_s` counts as that, an
agent's rate is kept within `rate_clamp` times the median rate of the job's other agents, and an agent
whose last unit of a job took longer than its estimate allowed is projected at the rate it showed until
it finishes one on time (so a bid of 0 s cannot draw every unit to one agent). Failure handling follows
Flamenco (design.md section 5): a failed unit is retried on another agent (on the same one where no
other live agent may take it), an agent failing three units of a job is blocklisted for that job, and a
lost agent's units return to the auction.
"""

from __future__ import annotations

import bisect
import dataclasses
import heapq
import hmac
import math
import random
import statistics
from collections import Counter, deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple, Protocol

from core.model import messages as m
from core.model.seeds import unit_seed
from core.model.status import JobStatus, UnitStatus, job_transition, unit_transition
from core.model.units import SLOTS, WorkUnit, batch_size, batched


@dataclass(frozen=True)
class Config:
    """Timeouts and rules of the auction. Times in seconds."""

    cfp_timeout_s: float = 2.0  # agents that have not answered a CFP by then are left out of that round
    # An agent that lets a call for proposals time out unanswered is not called, nor counted on in the
    # projection, for cfp_timeout_s doubling with each silence in a row, up to this: one that never bids
    # (broken, or lying about its speed) would otherwise be projected the units and keep them from the rest.
    silence_max_s: float = 30.0
    heartbeat_timeout_s: float = 15.0  # Flamenco uses 60 s; agents here beat every few seconds
    # A lost agent is forgotten after this (its credits kept, should it come back): a restarted agent
    # comes back under a new name, and the old one would stay listed as lost for as long as the master runs.
    forget_lost_s: float = 600.0
    award_grace_s: float = 10.0  # an award not listed in the agent's heartbeats by then was lost in transit
    render_factor: float = 3.0  # render deadline = estimate x factor + slack
    render_slack_s: float = 30.0
    blocklist_after: int = 3  # failures of one job's units on one agent
    max_unit_failures: int = 5  # a unit failing this often fails its job, however many agents remain
    credit_tolerance: float = 0.10  # finishing within 10 % of the estimate earns a credit
    recent_window: int = 10  # successes counted in an agent's record
    # Bidders finishing within this fraction of the fastest are equals, and the best record wins among
    # them; a free agent is also called to units projected to another free agent that it would finish
    # within this fraction of their projected time.
    finish_tolerance: float = 0.10
    min_estimate_s: float = 1e-3  # a lower (or zero) bid counts as this in the projection
    rate_clamp: float = 100.0  # an agent's rate stays within this factor of the job's median rate
    refine_moves: int = 64  # moves and swaps that shorten each projection (0: plain list schedule)
    refine_below: float = 3.0  # refine only while open units are at most this many per agent (end game)
    # Units an agent may hold at once, and (half of them, `batch_size`) win in one round and render in one
    # call: its next batch is awarded while one renders, so its render process never waits for the upload,
    # the inform and the next auction (~35 ms a unit on one machine). 2: one unit a round and a call.
    slots: int = SLOTS
    # Units are queued behind others only while the open units are at least this many per live agent (and
    # at least two batches, `_queueing`): in the end game a queued unit is committed before anyone knows
    # which agent frees up first, and the simulation's tail grew (64 agents, 2 slots: efficiency 0.77 ->
    # 0.71 with 3 here instead of 4).
    queue_above: float = 4.0
    max_cfp_units: int = m.MAX_CFP_UNITS
    upload_url: str = "http://127.0.0.1:8765/jobs/{job}/units/{index}/tile"


@dataclass(frozen=True)
class Send:
    """Deliver `message` to agent `to` (a JID)."""

    to: str
    message: m.Message


@dataclass(frozen=True)
class Event:
    """Something the job store or the log should know: one subclass per kind, with typed fields. Tokens are
    left out of the repr, so that logging an event leaks no award's secret."""


@dataclass(frozen=True)
class UnitAwarded(Event):
    job_id: str
    index: int
    agent: str
    token: str = field(repr=False)
    estimate: float  # seconds, the winning bid
    attempt: int  # 1 for the unit's first award
    deadline: float  # render deadline, auction time


@dataclass(frozen=True)
class UnitDone(Event):
    """The unit's tile is durable and its award's holder is done; the agent's parameters and record."""

    job_id: str
    index: int
    agent: str
    token: str = field(repr=False)
    seconds: float
    estimate: float
    tile_hash: str
    depth: int
    spp: int
    band: int
    nonfinite: int
    credits: int  # the agent's credits after this unit
    on_time: bool  # within `Config.credit_tolerance` of its estimate

    @property
    def params(self) -> dict[str, int]:
        """The render parameters the agent chose, as the store records them."""
        return {"depth": self.depth, "spp": self.spp, "band": self.band, "nonfinite": self.nonfinite}


@dataclass(frozen=True)
class UnitFailed(Event):
    """The unit failed on its agent (its report, or its render deadline passed): back to pending."""

    job_id: str
    index: int
    agent: str
    token: str = field(repr=False)
    reason: str
    credits: int  # the agent's credits after this failure


@dataclass(frozen=True)
class UnitRequeued(Event):
    """The unit went back to pending without blaming its agent (lost, or the award never arrived)."""

    job_id: str
    index: int
    agent: str
    token: str = field(repr=False)
    reason: str


@dataclass(frozen=True)
class JobDone(Event):
    job_id: str


@dataclass(frozen=True)
class JobFailed(Event):
    job_id: str
    reason: str


@dataclass(frozen=True)
class JobCancelled(Event):
    job_id: str
    reason: str


@dataclass(frozen=True)
class AgentRegistered(Event):
    agent: str
    speed: float


@dataclass(frozen=True)
class AgentLost(Event):
    agent: str
    reason: str


@dataclass(frozen=True)
class AgentBack(Event):
    agent: str


@dataclass(frozen=True)
class AgentSilent(Event):
    """An agent let a call for proposals time out: it is left out of auctions for `seconds`."""

    agent: str
    seconds: float


@dataclass(frozen=True)
class AgentForgotten(Event):
    """An agent lost for `Config.forget_lost_s` is dropped from the agents the master lists."""

    agent: str


@dataclass(frozen=True)
class AgentBlocklisted(Event):
    job_id: str
    agent: str
    reason: str


@dataclass(frozen=True)
class BidRefused(Event):
    """An agent answered a call for proposals with a refusal."""

    job_id: str
    agent: str
    reason: str


@dataclass(frozen=True)
class MessageIgnored(Event):
    """A message or request that changes nothing (late, forged, duplicate, out of its auction), and why."""

    agent: str | None
    reason: str
    job_id: str | None = None
    index: int | None = None


Command = Send | Event


class ResumedJob(Protocol):
    """A running job as a restarted master finds it (the job store's `RunningJob`): `Auction.restore`."""

    @property
    def job_id(self) -> str: ...
    @property
    def units(self) -> Sequence[WorkUnit]: ...
    @property
    def done(self) -> Sequence[int]: ...
    @property
    def failures(self) -> Sequence[tuple[int, str, str]]: ...  # (unit index, agent, reason), oldest first
    @property
    def delivered_by(self) -> Mapping[int, str]: ...  # done unit -> the agent whose tile made it done


@dataclass
class UnitState:
    spec: WorkUnit
    status: UnitStatus = UnitStatus.PENDING
    attempts: int = 0
    failures: int = 0
    failed_on: set[str] = field(default_factory=set)
    last_reason: str = ""
    agent: str | None = None
    token: str | None = None
    conversation: str | None = None
    awarded_at: float = 0.0
    estimate: float = 0.0
    deadline: float = math.inf
    delivered_by: str | None = None  # the agent whose tile made it done


class PlansWith(NamedTuple):
    """What an agent plans a job's units with, as its Register told (None: not told)."""

    rules_sha256: str | None  # its rule file's, for a job without rules of its own
    defuzzifier: str | None  # its --defuzzifier, for a job that names none (None: the file's dialect)


NOT_TOLD = PlansWith(None, None)  # an agent known from heartbeats alone, or whose Register did not tell


@dataclass
class Agent:
    name: str
    last_seen: float
    credits: int = 0
    recent: deque[bool] = field(default_factory=lambda: deque(maxlen=10))
    holding: set[tuple[str, int]] = field(default_factory=set)
    invited: str | None = None  # conversation id of the open auction round it was called to
    lost: bool = False
    speed: float = 1.0
    registered: bool = True  # False: known from heartbeats alone, its speed not yet told
    silences: int = 0  # calls for proposals it let time out in a row
    silent_until: float | None = None  # left out of auctions until then (Config.silence_max_s)
    slots: int | None = None  # units it holds at once, as its Register told (None: Config.slots)
    rules: PlansWith = NOT_TOLD  # what it plans with, as its Register told
    # Seconds per unit of cost, per job: from its latest bids, and from its last unit that overran.
    rates: dict[str, float] = field(default_factory=dict)
    late_rates: dict[str, float] = field(default_factory=dict)

    @property
    def score(self) -> int:
        return self.credits + sum(self.recent)


@dataclass
class Job:
    info: m.JobInfo
    units: dict[int, UnitState]
    order: int
    status: JobStatus = JobStatus.RUNNING
    error: str = ""
    failures_by_agent: Counter[str] = field(default_factory=Counter)
    blocklist: set[str] = field(default_factory=set)


@dataclass
class Round:
    conversation: str
    job_id: str
    offered: dict[str, tuple[int, ...]]  # agent -> unit indices it was called to bid on
    units: frozenset[int]  # every unit this round holds as ANNOUNCED, even if its bidders are lost
    deadline: float
    room: dict[str, int] = field(default_factory=dict)  # agent -> units it may win in this round (default 1)
    bids: dict[str, dict[int, float]] = field(default_factory=dict)
    answered: set[str] = field(default_factory=set)


# --- the look-ahead: a projected list schedule (plain functions, no state) ---------------------------------


@dataclass(frozen=True)
class PlanAgent:
    """An agent as the projection sees it: when it is next free, and its seconds per unit of cost."""

    name: str
    available: float
    rate: float


@dataclass(frozen=True)
class ProjectedUnit:
    """A unit to place: its index, cost, and the agents that may not take it (it failed on them)."""

    index: int
    cost: float
    excluded: frozenset[str] = frozenset()


@dataclass(frozen=True)
class Placement:
    agent: str
    start: float
    finish: float


def project(units: Iterable[ProjectedUnit], agents: Iterable[PlanAgent]) -> dict[int, Placement]:
    """List schedule of `units`, most costly first, each on the agent where it would finish earliest (ties:
    the earlier start, then the name). Units that no agent may take are left out.

    Agents of one rate are interchangeable, so each unit only compares the earliest free agent of every
    rate (a heap per rate): O(units x rates x log agents), not units x agents.
    """
    heaps: dict[float, list[tuple[float, str]]] = {}
    for agent in agents:
        heaps.setdefault(agent.rate, []).append((agent.available, agent.name))
    for heap in heaps.values():
        heapq.heapify(heap)
    plan: dict[int, Placement] = {}
    for unit in sorted(units, key=lambda u: (-u.cost, u.index)):
        best: tuple[float, float, str, float] | None = None  # finish, start, name, rate
        for rate, heap in heaps.items():
            entry = _first_allowed(heap, unit.excluded)
            if entry is not None:
                candidate = (entry[0] + rate * unit.cost, entry[0], entry[1], rate)
                best = candidate if best is None or candidate < best else best
        if best is None:
            continue
        finish, start, name, rate = best
        heap = heaps[rate]
        if heap[0] == (start, name):
            heapq.heapreplace(heap, (finish, name))
        else:  # a unit with exclusions took an agent below the root (rare): O(agents)
            heap.remove((start, name))
            heap.append((finish, name))
            heapq.heapify(heap)
        plan[unit.index] = Placement(name, start, finish)
    return plan


def refine(
    plan: dict[int, Placement],
    units: Iterable[ProjectedUnit],
    agents: Iterable[PlanAgent],
    max_moves: int = 64,
    gap: float = 0.002,
) -> dict[int, Placement]:
    """A shorter schedule than `plan` where one is found: units move, or swap, off the agent that finishes
    last while that lowers the later finish of the pair (the best such step first, `max_moves` at most),
    until the schedule ends within `gap` of the fluid bound (`fluid_finish`). Each agent then takes its
    units most costly first. List scheduling alone ends ~5 % above the ideal with a few units per agent
    (the last units do not fill the gaps); this recovers most of it.
    """
    unit_of = {u.index: u for u in units}
    agent_of = {a.name: a for a in agents}
    if not plan:
        return {}
    good_enough = fluid_finish([unit_of[i].cost for i in plan], agent_of.values()) * (1 + gap)
    owned: dict[str, list[int]] = {name: [] for name in agent_of}
    finish = {a.name: a.available for a in agent_of.values()}
    for index, place in plan.items():
        owned[place.agent].append(index)
        finish[place.agent] = max(finish[place.agent], place.finish)
    for _ in range(max_moves):
        last = max(finish, key=lambda n: (finish[n], n))
        if finish[last] <= good_enough:
            break
        step = _best_step(last, owned, finish, unit_of, agent_of)
        if step is None:
            break
        index, other, back = step
        _move(index, last, other, owned, finish, unit_of, agent_of)
        if back is not None:
            _move(back, other, last, owned, finish, unit_of, agent_of)
    out: dict[int, Placement] = {}
    for name, indices in owned.items():
        t = agent_of[name].available
        for index in sorted(indices, key=lambda i: (-unit_of[i].cost, i)):
            end = t + agent_of[name].rate * unit_of[index].cost
            out[index] = Placement(name, t, end)
            t = end
    return out


def fluid_finish(costs: Iterable[float], agents: Iterable[PlanAgent]) -> float:
    """The earliest end of `costs` if work could be split at will: the time T at which the agents, each
    working from its availability at 1 / rate cost per second, have done it all (a lower bound)."""
    work = sum(costs)
    ranked = sorted((a.available, 1.0 / max(a.rate, _MIN_RATE)) for a in agents)
    t, pace = ranked[0][0], 0.0
    for i, (start, speed) in enumerate(ranked):
        if pace > 0 and t + work / pace <= start:
            break
        work -= pace * (start - t)
        t, pace = start, pace + speed
        if i == len(ranked) - 1:
            break
    return t + work / pace


def _best_step(
    last: str,
    owned: dict[str, list[int]],
    finish: dict[str, float],
    unit_of: dict[int, ProjectedUnit],
    agent_of: dict[str, PlanAgent],
) -> tuple[int, str, int | None] | None:
    """The move (unit, to agent, None) or swap (unit, with agent, its unit) that lowers the later finish of
    `last` and the other agent the most. A swap trading cost d ends at max(top - ra d, fb + rb d), lowest at
    d* = (top - fb) / (ra + rb): only the other agent's two units nearest to that difference are tried
    (a bisection in its sorted costs), so a step costs O(units of last x agents x log units)."""
    top, rate_a = finish[last], agent_of[last].rate
    best: tuple[float, int, str, int | None] | None = None
    for other, theirs in owned.items():
        if other == last:
            continue
        rate_b, fin_b = agent_of[other].rate, finish[other]
        ranked = sorted((unit_of[i].cost, i) for i in theirs)
        costs = [c for c, _ in ranked]
        ideal = (top - fin_b) / (rate_a + rate_b)
        for index in owned[last]:
            u = unit_of[index]
            if other in u.excluded:
                continue
            options: list[tuple[float, int | None]] = [(u.cost, None)]  # d = the unit's cost: a move
            at = bisect.bisect_left(costs, u.cost - ideal)
            options += [(u.cost - ranked[j][0], ranked[j][1]) for j in (at - 1, at) if 0 <= j < len(ranked)]
            for d, back in options:
                if d <= 0 or (back is not None and last in unit_of[back].excluded):
                    continue
                worst = max(top - rate_a * d, fin_b + rate_b * d)
                if worst < top - 1e-9 and (best is None or worst < best[0]):
                    best = (worst, index, other, back)
    return None if best is None else best[1:]


def _move(
    index: int,
    src: str,
    dst: str,
    owned: dict[str, list[int]],
    finish: dict[str, float],
    unit_of: dict[int, ProjectedUnit],
    agent_of: dict[str, PlanAgent],
) -> None:
    owned[src].remove(index)
    owned[dst].append(index)
    finish[src] -= agent_of[src].rate * unit_of[index].cost
    finish[dst] += agent_of[dst].rate * unit_of[index].cost


def _batch_deadlines(out: list[Command], wins: dict[str, list[UnitState]]) -> list[Command]:
    """Units one agent won in one round render in one call and end together, after the last of them would
    have ended one by one: each is given the last one's deadline (its own would pass before the batch ends
    when the others take more than twice its estimate plus the slack)."""
    deadlines = {}
    for won in wins.values():
        last = max(u.deadline for u in won)
        for unit in won:
            unit.deadline = deadlines[unit.spec.index] = last
    return [dataclasses.replace(c, deadline=deadlines[c.index]) if isinstance(c, UnitAwarded) else c
            for c in out]


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
    failed = frozenset(unit.failed_on)
    return failed if not failed or any(name not in failed for name in usable) else frozenset()


def _first_allowed(heap: list[tuple[float, str]], excluded: frozenset[str]) -> tuple[float, str] | None:
    if not excluded:
        return heap[0] if heap else None
    allowed = [entry for entry in heap if entry[1] not in excluded]
    return min(allowed) if allowed else None


def _round_rate(rate: float) -> float:
    # Rates learnt from sums of bids differ in the last bits between agents of one speed; rounding lets
    # them share a heap in `project`.
    return float(f"{rate:.9g}")


class Auction:
    """The master's state: jobs, units, agents, open auction rounds. See the module docstring."""

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
        self.jobs: dict[str, Job] = {}
        self.agents: dict[str, Agent] = {}
        self.rounds: dict[str, Round] = {}

    @classmethod
    def restore(
        cls,
        jobs: Iterable[ResumedJob],
        describe: Callable[[str], m.JobInfo],
        credits: dict[str, int] | None = None,
        config: Config | None = None,
        rng: random.Random | None = None,
    ) -> tuple[Auction, list[Command]]:
        """The auction after a master restart: every running job with its done units and past failures, and
        the agents' records (`credits`, applied as each registers again). `describe` gives a job's CFP
        description (its scene URL depends on where the master serves now); a job it cannot describe fails
        alone. Returns the auction and the events of resuming (a job that was in fact complete, or failed),
        for the job store to apply."""
        auction = cls(config, rng, credits=credits)
        out: list[Command] = []
        for job in jobs:
            try:
                info = describe(job.job_id)
            except Exception as exc:  # one job the master cannot describe must not stop the others
                out.append(JobFailed(job.job_id, f"cannot resume the job: {type(exc).__name__}: {exc}"))
                continue
            out += auction.add_job(info, job.units, job.done, job.failures, job.delivered_by)
        return auction, out

    # --- set-up --------------------------------------------------------------------------------------

    def add_job(
        self,
        info: m.JobInfo,
        units: Sequence[WorkUnit],
        done: Iterable[int] = (),
        failures: Iterable[tuple[int, str, str]] = (),
        delivered_by: Mapping[int, str] | None = None,
    ) -> list[Command]:
        """Start auctioning a job's units. A resumed job passes the units already `done` (and `delivered_by`,
        whose tile made each one done) and its past `failures` as (unit index, agent, reason), so retries,
        blocklists and deliveries survive a master restart."""
        if info.job_id in self.jobs:
            raise ValueError(f"job {info.job_id!r} already known")
        if len({u.index for u in units}) != len(units) or not units:
            raise ValueError(f"job {info.job_id!r}: unit indices must be unique and non-empty")
        done = set(done)
        if done - {u.index for u in units}:
            raise ValueError(f"job {info.job_id!r}: done units {sorted(done - {u.index for u in units})} unknown")
        # Units done before a restart start as done: a state, not a change of it.
        job = Job(info, {u.index: UnitState(u, UnitStatus.DONE if u.index in done else UnitStatus.PENDING)
                         for u in units}, order=len(self.jobs))
        for index, agent in (delivered_by or {}).items():
            if index in done:
                job.units[index].delivered_by = agent
        for index, agent, reason in failures:
            unit = job.units[index]
            unit.failures += 1
            unit.failed_on.add(agent)
            unit.last_reason = reason
            job.failures_by_agent[agent] += 1
        job.blocklist = {a for a, n in job.failures_by_agent.items() if n >= self.config.blocklist_after}
        self.jobs[info.job_id] = job
        return self._finish_if_done(job) + self._fail_if_stuck(job)

    def register(self, agent: str, now: float, speed: float = 1.0, credits: int = 0,
                 registered: bool = True, slots: int | None = None,
                 rules: PlansWith = NOT_TOLD) -> list[Command]:
        """An agent announces itself (or comes back); its record (credits) may come from the store.
        `registered` False: heard from by heartbeat only, at speed 1.0 until its Register comes. `slots`:
        the units it told it holds at once (None: the master's `Config.slots`); `rules`: its rule file's
        sha256 and defuzzifier (None: not told)."""
        known = self.agents.get(agent)
        if known is None:
            credits = self.known_credits.get(agent, credits)
            known = self.agents[agent] = Agent(agent, now, credits=credits, speed=speed, registered=registered,
                                               slots=slots, rules=rules)
            known.recent = deque(maxlen=self.config.recent_window)
            return [AgentRegistered(agent, speed)]
        known.speed = speed
        known.registered = True
        known.slots = slots if registered else known.slots
        known.rules = rules if registered else known.rules
        return self._seen(known, now)

    def plan_alike(self, rules_sha256: str | None, defuzzifier: str | None) -> bool:
        """Whether every live agent plans a job's units as the master's plan does: a job without rules of its
        own with the master's rules (`rules_sha256`; None: the job has its own, which every agent takes),
        and each agent its own defuzzifier where the job names none (`defuzzifier`). False without live
        agents, or with one that did not tell its rules (an agent known from heartbeats alone)."""
        live = [a for a in self.agents.values() if not a.lost]
        return bool(live) and all(
            a.rules.rules_sha256 is not None and (rules_sha256 is None or a.rules.rules_sha256 == rules_sha256)
            and (defuzzifier is not None or a.rules.defuzzifier is None) for a in live)

    # --- messages in ---------------------------------------------------------------------------------

    def on_message(self, sender: str, msg: m.Message, now: float) -> list[Command]:
        """Dispatch a parsed message from `sender` (a JID the transport has already authenticated)."""
        match msg:
            case m.Register():
                welcome = Send(sender, m.Welcome(conversation=msg.conversation))  # the agent retries until it
                return [*self.register(sender, now, speed=msg.speed, slots=msg.slots,
                                       rules=PlansWith(msg.rules_sha256, msg.defuzzifier)), welcome]
            case m.Heartbeat():
                return self.on_heartbeat(sender, msg, now)
            case m.Propose():
                return self.on_propose(sender, msg, now)
            case m.Refuse():
                return self.on_refuse(sender, msg, now)
            case m.Inform():
                # A unit is done only once its tile is durable: the master feeds on_inform from the upload.
                return [_ignored(sender, "an inform counts only through its tile's upload", msg.job_id, msg.index)]
            case m.Failure():
                return self.on_failure(sender, msg, now)
        return [_ignored(sender, f"{msg.performative} is not a message the master accepts")]

    def on_heartbeat(self, agent: str, msg: m.Heartbeat, now: float) -> list[Command]:
        """Agent alive; units it holds are reconciled with the awards (lost awards, stale work)."""
        known = self.agents.get(agent)
        out = self.register(agent, now, registered=False) if known is None else self._seen(known, now)
        state = self.agents[agent]
        if not state.registered:  # e.g. this master restarted while the agent stayed connected
            out.append(Send(agent, m.Introduce(conversation=self._new_id())))
        busy = {(b.job_id, b.index) for b in msg.busy}
        for key in sorted(state.holding - busy):
            unit = self.jobs[key[0]].units[key[1]]
            if now - unit.awarded_at > self.config.award_grace_s:
                out += self._requeue(key, "award not acknowledged by the agent")
        for job_id, index in sorted(busy - state.holding):
            if self._delivered(agent, job_id, index):
                continue  # a heartbeat sent while its tile's upload was ending: the unit is done, by it
            # Work the master did not award to it (revoked, or before a master restart): stop it.
            cancel = m.Cancel(
                conversation=self._new_id(), job_id=job_id, index=index, reason="not awarded to you"
            )
            out.append(Send(agent, cancel))
        return out

    def on_propose(self, agent: str, msg: m.Propose, now: float) -> list[Command]:
        round_, why = self._round_for(agent, msg.conversation, msg.job_id)
        if round_ is None:
            return [_ignored(agent, why, msg.job_id)]
        offered = set(round_.offered[agent])
        bids = {e.index: e.seconds for e in msg.estimates if e.index in offered}
        round_.bids[agent] = bids
        self._answered(round_, agent)
        self._learn_rate(self.agents[agent], self.jobs[round_.job_id], bids)
        return (
            []
            if len(bids) == len(msg.estimates)
            else [_ignored(agent, "bid on units not offered", msg.job_id)]
        )

    def on_refuse(self, agent: str, msg: m.Refuse, now: float) -> list[Command]:
        round_, why = self._round_for(agent, msg.conversation, msg.job_id)
        if round_ is None:
            return [_ignored(agent, why, msg.job_id)]
        self._answered(round_, agent)
        return [BidRefused(msg.job_id, agent, msg.reason)]

    def _answered(self, round_: Round, agent: str) -> None:
        round_.answered.add(agent)
        state = self.agents[agent]
        state.silences, state.silent_until = 0, None

    def on_inform(self, agent: str, msg: m.Inform, now: float) -> list[Command]:
        """A unit finished. Only the current award's holder, token and conversation count."""
        unit, why = self._award_for(agent, msg.job_id, msg.index, msg.token, msg.conversation)
        if unit is None:
            return [_ignored(agent, why, msg.job_id, msg.index)]
        state = self.agents[agent]
        state.holding.discard((msg.job_id, msg.index))
        on_time = msg.seconds <= unit.estimate * (1 + self.config.credit_tolerance)
        state.credits += 1 if on_time else -1
        if on_time:
            state.late_rates.pop(msg.job_id, None)
        elif unit.spec.work > 0:
            state.late_rates[msg.job_id] = _round_rate(min(msg.seconds / unit.spec.work, _MAX_RATE))
        state.recent.append(True)
        done = UnitDone(
            msg.job_id, msg.index, agent, unit.token, seconds=msg.seconds, estimate=unit.estimate,
            tile_hash=msg.tile_hash, depth=msg.depth, spp=msg.spp, band=msg.band, nonfinite=msg.nonfinite,
            credits=state.credits, on_time=on_time,
        )  # fmt: skip
        job = self.jobs[msg.job_id]
        self._clear_award(job, unit, UnitStatus.DONE)
        unit.delivered_by = agent
        return [done, *self._finish_if_done(job)]

    def _delivered(self, agent: str, job_id: str, index: int) -> bool:
        """Whether the unit is done by this agent's tile."""
        job = self.jobs.get(job_id)
        unit = job.units.get(index) if job else None
        return unit is not None and unit.status == UnitStatus.DONE and unit.delivered_by == agent

    def on_failure(self, agent: str, msg: m.Failure, now: float, blame: bool = True) -> list[Command]:
        """The agent could not render its unit: the unit fails on it (counted against it, toward its
        blocklisting), or without `blame` goes back to the auction (a failure the farm's own state may
        have caused, such as the master's disk being full)."""
        unit, why = self._award_for(agent, msg.job_id, msg.index, msg.token, msg.conversation)
        if unit is None:
            return [_ignored(agent, why, msg.job_id, msg.index)]
        if not blame:
            return self._requeue((msg.job_id, msg.index), f"failed on {agent}, not counted: {msg.reason}")
        return self._fail_unit((msg.job_id, msg.index), f"failed on {agent}: {msg.reason}")

    def upload_allowed(self, job_id: str, index: int, token: str) -> bool:
        """Whether a tile upload with this token is for the unit's current award (the data plane's check)."""
        job = self.jobs.get(job_id)
        unit = job.units.get(index) if job else None
        if unit is None or unit.status != UnitStatus.AWARDED or unit.token is None:
            return False
        return hmac.compare_digest(unit.token.encode(), token.encode())

    # --- time passes ---------------------------------------------------------------------------------

    def tick(self, now: float) -> list[Command]:
        """Everything due at `now`: timeouts, then auctions to resolve, then new calls for proposals."""
        return self.expire(now) + self.decide(now) + self.announce(now)

    def expire(self, now: float) -> list[Command]:
        """Lost agents give their units back; units past their render deadline are failed on their agent."""
        out: list[Command] = []
        for state in self.agents.values():
            if not state.lost and now - state.last_seen > self.config.heartbeat_timeout_s:
                state.lost = True
                out.append(AgentLost(state.name, "no heartbeat"))
                for key in sorted(state.holding):
                    out += self._requeue(key, f"agent {state.name} lost")
                if state.invited in self.rounds:
                    self.rounds[state.invited].offered.pop(state.name, None)
                state.invited = None
        out += self._forget_lost(now)
        for job in self._running():
            for unit in job.units.values():
                if unit.status == UnitStatus.AWARDED and now > unit.deadline:
                    holder = unit.agent
                    out.append(
                        Send(
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

    def decide(self, now: float) -> list[Command]:
        """Resolve rounds whose deadline passed or whose invited agents all answered."""
        out: list[Command] = []
        for conv, round_ in list(self.rounds.items()):
            if now >= round_.deadline or set(round_.offered) <= round_.answered:
                del self.rounds[conv]
                out += self._resolve(round_, now)
        return out

    def announce(self, now: float) -> list[Command]:
        """Calls for proposals: each free agent is offered the pending units the projection gives it, and
        those it would finish about as soon as the free agent they are projected to (module docstring)."""
        out: list[Command] = []
        for agent in self.agents.values():
            if agent.silent_until is not None and now >= agent.silent_until:
                agent.silent_until = None  # called again; its silences count on until it answers
        open_units = sum(u.status == UnitStatus.PENDING for j in self._running() for u in j.units.values())
        free_when: dict[bool, list[Agent]] = {}  # the free agents, whether units may queue or not
        for job in self._running():
            queueing = self._queueing(job, open_units)
            if queueing not in free_when:
                free_when[queueing] = sorted((a for a in self.agents.values() if self._is_free(a, queueing)),
                                             key=lambda a: (-a.score, a.name))
            free = free_when[queueing]
            callable_now = {a.name for a in free if a.invited is None}  # earlier jobs' rounds took some
            agents = [a for a in free if a.name in callable_now and a.name not in job.blocklist]
            pending = sorted(
                (u for u in job.units.values() if u.status == UnitStatus.PENDING),
                key=lambda u: (-u.spec.work, u.spec.index),
            )
            if not agents or not pending:
                continue
            rates = self._rates(job)
            plan = self._project(job, now, rates)
            excluded = {u.spec.index: _excluded(u, rates.keys()) for u in pending}
            offered, room = {}, {}
            for agent in agents:
                units = tuple(
                    u.spec.index
                    for u in pending
                    if self._worth_offering(agent.name, u, excluded[u.spec.index], plan, rates, now, callable_now)
                )
                if units:
                    offered[agent.name], room[agent.name] = units, self._room(agent, queueing, job)
            if not offered:
                continue
            # No agent is offered more units than the round calls agents or than it may win; one that may
            # win a batch is offered the units projected to it first, so that the agents' batches differ.
            offered = {name: _own_first(units, name, plan, room[name])[:min(self.config.max_cfp_units,
                                                                            max(len(offered), room[name]))]
                       for name, units in offered.items()}
            conv = self._new_id()
            held = frozenset(i for indices in offered.values() for i in indices)
            self.rounds[conv] = Round(conv, job.info.job_id, offered, held, now + self.config.cfp_timeout_s, room)
            for index in sorted(held):
                self._set_unit(job, job.units[index], UnitStatus.ANNOUNCED)
            for name, indices in offered.items():
                self.agents[name].invited = conv
                specs = tuple(job.units[i].spec for i in indices)
                cfp = m.CallForProposal(
                    conversation=conv, job=job.info, units=specs, reply_within_s=self.config.cfp_timeout_s
                )
                out.append(Send(name, cfp))
        return out

    def projection(self, job_id: str, now: float) -> dict[int, Placement]:
        """Where the look-ahead would place each open (pending or announced) unit of the job at `now`."""
        job = self.jobs[job_id]
        return self._project(job, now, self._rates(job))

    def rate(self, agent: str, job_id: str) -> float:
        """Seconds per unit of cost the projection assumes for `agent` on the job."""
        job = self.jobs[job_id]
        rates = self._rates(job)
        return rates[agent] if agent in rates else self._prior_rate(self.agents[agent], job, rates)

    def next_deadline(self) -> float | None:
        """The earliest time at which `tick` has something to do without a new message (for timers)."""
        times = [r.deadline for r in self.rounds.values()]
        times += [a.last_seen + (self.config.forget_lost_s if a.lost else self.config.heartbeat_timeout_s)
                  for a in self.agents.values()]
        times += [a.silent_until for a in self.agents.values() if a.silent_until is not None]
        for job in self._running():
            times += [u.deadline for u in job.units.values() if u.status == UnitStatus.AWARDED]
        finite = [t for t in times if math.isfinite(t)]
        return min(finite) if finite else None

    def cancel_job(self, job_id: str, reason: str = "cancelled by the user") -> list[Command]:
        job = self.jobs.get(job_id)
        if job is None or job.status != JobStatus.RUNNING:
            return [_ignored(None, "no running job of that id", job_id)]
        out = self._stop_job(job, JobStatus.CANCELLED, reason)
        return [*out, JobCancelled(job_id, reason)]

    # --- queries -------------------------------------------------------------------------------------

    def counts(self, job_id: str) -> Counter[str]:
        return Counter(u.status.value for u in self.jobs[job_id].units.values())

    # --- internals -----------------------------------------------------------------------------------

    def _new_id(self) -> str:
        return f"{self.rng.getrandbits(64):016x}"

    def _forget_lost(self, now: float) -> list[Command]:
        stale = [a for a in self.agents.values()
                 if a.lost and not a.holding and now - a.last_seen > self.config.forget_lost_s]
        for agent in stale:
            self.known_credits[agent.name] = agent.credits
            del self.agents[agent.name]
        return [AgentForgotten(a.name) for a in stale]

    def _running(self) -> list[Job]:
        return sorted((j for j in self.jobs.values() if j.status == JobStatus.RUNNING), key=lambda j: j.order)

    def _is_free(self, agent: Agent, queueing: bool) -> bool:
        """Callable to an auction: live, not in one already, and holding nothing, or with a slot for another
        unit while the farm has plenty of work (`queueing`, from `_queueing`, decided per job at each call)."""
        if agent.lost or agent.invited is not None or agent.silent_until is not None:
            return False
        return not agent.holding or (len(agent.holding) < self._slots(agent) and queueing)

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
        return batch_size(slots) if batched(job.info.level, job.info.first_spp) else 1

    def _queueing(self, job: Job, open_units: int) -> bool:
        """Whether units of `job` may be queued behind others: only while the farm's `open_units` are at
        least max(two of its batches, `queue_above`) per live agent (see `Config.queue_above`)."""
        live = sum(not a.lost for a in self.agents.values())
        return open_units >= max(2 * self._batch(job, self.config.slots), self.config.queue_above) * live

    def _seen(self, agent: Agent, now: float) -> list[Command]:
        agent.last_seen = max(agent.last_seen, now)
        if agent.lost:
            # Back from an outage long enough to lose it: the calls it missed meanwhile are not held against it.
            agent.lost, agent.silences, agent.silent_until = False, 0, None
            return [AgentBack(agent.name)]
        return []

    def _round_for(self, agent: str, conversation: str, job_id: str) -> tuple[Round | None, str]:
        round_ = self.rounds.get(conversation)
        if round_ is None:
            return None, "no open auction with that conversation id"
        if agent not in round_.offered:
            return None, "agent not called to this auction"
        if job_id != round_.job_id:
            return None, "job id does not match the auction"
        if agent in round_.answered:
            return None, "already answered this auction"
        return round_, ""

    def _award_for(
        self, agent: str, job_id: str, index: int, token: str, conv: str
    ) -> tuple[UnitState | None, str]:
        job = self.jobs.get(job_id)
        unit = job.units.get(index) if job else None
        if unit is None:
            return None, "unknown job or unit"
        if unit.status == UnitStatus.DONE:
            return None, "unit already done"
        if job.status != JobStatus.RUNNING:
            return None, f"job is {job.status.value}"
        if unit.status != UnitStatus.AWARDED or unit.agent != agent:
            return None, "unit not awarded to this agent"
        if not hmac.compare_digest(unit.token.encode(), token.encode()):
            return None, "wrong token"
        if conv != unit.conversation:
            return None, "wrong conversation id"
        return unit, ""

    def _resolve(self, round_: Round, now: float) -> list[Command]:
        job = self.jobs.get(round_.job_id)
        for name in round_.offered:
            if name in self.agents and self.agents[name].invited == round_.conversation:
                self.agents[name].invited = None
        out: list[Command] = self._silenced(round_, now)
        if job is None or job.status != JobStatus.RUNNING:
            return out
        wins: dict[str, list[UnitState]] = {}
        units = sorted((job.units[i] for i in round_.units), key=lambda u: (-u.spec.work, u.spec.index))
        usable = self._rates(job).keys()
        for unit in units:
            if unit.status != UnitStatus.ANNOUNCED:
                continue
            full = {name for name, won in wins.items() if len(won) >= round_.room.get(name, 1)}
            winner = self._pick(round_, unit, job, full, now, _excluded(unit, usable))
            if winner is None:
                self._set_unit(job, unit, UnitStatus.PENDING)
            else:
                wins.setdefault(winner, []).append(unit)
                out += self._award(job, unit, winner, round_.bids[winner][unit.spec.index], now)
        out = _batch_deadlines(out, wins)
        for name in sorted(set(round_.bids) - set(wins)):
            if name in self.agents and round_.bids[name]:
                reject = m.Reject(
                    conversation=round_.conversation,
                    job_id=job.info.job_id,
                    reason="units awarded to other agents",
                )
                out.append(Send(name, reject))
        return out

    def _silenced(self, round_: Round, now: float) -> list[Command]:
        """The agents called to `round_` that never answered, each left out of auctions for a while."""
        out: list[Command] = []
        for name in sorted(set(round_.offered) - round_.answered):
            agent = self.agents.get(name)
            if agent is None or agent.lost:
                continue
            agent.silences += 1
            pause = min(self.config.silence_max_s, self.config.cfp_timeout_s * 2 ** (agent.silences - 1))
            agent.silent_until = now + pause
            out.append(AgentSilent(name, pause))
        return out

    # --- the look-ahead --------------------------------------------------------------------------------

    def _project(self, job: Job, now: float, rates: dict[str, float]) -> dict[int, Placement]:
        units = [
            ProjectedUnit(u.spec.index, u.spec.work, _excluded(u, rates.keys()))
            for u in job.units.values()
            if u.status in (UnitStatus.PENDING, UnitStatus.ANNOUNCED)
        ]
        agents = [PlanAgent(name, self._available(self.agents[name], now), rate) for name, rate in rates.items()]
        plan = project(units, agents)
        # Refining pays in the end game, where the last units decide the makespan; earlier the next
        # projection (at the next inform) corrects the list schedule anyway, and refining every tick of
        # a 256-unit, 64-agent job cost ~60 ms of master CPU each time.
        if not self.config.refine_moves or len(units) > self.config.refine_below * max(1, len(agents)):
            return plan
        return refine(plan, units, agents, self.config.refine_moves)

    def _rates(self, job: Job) -> dict[str, float]:
        """Seconds per unit of cost of every live agent the job may use: learnt, or derived from speeds."""
        live = [a for a in self.agents.values()
                if not a.lost and a.silent_until is None and a.name not in job.blocklist]
        job_id = job.info.job_id
        known = {
            a.name: max(a.rates.get(job_id, 0.0), a.late_rates.get(job_id, 0.0))
            for a in live
            if job_id in a.rates or job_id in a.late_rates
        }
        rates = dict(known)
        for a in live:
            if a.name not in known:
                rates[a.name] = self._prior_rate(a, job, known)
        return rates

    def _prior_rate(self, agent: Agent, job: Job, known: dict[str, float]) -> float:
        """Before it bids: its registered speed relative to agents whose rate is known (else 1 / speed)."""
        speed = max(agent.speed, 1e-9)
        if not known:
            return _round_rate(1.0 / speed)
        # rate x speed is the job's cost in speed-seconds: alike for all agents if speeds are right.
        return _round_rate(statistics.median(r * self.agents[n].speed for n, r in known.items()) / speed)

    def _learn_rate(self, agent: Agent, job: Job, bids: dict[int, float]) -> None:
        """The agent's rate on the job from its bids: seconds over cost, summed (big units weigh most)."""
        costs = {i: job.units[i].spec.work for i in bids if i in job.units and job.units[i].spec.work > 0}
        if not costs:
            return
        seconds = sum(max(bids[i], self.config.min_estimate_s) for i in costs)
        rate = min(max(seconds / sum(costs.values()), _MIN_RATE), _MAX_RATE)
        job_id = job.info.job_id
        others = [
            a.rates[job_id]
            for a in self.agents.values()
            if a is not agent and not a.lost and job_id in a.rates
        ]
        if others:
            median, clamp = statistics.median(others), self.config.rate_clamp
            rate = min(max(rate, median / clamp), median * clamp)
        agent.rates[job_id] = _round_rate(rate)

    def _available(self, agent: Agent, now: float) -> float:
        """When the agent should be free: now, or when the units it holds should end (one after the other,
        in award order). An agent past that time is assumed to need as long again as it has overrun (a late
        agent looks ever later)."""
        held = [self.jobs[j].units[i] for j, i in agent.holding if j in self.jobs and i in self.jobs[j].units]
        if not held:
            return now
        end = -math.inf
        for unit in sorted(held, key=lambda u: u.awarded_at):
            end = max(end, unit.awarded_at) + unit.estimate
        return end if end >= now else 2 * now - end

    def _worth_offering(
        self,
        name: str,
        unit: UnitState,
        excluded: frozenset[str],
        plan: dict[int, Placement],
        rates: dict[str, float],
        now: float,
        callable_now: set[str],
    ) -> bool:
        place = plan.get(unit.spec.index)
        if place is None or name in excluded:
            return False
        if place.agent == name:
            return True
        # Contested among agents free now, when this one would finish about as soon (records decide).
        duration = rates[name] * unit.spec.work
        return (
            place.agent in callable_now
            and place.start <= now
            and duration <= (place.finish - now) * (1 + self.config.finish_tolerance) + 1e-9
        )

    def _pick(self, round_: Round, unit: UnitState, job: Job, full: set[str], now: float,
              excluded: frozenset[str]) -> str | None:
        bids = {
            name: bids[unit.spec.index]
            for name, bids in round_.bids.items()
            if unit.spec.index in bids
            and name not in full
            and name in self.agents
            and not self.agents[name].lost
            and name not in job.blocklist
            and name not in excluded
        }
        if not bids:
            return None
        # A bidder still rendering a unit (a free slot) starts this one when that ends.
        finish = {n: self._available(self.agents[n], now) - now + e for n, e in bids.items()}
        fastest = min(finish.values())
        near = {n: f for n, f in finish.items() if f <= fastest * (1 + self.config.finish_tolerance) + 1e-9}
        # Best record first (MAgArRO), then the earlier finish, then the name for determinism.
        return min(near, key=lambda n: (-self.agents[n].score, near[n], n))

    def _award(self, job: Job, unit: UnitState, agent: str, estimate: float, now: float) -> list[Command]:
        self._set_unit(job, unit, UnitStatus.AWARDED)
        unit.agent, unit.token, unit.conversation = agent, f"{self.rng.getrandbits(128):032x}", self._new_id()
        unit.attempts += 1
        start = self._available(self.agents[agent], now)  # after the units it holds already
        unit.awarded_at, unit.estimate = now, estimate
        unit.deadline = start + estimate * self.config.render_factor + self.config.render_slack_s
        self.agents[agent].holding.add((job.info.job_id, unit.spec.index))
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
        event = UnitAwarded(job.info.job_id, unit.spec.index, agent, unit.token, estimate, unit.attempts,
                            unit.deadline)
        return [Send(agent, award), event]

    def _set_unit(self, job: Job, unit: UnitState, status: UnitStatus) -> None:
        """The one place a unit's status changes: checked against `core.model.status.UNIT_TRANSITIONS`."""
        where = f"job {job.info.job_id!r} unit {unit.spec.index}"
        unit.status = unit_transition(where, unit.status, status)

    def _set_job(self, job: Job, status: JobStatus) -> None:
        """The one place a job's status changes: checked against `core.model.status.JOB_TRANSITIONS`."""
        job.status = job_transition(f"job {job.info.job_id!r}", job.status, status)

    def _clear_award(self, job: Job, unit: UnitState, status: UnitStatus) -> None:
        self._set_unit(job, unit, status)
        unit.agent = unit.token = unit.conversation = None
        unit.deadline = math.inf

    def _requeue(self, key: tuple[str, int], reason: str) -> list[Command]:
        """Unit back to the auction without blaming its agent (the agent vanished, not the unit)."""
        job = self.jobs[key[0]]
        unit = job.units[key[1]]
        if unit.agent in self.agents:
            self.agents[unit.agent].holding.discard(key)
        event = UnitRequeued(key[0], key[1], unit.agent, unit.token, reason)
        self._clear_award(job, unit, UnitStatus.PENDING)
        return [event]

    def _fail_unit(self, key: tuple[str, int], reason: str) -> list[Command]:
        """The unit failed on its agent: retry elsewhere; blocklist the agent after repeated failures."""
        job = self.jobs[key[0]]
        unit = job.units[key[1]]
        agent = unit.agent
        state = self.agents[agent]
        state.holding.discard(key)
        state.credits -= 1
        state.recent.append(False)
        unit.failures += 1
        unit.failed_on.add(agent)
        unit.last_reason = reason
        out: list[Command] = [UnitFailed(key[0], key[1], agent, unit.token, reason, state.credits)]
        self._clear_award(job, unit, UnitStatus.PENDING)
        job.failures_by_agent[agent] += 1
        if job.failures_by_agent[agent] >= self.config.blocklist_after and agent not in job.blocklist:
            job.blocklist.add(agent)
            why = f"{job.failures_by_agent[agent]} failed units of this job"
            out.append(AgentBlocklisted(key[0], agent, why))
        return out + self._fail_if_stuck(job)

    def _fail_if_stuck(self, job: Job) -> list[Command]:
        """Fail the job when a remaining unit failed too often, or every agent the farm knows (lost ones
        may come back until they are forgotten) is blocklisted for it."""
        for unit in sorted(job.units.values(), key=lambda u: u.spec.index):
            if unit.status != UnitStatus.PENDING:
                continue
            if unit.failures >= self.config.max_unit_failures:
                why = f"unit {unit.spec.index} failed {unit.failures} times; last: {unit.last_reason}"
            elif self.agents and unit.failures and not set(self.agents) - job.blocklist:
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

    def _stop_job(self, job: Job, status: JobStatus, reason: str) -> list[Command]:
        out: list[Command] = []
        self._set_job(job, status)
        job.error = reason
        for unit in job.units.values():
            if unit.status == UnitStatus.AWARDED:
                self.agents[unit.agent].holding.discard((job.info.job_id, unit.spec.index))
                out.append(
                    Send(
                        unit.agent,
                        m.Cancel(
                            conversation=unit.conversation,
                            job_id=job.info.job_id,
                            index=unit.spec.index,
                            reason=reason[:1024],
                        ),
                    )
                )
            if unit.status != UnitStatus.DONE:
                self._clear_award(job, unit, UnitStatus.FAILED)
        return out

    def _finish_if_done(self, job: Job) -> list[Command]:
        if job.status == JobStatus.RUNNING and all(u.status == UnitStatus.DONE for u in job.units.values()):
            self._set_job(job, JobStatus.DONE)
            return [JobDone(job.info.job_id)]
        return []


_MIN_RATE, _MAX_RATE = 1e-9, 1e9  # seconds per unit of cost: the projection's arithmetic stays finite


def _ignored(
    agent: str | None, reason: str, job_id: str | None = None, index: int | None = None
) -> MessageIgnored:
    return MessageIgnored(agent, reason, job_id, index)
