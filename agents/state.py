"""The render agent's decisions as a pure state machine: typed stimuli in, typed instructions out, no I/O.

`AgentState.handle(stimulus, now)` is its one entry, after dask.distributed's worker state machine (beside the
master's `master.auction.Auction`): no asyncio, no clock, no network, no Mitsuba. `agents.render_agent` feeds it
and carries out what it returns; tests/test_agent_state.py drives it with a fake clock.

Stimuli (each with a `stimulus_id`): `MessageReceived` (the master's message), `Measured`, `Tick`,
`BundleReady`/`BundleFailed`, `RenderFinished`/`RenderFailed`, `UploadDone`/`UploadFailed`.
Instructions: `SendToMaster`, `FetchBundle`, `StartRender` (with `Batched` units), `AbortRender`, `Upload`,
`DiscardTile`, `Log`. Each held unit (`Work`) has a `WorkStatus`, changed only as `TRANSITIONS` allows;
`validate()` checks the state's invariants and `story(job_id, index)` lists a unit's status changes.
"""

from __future__ import annotations

import itertools
import logging
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Protocol

from core.errors import QuekaroError
from core.model import messages as m
from core.model.job import SceneSpec
from core.model.status import TransitionError
from core.model.units import SLOTS, WorkUnit, batch_size, batched

HEARTBEAT_S = 2.0
MAX_RENDER_S = 6 * 3600.0  # a render longer than this is killed whatever the estimate
FINISHED_MEMORY = 4096  # (job, unit, token) of finished awards remembered to ignore their duplicates
STORY_LENGTH = 32  # status changes remembered per unit (of at most FINISHED_MEMORY units)
MAX_BUSY = 256  # units listed in one heartbeat (Heartbeat.busy's limit)
MAX_REASON = 1024  # characters of a Refuse's or Failure's reason

Key = tuple[str, int]


class Params(Protocol):
    """What the rules chose for one unit (core.rules.unit_params.RenderParams fits)."""

    @property
    def depth(self) -> int: ...

    @property
    def spp(self) -> int: ...

    @property
    def band(self) -> int: ...


PlanFn = Callable[[m.JobInfo, tuple[WorkUnit, ...]], Sequence[Params]]
SecondsFn = Callable[[float, int, float], float]  # (unit cost, spp, speed) -> seconds: agents.speed.estimate_seconds


# ---- stimuli -----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Stimulus:
    """Something that happened, fed to `AgentState.handle`. `stimulus_id` names it in the units' stories
    (agents.render_agent gives every one a readable, unique id)."""

    stimulus_id: str = field(default="", kw_only=True)


@dataclass(frozen=True)
class MessageReceived(Stimulus):
    """A message of the master's (`m.CallForProposal`, `m.Award`, `m.Reject`, `m.Cancel`, `m.Welcome`,
    `m.Introduce`; an `m.Awards` goes in as one of these per award)."""

    message: m.Message


@dataclass(frozen=True)
class Measured(Stimulus):
    """The agent's measured speed (mega-rays/s) and what compiling a new kernel costs on top (s)."""

    speed: float
    compile_s: float = 0.0


@dataclass(frozen=True)
class Tick(Stimulus):
    """Time passes. `online`: connected to the XMPP server now; `connection`: which connection (a number that
    changes on every reconnect, so that the agent registers again)."""

    online: bool = True
    connection: int = 0


@dataclass(frozen=True)
class BundleReady(Stimulus):
    """The scene of the unit under `ticket` is on disk."""

    ticket: int
    scene: SceneSpec


@dataclass(frozen=True)
class BundleFailed(Stimulus):
    ticket: int
    reason: str


@dataclass(frozen=True)
class RenderFinished(Stimulus):
    """The unit is rendered and its tile written at `path`; `seconds` the render's own time, `spp` the samples
    per pixel Mitsuba took (a stratified sampler rounds the rules' count; None: the rules' count)."""

    ticket: int
    path: Path
    seconds: float
    nonfinite: int = 0
    spp: int | None = None


@dataclass(frozen=True)
class RenderFailed(Stimulus):
    ticket: int
    reason: str


@dataclass(frozen=True)
class UploadDone(Stimulus):
    """The tile is uploaded (the master took it: the unit is done)."""

    ticket: int


@dataclass(frozen=True)
class UploadFailed(Stimulus):
    ticket: int
    reason: str


# ---- instructions ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Instruction:
    """What `AgentState.handle` asks its caller to do, in order."""


@dataclass(frozen=True)
class SendToMaster(Instruction):
    """Send `message` to the master."""

    message: m.Message


