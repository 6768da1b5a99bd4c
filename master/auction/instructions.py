"""What the auction tells the master to do: send a message, answer a tile's upload, record a fact.

Records are what the job store applies (`master.store.JobStore.apply`) and the log prints (`sentence()`,
with `fields()` for --log-format json). Every instruction names the stimulus that caused it; tokens stay
out of reprs, sentences and fields.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from typing import Any, ClassVar

from core.model import messages as m
from core.model.units import WorkUnit


@dataclass(frozen=True)
class Instruction:
    """One thing for the master's I/O to do; `stimulus_id` names the stimulus it answers."""

    stimulus_id: str = field(default="", kw_only=True, compare=False)


@dataclass(frozen=True)
class SendToAgent(Instruction):
    """Deliver `message` to agent `to` (a JID)."""

    to: str
    message: m.Message


@dataclass(frozen=True)
class RefuseTile(Instruction):
    """Answer the tile's upload with this refusal (the tile is removed): it claims what its award forbids."""

    job_id: str
    index: int
    reason: str


@dataclass(frozen=True)
class Record(Instruction):
    """A fact for the job store and the log: one subclass per kind, with typed fields."""

    level: ClassVar[int] = logging.INFO
    template: ClassVar[str] = ""  # the sentence, with the record's fields by name

    def sentence(self) -> str:
        return self.template.format(**{f.name: getattr(self, f.name) for f in dataclasses.fields(self)})

    def fields(self) -> dict[str, Any]:
        """The record's fields for a structured log, its kind first, tokens left out."""
        out = {"record": type(self).__name__}
        out.update({f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.repr})
        return out


@dataclass(frozen=True)
class UnitRecord(Record):
    """A record of one unit's award; a progressive job's unit rows are passes, which `origin` names as the
    user knows them, (unit, pass): its sentence says "unit 2, pass 3", not the row's index."""

    origin: tuple[int, int] | None = field(default=None, kw_only=True)

    def sentence(self) -> str:
        values = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        if self.origin is not None:
            values["index"] = "{}, pass {}".format(*self.origin)
        return self.template.format(**values)


@dataclass(frozen=True)
class UnitAwarded(UnitRecord):
    template: ClassVar[str] = "unit {index} of job {job_id}: awarded to {agent}, estimate {estimate:.2f} s " \
                              "(try {attempt})"
    job_id: str
    index: int
    agent: str
    token: str = field(repr=False)
    estimate: float  # seconds, the winning bid
    attempt: int  # 1 for the unit's first award
    deadline: float  # render deadline, auction time


@dataclass(frozen=True)
class UnitDone(UnitRecord):
    """The unit's tile is durable and its award's holder is done: the tile, the parameters it was rendered
    with (as the store keeps them), and the agent's record."""

    template: ClassVar[str] = ("unit {index} of job {job_id}: done by {agent} in {seconds:.2f} s (estimate "
                               "{estimate:.2f} s; spp {report[spp]}, depth {report[depth]}, band {report[band]})")
    job_id: str
    index: int
    agent: str
    token: str = field(repr=False)
    seconds: float
    estimate: float
    tile_path: str
    tile_hash: str
    report: dict[str, Any]  # the tile's header as the store records it (TileReport.stored)
    credits: int  # the agent's credits after this unit
    on_time: bool  # within `Config.credit_tolerance` of its estimate

    @property
    def params(self) -> dict[str, int]:
        """The render parameters the agent chose, as the store records them with the attempt."""
        return {k: self.report[k] for k in ("depth", "spp", "band", "nonfinite")}


@dataclass(frozen=True)
class UnitFailed(UnitRecord):
    """The unit failed on its agent (its report, or its render deadline passed): back to pending."""

    template: ClassVar[str] = "unit {index} of job {job_id}: {reason}; back to the auction"
    level: ClassVar[int] = logging.WARNING
    job_id: str
    index: int
    agent: str
    token: str = field(repr=False)
    reason: str
    credits: int  # the agent's credits after this failure


@dataclass(frozen=True)
class UnitRequeued(UnitRecord):
    """The unit went back to pending without blaming its agent (lost, or the award never arrived)."""

    template: ClassVar[str] = "unit {index} of job {job_id}: back to the auction ({reason})"
    level: ClassVar[int] = logging.WARNING
    job_id: str
    index: int
    agent: str
    token: str = field(repr=False)
    reason: str


@dataclass(frozen=True)
class UnitRetried(Record):
    """A done unit goes back to the auction at the user's request: its tile is dropped, its job runs again."""

    template: ClassVar[str] = "unit {index} of job {job_id}: to be rendered again ({reason})"
    job_id: str
    index: int
    reason: str


@dataclass(frozen=True)
class JobRequeued(Record):
    """A failed or cancelled job runs again at the user's request: its `units` not done go back to pending
    (the done ones keep their tiles); its error and end are cleared, and its failures before are forgiven."""

    template: ClassVar[str] = "job {job_id}: runs again, {count} units back to the auction ({reason})"
    job_id: str
    units: tuple[int, ...] = field(repr=False)
    count: int
    reason: str


