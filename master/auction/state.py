"""The auction's state: its settings, and what it knows of each job, unit, agent and open auction round.

Plain records: only `master.auction.machine.Auction` changes them, each unit's status through the table of
`core.model.status`, with the change kept in the unit's story. Beside them it keeps indexes, so that its
ticks need not read every unit and agent: a job's units by status, its open units by cost and its awards by
deadline (`Job`), and the agents its ticks watch (`Watch`); `Auction.validate` checks them against the
records.
"""

from __future__ import annotations

import bisect
import heapq
import math
from collections import Counter, deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple, Protocol

from core.model import messages as m
from core.model.status import JobStatus, UnitStatus
from core.model.units import SLOTS, WorkUnit
from master.auction.passes import PassBook, ResumedPasses
from planning.progressive import Goal

STORY_LENGTH = 32  # changes of status kept per unit (the oldest are forgotten)
OPEN = frozenset({UnitStatus.PENDING, UnitStatus.ANNOUNCED})  # a unit the auction has yet to award


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
    # A budget job's pass holds at least this many samples (its unit's pixels x spp) where the unit has them:
    # each pass pays an award, a render call, a tile's upload and its record, ~17 ms on a 2-agent farm here
    # (cbox 512 px at level VB in five passes a unit: 170 passes rendered 4.1 s, its 34 units whole 1.8 s).
    # 2^18 samples render in ~70 ms on this machine's 2 cores; bench hosts' units (6.4 M samples) keep
    # their five passes. 1: every unit in its five passes, however small.
    pass_samples: int = 1 << 18
    max_cfp_units: int = m.MAX_CFP_UNITS
    upload_url: str = "http://127.0.0.1:8765/jobs/{job}/units/{index}/tile"