@dataclass(frozen=True)
class FetchBundle(Instruction):
    """Make the job's scene bundle available (fetch it with `token` unless cached); answer BundleReady or
    BundleFailed."""

    ticket: int
    job: m.JobInfo
    token: str = field(repr=False)


@dataclass(frozen=True)
class Batched:
    """A further unit of a StartRender: rendered in the same call as the first."""

    ticket: int
    award: m.Award = field(repr=False)
    params: Params


@dataclass(frozen=True)
class StartRender(Instruction):
    """Render the award's unit with `params` in the render process, and the units in `more` (same job and
    depth) with it in one call where the scene allows, killed after `timeout_s`; write their tiles; answer
    RenderFinished or RenderFailed for each ticket."""

    ticket: int
    award: m.Award = field(repr=False)
    scene: SceneSpec
    params: Params
    timeout_s: float
    more: tuple[Batched, ...] = ()

    @property
    def tickets(self) -> tuple[int, ...]:
        return (self.ticket, *(b.ticket for b in self.more))


@dataclass(frozen=True)
class AbortRender(Instruction):
    """End the render under `ticket` now, if it still runs (its unit was cancelled); it then answers
    RenderFailed, and the next render starts a new render process."""

    ticket: int


@dataclass(frozen=True)
class Upload(Instruction):
    """Hash the tile at `path` and upload it with the award's token; answer UploadDone or UploadFailed."""

    ticket: int
    award: m.Award = field(repr=False)
    path: Path


@dataclass(frozen=True)
class DiscardTile(Instruction):
    """Delete the unit's tile file, if any (uploaded, failed or cancelled)."""

    job_id: str
    index: int


@dataclass(frozen=True)
class Log(Instruction):
    level: int
    text: str


# ---- a unit's status -----------------------------------------------------------------------------------

# queued: awarded, waiting for the render process; fetching: its render step fetches the bundle; rendering;
# uploading: its tile (held until the upload ends); done, failed: answered; cancelled: taken back by the master
# (perhaps still in its render step or upload, whose end is then discarded).
WorkStatus = Literal["queued", "fetching", "rendering", "uploading", "done", "failed", "cancelled"]
HELD: frozenset[WorkStatus] = frozenset({"queued", "fetching", "rendering", "uploading"})

TRANSITIONS: frozenset[tuple[WorkStatus, WorkStatus]] = frozenset({
    ("queued", "fetching"),  # the render process is free: the oldest award's step begins with its bundle
    ("queued", "rendering"),  # batched into an older unit's call (same job and depth)
    ("queued", "failed"),  # an award naming URLs other than the master's: never started
    ("fetching", "rendering"),  # its bundle is here and it is planned
    ("fetching", "failed"),  # no bundle, or no plan
    ("rendering", "uploading"),
    ("rendering", "failed"),
    ("uploading", "done"),
    ("uploading", "failed"),
    *((held, "cancelled") for held in ("queued", "fetching", "rendering", "uploading")),
})


@dataclass(frozen=True)
class Transition:
    """One status change of a unit, in its story: the stimulus that made it, from what (None: the award
    that created its Work) to what, and when (`handle`'s `now`)."""

    stimulus_id: str
    start: WorkStatus | None
    finish: WorkStatus
    at: float


# ---- state -----------------------------------------------------------------------------------------


@dataclass(eq=False)
class Work:
    """One awarded unit on its way: the latest award and its status. `ticket` names it in stimuli and
    instructions (a unit awarded again after a cancel is a new Work with a new ticket)."""

    ticket: int
    award: m.Award
    status: WorkStatus = "queued"  # changed by AgentState._move only
    started: float = 0.0  # when its render step began (bundle, plan, render, tile)
    share: float = 1.0  # its part of its render step's seconds: its base estimate over its batch's
    predicted: float | None = None  # its uncorrected estimate when its step began (calibration's reference)
    params: Params | None = None
    rendered: RenderFinished | None = None
    uploaded_as: m.Award | None = None  # the award its tile was uploaded under (the latest at the time)

    @property
    def key(self) -> Key:
        return self.award.job.job_id, self.award.unit.index

    @property
    def cancelled(self) -> bool:
        """The master took it back."""
        return self.status == "cancelled"

    def __str__(self) -> str:
        return f"unit {self.key[1]} of job {self.key[0]} (ticket {self.ticket}, {self.status})"


JOBS_KEPT = 64  # jobs an agent remembers having rendered (AgentState.jobs_rendered)