@dataclass(frozen=True)
class PassesOrdered(Record):
    """A progressive job's next passes, each a work unit of its own (master.auction.passes): the store
    keeps them as the job's units."""

    template: ClassVar[str] = "job {job_id}: {count} passes ordered ({why})"
    level: ClassVar[int] = logging.DEBUG
    job_id: str
    units: tuple[WorkUnit, ...] = field(repr=False)
    count: int
    why: str  # "a round" or "extra passes for idle agents"


@dataclass(frozen=True)
class PassesSettled(Record):
    """A progressive job reached its goal (or its cap, or its time): why, and each unit's verdict; the
    passes still out are withdrawn and the job is done."""

    template: ClassVar[str] = "job {job_id}: progressive passes end: {reason}"
    job_id: str
    reason: str
    verdicts: dict[int, str]


@dataclass(frozen=True)
class PassesWithdrawn(Record):
    """Passes of a progressive job called off before they land: their unit has what its round asks
    (planning.progressive.Withdraw). The store fails them and cancels their attempts."""

    template: ClassVar[str] = "job {job_id}: {count} passes withdrawn ({reason})"
    level: ClassVar[int] = logging.DEBUG
    job_id: str
    units: tuple[int, ...] = field(repr=False)
    count: int
    reason: str


@dataclass(frozen=True)
class JobDone(Record):
    template: ClassVar[str] = "job {job_id}: every unit done"
    job_id: str


@dataclass(frozen=True)
class JobFailed(Record):
    template: ClassVar[str] = "job {job_id}: failed: {reason}"
    level: ClassVar[int] = logging.ERROR
    job_id: str
    reason: str


@dataclass(frozen=True)
class JobCancelled(Record):
    template: ClassVar[str] = "job {job_id}: cancelled ({reason})"
    job_id: str
    reason: str


@dataclass(frozen=True)
class AgentJoined(Record):
    """An agent the master did not know registered (or was first heard from by heartbeat)."""

    template: ClassVar[str] = "agent {agent}: joined, speed {speed:.3g}"
    agent: str
    speed: float


@dataclass(frozen=True)
class AgentLost(Record):
    template: ClassVar[str] = "agent {agent}: lost ({reason})"
    level: ClassVar[int] = logging.WARNING
    agent: str
    reason: str


@dataclass(frozen=True)
class AgentBack(Record):
    template: ClassVar[str] = "agent {agent}: back"
    agent: str


@dataclass(frozen=True)
class AgentSilent(Record):
    """An agent let a call for proposals time out: it is left out of auctions for `seconds`."""

    template: ClassVar[str] = "agent {agent}: did not answer a call for proposals; left out for {seconds:.1f} s"
    level: ClassVar[int] = logging.WARNING
    agent: str
    seconds: float


@dataclass(frozen=True)
class AgentForgotten(Record):
    """An agent lost for `Config.forget_lost_s` is dropped from the agents the master lists."""

    template: ClassVar[str] = "agent {agent}: lost too long, no longer listed"
    agent: str


@dataclass(frozen=True)
class AgentDrained(Record):
    """The user drained the agent: it gets no new award, and finishes what it holds (`holding` units)."""

    template: ClassVar[str] = "agent {agent}: draining ({holding} units left to finish)"
    agent: str
    holding: int


@dataclass(frozen=True)
class AgentResumed(Record):
    template: ClassVar[str] = "agent {agent}: resumed, called to auctions again"
    agent: str


@dataclass(frozen=True)
class AgentBlocklisted(Record):
    template: ClassVar[str] = "agent {agent}: blocklisted for job {job_id} ({reason})"
    level: ClassVar[int] = logging.WARNING
    job_id: str
    agent: str
    reason: str


@dataclass(frozen=True)
class BidRefused(Record):
    """An agent answered a call for proposals with a refusal."""

    template: ClassVar[str] = "agent {agent}: will not bid on job {job_id}: {reason}"
    job_id: str
    agent: str
    reason: str


@dataclass(frozen=True)
class MessageIgnored(Record):
    """A message, tile or request that changes nothing (late, forged, duplicate, out of its auction)."""

    agent: str | None
    reason: str
    job_id: str | None = None
    index: int | None = None

    def sentence(self) -> str:
        about = f"unit {self.index} of job {self.job_id}" if self.index is not None else \
            f"job {self.job_id}" if self.job_id else None
        who = f"from {self.agent}" if self.agent else "from the user"
        return f"ignored {who}" + (f" about {about}" if about else "") + f": {self.reason}"


@dataclass(frozen=True)
class JobsPaused(Record):
    """Every job stands still (no awards, deadlines or losses) until `JobsResumed`."""

    template: ClassVar[str] = "every job paused: {reason} ({free_bytes} bytes free)"
    level: ClassVar[int] = logging.ERROR
    reason: str
    free_bytes: int


@dataclass(frozen=True)
class JobsResumed(Record):
    template: ClassVar[str] = "jobs resume: {reason} ({free_bytes} bytes free)"
    level: ClassVar[int] = logging.WARNING
    reason: str
    free_bytes: int