@dataclass(frozen=True)
class Transition:
    """One change of a unit's status: the stimulus that made it, from what to what, at what auction time."""

    stimulus_id: str
    start: str
    finish: str
    at: float


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
    @property
    def goal(self) -> Goal | None: ...  # a progressive job's
    @property
    def resumed(self) -> ResumedPasses | None: ...  # a progressive job's passes so far
    @property
    def channels(self) -> Sequence[str] | None: ...  # what every tile of the job carries


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
    withdrawn: bool = False  # a pass its job no longer needs: failed, and never requeued
    story: deque[Transition] = field(default_factory=lambda: deque(maxlen=STORY_LENGTH))


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
    threads: int | None = None  # its render threads, as its Register told (None: not told)
    host: str | None = None  # the machine it runs on, as its Register told
    draining: bool = False  # the user drained it: no new award, it finishes what it holds
    # Seconds per unit of cost, per job: from its latest bids, and from its last unit that overran.
    rates: dict[str, float] = field(default_factory=dict)
    late_rates: dict[str, float] = field(default_factory=dict)
    # When the units it holds should end, one after the other in award order (-inf: none): kept by the
    # auction as it awards and releases them (`Auction._hold`, `_release`).
    held_end: float = -math.inf

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
    channels: tuple[str, ...] | None = None  # what every tile of the job carries (None: not checked)
    passes: PassBook | None = None  # a progressive job's decisions (its units are its passes)
    # Kept by `add` and `moved`, so that the auction's ticks need not read every unit: unit indices by
    # status; the open (pending or announced) units' (-cost, index), sorted (the most costly first), their
    # costs in the same order, and those that failed before.
    by_status: dict[UnitStatus, set[int]] = field(default_factory=dict)
    open_order: list[tuple[float, int]] = field(default_factory=list)
    open_costs: list[float] = field(default_factory=list)
    open_failed: set[int] = field(default_factory=set)
    # The awarded units' (deadline, index, attempts), a heap (`set_deadline`): entries of units since done,
    # failed or awarded again are dropped when met.
    due: list[tuple[float, int, int]] = field(default_factory=list)

    def __post_init__(self) -> None:
        for unit in self.units.values():
            self._index(unit.spec.index, unit.status)

    def add(self, unit: UnitState) -> None:
        """A unit, new or in place of the one of its index (a progressive job's passes: pass 0 of each unit
        takes the unit's own index)."""
        index = unit.spec.index
        if index in self.units:
            self._unindex(index, self.units[index].status)
        self.units[index] = unit
        self._index(index, unit.status)

    def clear(self) -> None:
        """No units (a progressive job's submitted units become templates of its passes)."""
        self.units.clear()
        self.by_status.clear()
        self.open_order.clear()
        self.open_costs.clear()
        self.open_failed.clear()
        self.due.clear()

    def moved(self, index: int, start: UnitStatus, end: UnitStatus) -> None:
        """Unit `index` went from `start` to `end` (the machine's one place of status changes calls this)."""
        self.by_status[start].discard(index)
        self.by_status.setdefault(end, set()).add(index)
        if (start in OPEN) != (end in OPEN):
            (self._order if end in OPEN else self._unorder)(index)

    def open_count(self) -> int:
        return len(self.open_order)

    def _index(self, index: int, status: UnitStatus) -> None:
        self.by_status.setdefault(status, set()).add(index)
        if status in OPEN:
            self._order(index)

    def _unindex(self, index: int, status: UnitStatus) -> None:
        self.by_status[status].discard(index)
        if status in OPEN:
            self._unorder(index)

    def _order(self, index: int) -> None:
        key = self._order_key(index)
        at = bisect.bisect_left(self.open_order, key)
        self.open_order.insert(at, key)
        self.open_costs.insert(at, -key[0])
        if self.units[index].failed_on:  # a unit fails while awarded: this holds while it is open
            self.open_failed.add(index)

    def _unorder(self, index: int) -> None:
        at = bisect.bisect_left(self.open_order, self._order_key(index))
        del self.open_order[at], self.open_costs[at]
        self.open_failed.discard(index)

    def _order_key(self, index: int) -> tuple[float, int]:
        return -self.units[index].spec.work, index

    def set_deadline(self, unit: UnitState, deadline: float) -> None:
        """The render deadline of `unit`, awarded (`due` keeps it)."""
        if math.isfinite(deadline):
            heapq.heappush(self.due, (deadline, unit.spec.index, unit.attempts))
        unit.deadline = deadline

    def pop_late(self, now: float) -> list[UnitState]:
        """The awarded units past their render deadline at `now`, by index. They leave `due`: the auction
        fails them."""
        late: dict[int, UnitState] = {}
        while self.due and self.due[0][0] < now:
            entry = heapq.heappop(self.due)
            if self._current(entry):
                late[entry[1]] = self.units[entry[1]]
        return [late[i] for i in sorted(late)]

    def next_due(self) -> float | None:
        """The earliest render deadline of an awarded unit (None: none is finite)."""
        while self.due and not self._current(self.due[0]):
            heapq.heappop(self.due)
        return self.due[0][0] if self.due else None

    def _current(self, entry: tuple[float, int, int]) -> bool:
        deadline, index, attempts = entry
        unit = self.units.get(index)
        return (unit is not None and unit.status == UnitStatus.AWARDED and unit.attempts == attempts
                and unit.deadline == deadline)

    def having(self, *statuses: UnitStatus) -> list[UnitState]:
        """The units in any of `statuses`, by index."""
        indices = sorted(i for status in statuses for i in self.by_status.get(status, ()))
        return [self.units[i] for i in indices]


@dataclass
class Watch:
    """What the auction's ticks need of its agents without reading every one: the lost ones, the silent ones
    (`silent_until` set), those it may call to an auction (`Auction._callable`), and the live ones'
    last_seen in a heap (`beat` at each change; entries of agents heard from again, lost or forgotten since
    are dropped when met). The auction keeps it wherever those change; `Auction.validate` checks it."""

    lost: set[str] = field(default_factory=set)
    silent: set[str] = field(default_factory=set)
    callable: set[str] = field(default_factory=set)
    beats: list[tuple[float, str]] = field(default_factory=list)

    def beat(self, agent: Agent) -> None:
        heapq.heappush(self.beats, (agent.last_seen, agent.name))

    def oldest_beat(self, agents: Mapping[str, Agent]) -> float | None:
        """The earliest last_seen of a live agent (None: none is live)."""
        while self.beats:
            seen, name = self.beats[0]
            agent = agents.get(name)
            if agent is not None and not agent.lost and agent.last_seen == seen:
                return seen
            heapq.heappop(self.beats)
        return None


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