class Calibration:
    """Per job, the ratio of a unit's real wall time to its uncorrected estimate (moving average).

    The base estimate (agents/speed.py) misses what the reference render cannot know: scene loading,
    kernel compilation, bundle transfer, and a master cost scale that differs from rays (level off).
    """

    def __init__(self, alpha: float = 0.5, max_jobs: int = 64) -> None:
        self.alpha = alpha
        self.ratios: dict[str, float] = {}
        self.max_jobs = max_jobs

    def factor(self, job_id: str) -> float:
        return self.ratios.get(job_id, 1.0)

    def learn(self, job_id: str, base_estimate: float, actual: float) -> None:
        if base_estimate <= 0 or actual <= 0:
            return
        ratio = actual / base_estimate
        old = self.ratios.pop(job_id, None)
        self.ratios[job_id] = ratio if old is None else old + self.alpha * (ratio - old)
        while len(self.ratios) > self.max_jobs:  # oldest job first (dicts keep insertion order)
            self.ratios.pop(next(iter(self.ratios)))


class AgentState:
    """One render agent's state; `handle(stimulus, now)` returns what to do. `plan(job, units)` gives each
    unit's parameters (the agent's rules), `seconds(cost, spp, speed)` a render's base estimate.

    It holds at most `slots` units (awarded, not answered, not cancelled) and bids only below that; it
    renders one step at a time, in award order (the protocol is in agents/render_agent.py's docstring)."""

    def __init__(self, plan: PlanFn, seconds: SecondsFn, *, slots: int = SLOTS, threads: int = 1,
                 rules: str = "", heartbeat_s: float = HEARTBEAT_S, max_render_s: float = MAX_RENDER_S,
                 session: str = "0", check_url: Callable[[str], str | None] = lambda _url: None,
                 batch: int | None = None, rules_sha256: str | None = None,
                 defuzzifier: str | None = None, host: str | None = None) -> None:
        if slots < 1:
            raise ValueError(f"slots must be at least 1, got {slots}")
        self.batch = batch_size(slots) if batch is None else batch
        if not 1 <= self.batch <= slots:
            raise ValueError(f"batch must be from 1 to slots ({slots}), got {batch}")
        self.plan, self.seconds = plan, seconds
        self.check_url = check_url  # why a data plane URL is refused (not the master's, plain HTTP across a network)
        self.slots, self.threads, self.rules = slots, threads, rules[:256]
        self.rules_sha256, self.defuzzifier, self.host = rules_sha256, defuzzifier, host  # told in Register
        self.heartbeat_s, self.max_render_s, self.session = heartbeat_s, max_render_s, session
        self.speed: Measured | None = None
        self.calibration = Calibration()
        self.works: dict[Key, Work] = {}  # held: awarded, not answered, not cancelled (award order)
        self.queue: deque[Work] = deque()  # held, waiting for the render process
        # In the render step (perhaps cancelled since): the first unit from its bundle fetch on, the units
        # batched with it from its StartRender on; `_step_ticket` the first's ticket (an abort's).
        self.step: list[Work] = []
        self._step_ticket = 0
        self.delivering: dict[int, Work] = {}  # tiles uploading, by ticket
        self.finished: dict[tuple[str, int, str], None] = {}  # (job, unit, token) answered, oldest first
        self.planned: dict[Key, Params] = {}  # the rules' choice per unit bid on, oldest first
        self.kernels: set[tuple[Any, ...]] = set()  # what the render process has compiled
        self.jobs_rendered: dict[str, None] = {}  # jobs with a render call here, the latest JOBS_KEPT
        self.units_done = 0
        self.units_failed = 0
        self._tickets = itertools.count(1)
        self._conversations = itertools.count(1)
        self._registered_on: int | None = None  # the connection it last registered on
        # Conversations of its Registers on that connection while no Welcome answered one (empty: answered).
        self._unwelcomed: set[str] = set()
        self._next_beat = 0.0
        self._stories: dict[Key, deque[Transition]] = {}  # per unit, its last status changes; oldest unit first
        self._stimulus: tuple[str, float] = ("", 0.0)  # the stimulus being handled: its id, its `now`

    def handle(self, stimulus: Stimulus, now: float) -> list[Instruction]:
        """Apply one stimulus at time `now` (seconds, any epoch); the instructions to carry out, in order."""
        if not isinstance(stimulus, Stimulus):
            raise TypeError(f"not an agent stimulus: {type(stimulus).__name__}")
        self._stimulus = (stimulus.stimulus_id, now)
        match stimulus:
            case MessageReceived(message=message):
                return self._on_message(message, now)
            case Tick():
                return self._on_tick(stimulus, now)
            case Measured():
                self.speed = stimulus
                return []
            case BundleReady():
                return self._on_bundle(stimulus, now)
            case BundleFailed() | RenderFailed():
                return self._on_render_failed(stimulus, now)
            case RenderFinished():
                return self._on_rendered(stimulus, now)
            case UploadDone() | UploadFailed():
                return self._on_uploaded(stimulus, now)
        raise TypeError(f"not an agent stimulus: {type(stimulus).__name__}")

    def _on_message(self, message: m.Message, now: float) -> list[Instruction]:
        match message:
            case m.CallForProposal():
                return self._on_cfp(message)
            case m.Award():
                return self._on_award(message, now)
            case m.Cancel():
                return self._on_cancel(message)
            case m.Reject():
                return [Log(logging.DEBUG, f"rejected in {message.conversation}: {message.reason}")]
            case m.Welcome():
                return self._on_welcome(message)
            case m.Introduce():
                return self._on_introduce(message)
        return [Log(logging.WARNING, f"{message.performative} in {message.conversation}: not for an agent")]

    # ---- what it holds --------------------------------------------------------------------------------

    def busy_units(self) -> tuple[m.HeldUnit, ...]:
        """The units this agent holds: awarded, not answered, not cancelled."""
        return tuple(m.HeldUnit(job_id=j, index=i) for j, i in sorted(self.works))

    @property
    def rendering(self) -> Work | None:
        """The first unit of the render step, if one is in it."""
        return self.step[0] if self.step else None

    def is_free(self) -> bool:
        """Room for another unit: it holds fewer than `slots` (rendering, waiting or uploading). With one
        slot, also not rendering at all (not even a cancelled unit)."""
        if self.slots == 1:
            return not self.step and not self.works
        return len(self.works) < self.slots

    # ---- status, story, invariants --------------------------------------------------------------------

    def _move(self, work: Work, finish: WorkStatus) -> None:
        """Every status change of a Work goes here: TransitionError unless TRANSITIONS allows it."""
        if (work.status, finish) not in TRANSITIONS:
            raise TransitionError(f"{work}: {work.status} -> {finish} is not an allowed status change")
        self._record(work.key, work.status, finish)
        work.status = finish

    def _record(self, key: Key, start: WorkStatus | None, finish: WorkStatus) -> None:
        story = self._stories.pop(key, None) or deque(maxlen=STORY_LENGTH)
        story.append(Transition(self._stimulus[0], start, finish, self._stimulus[1]))
        _remember(self._stories, key, story)

    def story(self, job_id: str, index: int) -> list[Transition]:
        """The unit's last status changes (at most STORY_LENGTH), oldest first; [] once forgotten (the
        stories of the FINISHED_MEMORY units changed last are kept)."""
        return list(self._stories.get((job_id, index), ()))

    def validate(self) -> None:
        """Check the invariants between the held units, the queue, the render step, the uploads and the
        statuses; AssertionError naming the unit. Not one: holding at most `slots`, for it takes every
        award (the master keeps to the slots it registered)."""
        for work in self.queue:
            _expect(work.status == "queued" and self.works.get(work.key) is work, work, "in the queue")
        self._validate_step()
        for ticket, work in self.delivering.items():
            _expect(work.ticket == ticket and work.status in ("uploading", "cancelled"), work, "uploading")
            _expect(work.rendered is not None and work.uploaded_as is not None, work, "uploading, not rendered")
            _expect(work.cancelled or self.works.get(work.key) is work, work, "uploading, not held")
        for key, work in self.works.items():
            _expect(work.key == key and work.status in HELD, work, f"held under {key}")
            where = {"queued": self.queue, "uploading": self.delivering.values()}.get(work.status, self.step)
            _expect(sum(w is work for w in (*self.queue, *self.step, *self.delivering.values())) == 1
                    and any(w is work for w in where), work, "not in exactly the collection its status says")
            story = self._stories.get(key)
            _expect(not story or story[-1].finish == work.status, work, "its story ends in another status")
        bounded = {"finished": self.finished, "planned": self.planned, "stories": self._stories}
        for name, memory in bounded.items():
            if len(memory) > FINISHED_MEMORY:
                raise AssertionError(f"{name}: {len(memory)} entries, more than {FINISHED_MEMORY}")
        if self._unwelcomed and self._registered_on is None:
            raise AssertionError(f"Registers {sorted(self._unwelcomed)} awaited, but never registered")

    def _validate_step(self) -> None:
        """The render step: its units fetching (the first, alone), rendering or cancelled, at most `batch`;
        never idle while a unit waits."""
        if not self.step and self.queue:
            raise AssertionError(f"no render step, but {self.queue[0]} waits")
        if len(self.step) > self.batch:
            raise AssertionError(f"{len(self.step)} units in the render step, batches of {self.batch}")
        for n, work in enumerate(self.step):
            _expect(work.status in ("fetching", "rendering", "cancelled"), work, "in the render step")
            _expect(work.status != "fetching" or len(self.step) == 1, work, "fetching, with others in its step")
            _expect(work.status != "rendering" or work.params is not None, work, "rendering without a plan")
            _expect(work.cancelled or self.works.get(work.key) is work, work, "in the render step, not held")
            _expect(work not in self.step[n + 1:] and work not in self.delivering.values(), work, "twice")

    # ---- estimates ------------------------------------------------------------------------------------

    def estimate(self, job: m.JobInfo, unit: WorkUnit, params: Params) -> float:
        """Seconds this agent expects to spend on the unit: base seconds (cost x spp / speed), plus a kernel
        compilation if it has not rendered its window (`_kernel`), times the job's `Calibration` (the ratio
        of measured to estimated seconds of its done units)."""
        return self.uncorrected(job, unit, params) * self.calibration.factor(job.job_id)

    def uncorrected(self, job: m.JobInfo, unit: WorkUnit, params: Params) -> float:
        compile_s = 0.0
        if self.speed is not None and self._kernel(job, unit, params) not in self.kernels:
            compile_s = self.speed.compile_s  # Dr.Jit bakes the window size and the depth into the kernel
        return self.base_estimate(unit, params, job) + compile_s

    def base_estimate(self, unit: WorkUnit, params: Params, job: m.JobInfo | None = None) -> float:
        """Its render's seconds at this agent's measured speed, on the threads `job` renders on here (the
        speed was measured on all of them; a render is about as much slower as it has fewer)."""
        slower = self.threads / self.threads_for(job) if job is not None else 1.0
        return self.seconds(unit.cost, params.spp, self.speed.speed if self.speed else 1.0) * slower

    def threads_for(self, job: m.JobInfo) -> int:
        """The threads the job's renders run on here: its own (`submit -t`), never more than this agent's."""
        return min(job.threads, self.threads) if job.threads is not None else self.threads

    # ---- messages in ----------------------------------------------------------------------------------

    def _on_cfp(self, cfp: m.CallForProposal) -> list[Instruction]:
        """Propose an estimate per offered unit while `is_free`, remembering the plans; else Refuse (also a
        data plane URL it refuses, or units its rules cannot plan)."""
        job_id = cfp.job.job_id
        refused = self.check_url(cfp.job.scene_url)
        if refused:
            return [self._refuse(cfp, refused)]
        if not self.is_free():
            held = ", ".join(f"{j}/{i}" for j, i in self.works) or "a cancelled unit"
            return [self._refuse(cfp, f"busy rendering {held}")]
        try:
            plans = list(self.plan(cfp.job, cfp.units))
        except Exception as exc:  # a rule base that cannot plan this job: say so rather than bid
            return [self._refuse(cfp, f"cannot plan units: {type(exc).__name__}: {exc}")]
        for unit, params in zip(cfp.units, plans, strict=True):
            _remember(self.planned, (job_id, unit.index), params)
        estimates = tuple(m.Estimate(index=u.index, seconds=min(self.estimate(cfp.job, u, p), 1e9))
                          for u, p in zip(cfp.units, plans, strict=True))
        text = ", ".join(f"{e.index}: {e.seconds:.3f} s" for e in estimates)
        return [Log(logging.INFO, f"proposing for {job_id}: {text}"),
                SendToMaster(m.Propose(conversation=cfp.conversation, job_id=job_id, estimates=estimates))]

    @staticmethod
    def _refuse(cfp: m.CallForProposal, reason: str) -> SendToMaster:
        return SendToMaster(m.Refuse(conversation=cfp.conversation, job_id=cfp.job.job_id,
                                     reason=reason[:MAX_REASON]))

    def _on_award(self, award: m.Award, now: float) -> list[Instruction]:
        """A new unit queues (and starts if the render process is free). A duplicate (same unit, same token)
        is ignored, also after the unit is done; a re-award with a new token replaces the token it answers
        under. A unit it never bid on is planned when its step begins."""
        key = (award.job.job_id, award.unit.index)
        if (*key, award.token) in self.finished:
            return [Log(logging.INFO, f"{_unit(key)}: duplicate award ignored, the unit is finished")]
        work = self.works.get(key)
        if work is not None:
            if work.award.token == award.token:
                return []  # a duplicate of the award it holds
            work.award = award
            return [Log(logging.INFO, f"{_unit(key)}: re-awarded, answering under the new award")]
        work = Work(next(self._tickets), award)
        self._record(key, None, work.status)
        refused = self.check_url(award.job.scene_url) or self.check_url(award.upload_url)
        if refused:  # never fetched from nor uploaded to: an award naming other URLs is not the master's
            return self._fail(work, f"award refused: {refused}")
        self.works[key] = work
        self.queue.append(work)
        return self._start_next(now)

    def _on_cancel(self, cancel: m.Cancel) -> list[Instruction]:
        """One unit or a whole job, answered with nothing: queued units never start, one whose bundle is being
        fetched is not rendered, and a render in flight is ended once none of its units is wanted (its render
        process killed: the compiled kernels go with it, but a long render left to run held the agent, which
        looked free, and made the next unit awarded to it miss its deadline)."""
        out: list[Instruction] = []
        cancelled: list[Work] = []
        for key, work in list(self.works.items()):
            if key[0] == cancel.job_id and cancel.index in (None, key[1]):
                self._move(work, "cancelled")
                cancelled.append(work)
                del self.works[key]
                out.append(Log(logging.INFO, f"{_unit(key)}: cancelled by the master: {cancel.reason}"))
        self.queue = deque(w for w in self.queue if not w.cancelled)
        # A render in flight is ended once nothing in it is still wanted (a batch's other units go on).
        rendering = self.step and self.step[0].params is not None
        if rendering and all(w.cancelled for w in self.step) and any(w in cancelled for w in self.step):
            out.append(AbortRender(self._step_ticket))
        return out

    def _on_tick(self, tick: Tick, now: float) -> list[Instruction]:
        """Register on every new connection (once the speed is known), and again with each heartbeat until
        the master's Welcome answers one; a Heartbeat every `heartbeat_s` listing the held units."""
        if not tick.online:
            return []
        out: list[Instruction] = []
        if tick.connection != self._registered_on and self.speed is not None:
            self._registered_on, self._next_beat = tick.connection, now
            self._unwelcomed = set()
            out.append(self._register())
        elif self._unwelcomed and now >= self._next_beat:
            out.append(self._register())  # unanswered: the master may have been offline when it came
        if self._registered_on is not None and now >= self._next_beat:
            busy = self.busy_units()[:MAX_BUSY]
            out.append(SendToMaster(m.Heartbeat(conversation=self._conversation("hb"), busy=busy)))
            self._next_beat = now + self.heartbeat_s
        return out

    def _register(self) -> SendToMaster:
        conversation = self._conversation("register")
        self._unwelcomed.add(conversation)
        return SendToMaster(m.Register(conversation=conversation, speed=self.speed.speed, threads=self.threads,
                                       rules=self.rules, slots=self.slots, rules_sha256=self.rules_sha256,
                                       defuzzifier=self.defuzzifier, host=self.host))

    def _on_welcome(self, welcome: m.Welcome) -> list[Instruction]:
        """The master heard a Register of this connection: no more of them until the next connection."""
        if welcome.conversation not in self._unwelcomed:
            return [Log(logging.DEBUG, f"welcome in {welcome.conversation}: not a Register of this connection")]
        self._unwelcomed = set()
        return []

    def _on_introduce(self, ask: m.Introduce) -> list[Instruction]:
        """The master knows this agent from heartbeats only: Register again (and until a Welcome answers)."""
        if self._registered_on is None:
            return [Log(logging.DEBUG, f"introduce in {ask.conversation}: not registered yet, Register follows")]
        return [self._register()]

    def _conversation(self, kind: str) -> str:
        return f"{kind}-{self.session}-{next(self._conversations):x}"

    # ---- a unit's way: bundle, plan, render, upload ---------------------------------------------------

    def _start_next(self, now: float) -> list[Instruction]:
        """The render process is free and a unit waits: the oldest award's step begins (one at a time; the
        next as soon as the last one's tiles are written, while they upload)."""
        if self.step or not self.queue:
            return []
        work = self.queue.popleft()
        self._move(work, "fetching")
        self.step, self._step_ticket = [work], work.ticket
        work.started = now
        return [FetchBundle(work.ticket, work.award.job, work.award.token)]

    def _on_bundle(self, ready: BundleReady, now: float) -> list[Instruction]:
        """Plan the unit and render it, with the waiting units of its job and depth (`_batch_with`); not if
        it was cancelled meanwhile."""
        work = self._in_step(ready.ticket)
        if work is None:
            return [Log(logging.DEBUG, f"bundle of ticket {ready.ticket}: no such render")]
        if work.cancelled:
            self.step = []
            return [Log(logging.INFO, f"{_unit(work.key)}: cancelled before its render, not rendered"),
                    *self._start_next(now)]
        try:
            params = self._params_for(work, take=True)
        except Exception as exc:
            return self._on_render_failed(RenderFailed(work.ticket, describe(exc)), now)
        work.params = params
        self._move(work, "rendering")
        more = self._batch_with(work, now)
        self._rendered(work.award.job.job_id)
        base = [self.base_estimate(w.award.unit, w.params) for w in self.step]
        # One kernel a call: a new one's compilation is shared by the batch, as its seconds are.
        compile_s = self.uncorrected(work.award.job, work.award.unit, params) - base[0]
        for member, seconds in zip(self.step, base, strict=True):
            member.share = seconds / sum(base) if sum(base) > 0 else 1.0 / len(base)
            member.predicted = seconds + compile_s * member.share
        # Generous: the master's own deadline (estimate x 3 + 30 s) decides when it gives up.
        timeout = min(self.max_render_s, 120.0 + 10.0 * sum(base))
        return [StartRender(work.ticket, work.award, ready.scene, params, timeout, more)]

    def _params_for(self, work: Work, take: bool) -> Params:
        """What it bid on (a job's units and their features never change); planned afresh if forgotten or
        never bid on, and always with the job's own rules (in the bundle) when it has some. `take`: forget
        the remembered plan (the unit renders now)."""
        key, job = work.key, work.award.job
        remembered = self.planned.pop(key, None) if take else self.planned.get(key)
        if remembered is not None and not job.rules_sha256:
            return remembered
        return self.plan(job, (work.award.unit,))[0]

    def _batch_with(self, first: Work, now: float) -> tuple[Batched, ...]:
        """Waiting units of `first`'s job and depth that render in its call, oldest first, up to `batch`
        (half the slots) in all: not at level off (plain Mitsuba's render, one call a unit), nor in a two-pass
        (adaptive) job, nor on the job's first call here (`_first_call`). A unit that cannot be
        planned stays queued (and fails when its turn comes)."""
        job = first.award.job
        if not self.batches(job) or self._first_call(job):
            return ()
        more: list[Batched] = []
        for work in list(self.queue):
            if len(self.step) >= self.batch:
                break
            if work.cancelled or work.award.job.job_id != job.job_id:
                continue
            try:
                params = self._params_for(work, take=False)
            except Exception:
                continue
            if params.depth != first.params.depth:
                continue
            self.planned.pop(work.key, None)
            self.queue.remove(work)
            self._move(work, "rendering")
            work.params, work.started = params, now
            self.step.append(work)
            more.append(Batched(work.ticket, work.award, params))
        return tuple(more)

    def _first_call(self, job: m.JobInfo) -> bool:
        """Whether this is the job's first render call here: its first unit renders alone, so that its tile
        reaches the page after one unit's samples (one pass's, in passes), not a batch's."""
        return job.job_id not in self.jobs_rendered

    def _rendered(self, job_id: str) -> None:
        self.jobs_rendered.pop(job_id, None)
        self.jobs_rendered[job_id] = None
        while len(self.jobs_rendered) > JOBS_KEPT:  # the oldest first (dicts keep insertion order)
            self.jobs_rendered.pop(next(iter(self.jobs_rendered)))

    def batches(self, job: m.JobInfo) -> bool:
        """Whether the job's units render in batches here (`batched`, and a batch above 1): the render step
        then renders them on the whole film (core.render.batch), else each on its window."""
        return self.batch > 1 and batched(job.level, job.first_spp, job.passes, job.spill)

    def _kernel(self, job: m.JobInfo, unit: WorkUnit, params: Params) -> tuple[Any, ...]:
        """What the render process compiles for the unit: a batch's kernel is the whole film's (one per
        depth, core.render.batch.bounds; an image above BATCH_PIXELS or a scene the batches cannot
        render compiles per window, which this does not foresee), a unit's own its window's (`kernel_key`)."""
        if self.batches(job):
            return job.scene_hash, "film", job.width, job.height, params.depth, job.integrator
        return kernel_key(job, unit, params)

    def _on_render_failed(self, failed: BundleFailed | RenderFailed, now: float) -> list[Instruction]:
        work = self._in_step(failed.ticket)
        if work is None:
            return [Log(logging.DEBUG, f"failure of ticket {failed.ticket}: no such render")]
        self.step.remove(work)
        out: list[Instruction] = [DiscardTile(*work.key), *self._fail(work, failed.reason)]
        self._forget(work)
        return out + self._start_next(now)

    def _on_rendered(self, rendered: RenderFinished, now: float) -> list[Instruction]:
        """Upload the tile (the unit stays held until the upload ends; the next step renders meanwhile), or
        discard it if the unit was cancelled during its render."""
        work = self._in_step(rendered.ticket)
        if work is None:
            return [Log(logging.DEBUG, f"render of ticket {rendered.ticket}: no such render")]
        if not work.cancelled:
            self._move(work, "uploading")
        self.step.remove(work)
        key = work.key
        if work.params is not None:  # its kernel is compiled now, whatever becomes of its tile
            self.kernels.add(self._kernel(work.award.job, work.award.unit, work.params))
        if work.cancelled:
            out: list[Instruction] = [Log(logging.INFO, f"{_unit(key)}: rendered after its cancellation, "
                                                        "discarded"), DiscardTile(*key)]
        else:
            work.rendered, work.uploaded_as = rendered, work.award
            self.delivering[work.ticket] = work
            out = [Upload(work.ticket, work.award, rendered.path)]
        return out + self._start_next(now)

    def _on_uploaded(self, result: UploadDone | UploadFailed, now: float) -> list[Instruction]:
        work = self.delivering.pop(result.ticket, None)
        if work is None:
            return [Log(logging.DEBUG, f"upload of ticket {result.ticket}: no such upload")]
        out: list[Instruction] = [DiscardTile(*work.key)]
        if isinstance(result, UploadFailed):
            out += self._fail(work, result.reason)
        elif not work.cancelled:
            out += self._done(work, now)
        self._forget(work)
        return out

    def _done(self, work: Work, now: float) -> list[Instruction]:
        """Learn from the unit (time taken) and remember its award. Nothing is sent: the master counts a
        unit done by its tile's upload alone (the tile's header holds what an inform would say)."""
        award, rendered, params, predicted = work.uploaded_as, work.rendered, work.params, work.predicted
        assert award is not None and rendered is not None and params is not None and predicted is not None
        self._move(work, "done")
        key, wall = work.key, (now - work.started) * work.share
        self.units_done += 1
        _remember(self.finished, (*key, award.token), None)
        self.calibration.learn(key[0], predicted, wall)
        spp = params.spp if rendered.spp is None else rendered.spp
        return [Log(logging.INFO, f"{_unit(key)}: done in {wall:.3f} s (render {rendered.seconds:.3f} s, spp {spp}, "
                                  f"depth {params.depth}, band {params.band}; award estimate "
                                  f"{award.estimate_s:.3f} s)")]

    def _fail(self, work: Work, reason: str) -> list[Instruction]:
        """Failure under the latest award, unless the master cancelled the unit."""
        if work.cancelled:
            return []
        self._move(work, "failed")
        self.units_failed += 1
        award, key = work.award, work.key
        return [Log(logging.WARNING, f"{_unit(key)}: failed: {reason}"),
                SendToMaster(m.Failure(conversation=award.conversation, job_id=key[0], index=key[1],
                                       token=award.token, reason=reason[:MAX_REASON] or "failed"))]

    def _in_step(self, ticket: int) -> Work | None:
        return next((w for w in self.step if w.ticket == ticket), None)

    def _forget(self, work: Work) -> None:
        if self.works.get(work.key) is work:
            del self.works[work.key]


# ---- pure helpers ------------------------------------------------------------------------------------


def kernel_key(job: m.JobInfo, unit: WorkUnit, params: Params) -> tuple[Any, ...]:
    """What Dr.Jit compiles a kernel for: the scene, the window's size, the depth and the integrator."""
    window = unit.rect.window(params.band, job.width, job.height)
    return job.scene_hash, window.w, window.h, params.depth, job.integrator


def describe(exc: BaseException) -> str:
    """An error as a Failure's reason: a QuekaroError's own words, else its type and message."""
    text = str(exc) if isinstance(exc, QuekaroError) else f"{type(exc).__name__}: {exc}"
    return text or type(exc).__name__


def _unit(key: Key) -> str:
    return f"unit {key[1]} of job {key[0]}"


def _expect(holds: bool, work: Work, what: str) -> None:
    if not holds:
        raise AssertionError(f"{work}: {what}")


def _remember(memory: dict[Any, Any], key: Any, value: Any) -> None:
    """Store in a bounded memory, forgetting the oldest entries beyond FINISHED_MEMORY."""
    memory.pop(key, None)
    memory[key] = value
    while len(memory) > FINISHED_MEMORY:
        memory.pop(next(iter(memory)))
