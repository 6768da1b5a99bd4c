"""What the auction is told: a job submitted, cancelled or requeued, a message or a tile from an agent, the disk,
the clock, and what the user asks of units and agents from the page (retry a done unit, drain or resume an agent).

Each stimulus carries a `stimulus_id` (the master names it from its source: a message's conversation, a
tile's unit; the auction numbers one left empty), which every instruction it causes and every unit change
it makes repeat (`Auction.story`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from core.model import messages as m
from core.model.units import WorkUnit
from master.auction.passes import ResumedPasses
from master.auction.state import ResumedJob
from planning.progressive import Goal


@dataclass(frozen=True)
class Stimulus:
    stimulus_id: str = field(default="", kw_only=True, compare=False)


@dataclass(frozen=True)
class JobSubmitted(Stimulus):
    """Auction a job's units. `channels`: what every tile of it must carry (None: not checked). A job the
    master resumes after a restart passes its units already `done` (`delivered_by`: whose tile made each one
    done) and its past `failures` as (unit index, agent, reason), so that retries and blocklists survive."""

    info: m.JobInfo
    units: Sequence[WorkUnit]
    channels: tuple[str, ...] | None = None
    done: frozenset[int] = frozenset()
    failures: tuple[tuple[int, str, str], ...] = ()
    delivered_by: Mapping[int, str] = field(default_factory=dict)
    goal: Goal | None = None  # a progressive job's: its units are templates, its passes are auctioned
    resumed: ResumedPasses | None = None  # a progressive job after a restart: its units are its passes

    @classmethod
    def taken_up(cls, info: m.JobInfo, job: ResumedJob, stimulus_id: str) -> JobSubmitted:
        """A job the store holds, as the auction takes it up (after a restart, or to requeue it)."""
        return cls(info, job.units, None if job.channels is None else tuple(job.channels), frozenset(job.done),
                   tuple(job.failures), dict(job.delivered_by), job.goal, job.resumed, stimulus_id=stimulus_id)


@dataclass(frozen=True)
class PassMerged(Stimulus):
    """The master merged pass `index` (a pass's work unit: master.auction.passes) of a progressive job into
    its unit: the unit's samples per pixel, seconds of render and estimated relMSE now, all passes merged."""

    job_id: str
    index: int
    spp: int
    seconds: float
    relmse: float | None


@dataclass(frozen=True)
class JobCancelRequested(Stimulus):
    job_id: str
    reason: str = "cancelled by the user"


@dataclass(frozen=True)
class JobRequeueRequested(Stimulus):
    """The user asks a failed or cancelled job to run again: its done units stay done, the others go back to
    the auction. `taken_up`: the job as the store holds it, for a job the auction does not know (it ended
    before this master started); its past failures are not held against its units."""

    job_id: str
    taken_up: JobSubmitted | None = None


@dataclass(frozen=True)
class UnitRetryRequested(Stimulus):
    """The user asks for a done unit to be rendered again: it goes back to the auction (its job runs again)."""

    job_id: str
    index: int


@dataclass(frozen=True)
class AgentDrainRequested(Stimulus):
    """The user drains an agent: it is awarded nothing new and finishes the units it holds."""

    agent: str


@dataclass(frozen=True)
class AgentResumeRequested(Stimulus):
    """The user resumes a drained agent: it is called to auctions again."""

    agent: str


@dataclass(frozen=True)
class MessageReceived(Stimulus):
    """A parsed message from `sender`, a JID the transport has authenticated and the master admits."""

    sender: str
    message: m.Message


@dataclass(frozen=True)
class TileStored(Stimulus):
    """A tile is on the master's disk (fsynced), uploaded with `token`; `figures` and `channels` are what its
    header says, `extra` the rest of the header the report keeps (outputs, rules, emulated)."""

    job_id: str
    index: int
    token: str = field(repr=False)
    tile_path: str
    sha256: str
    figures: m.TileFigures
    channels: tuple[str, ...]
    extra: Mapping[str, Any] = field(default_factory=dict)

    def stored(self, agent: str) -> dict[str, Any]:
        """The tile's parameters as the job store records them, credited to the award's `agent`."""
        f = self.figures
        out: dict[str, Any] = {"depth": f.depth, "spp": f.spp, "band": f.band, "seconds": f.seconds,
                               "nonfinite": f.nonfinite, "outputs": dict(self.extra.get("outputs") or {}),
                               "agent": agent, "rules": self.extra.get("rules")}
        if self.extra.get("emulated"):
            out["emulated"] = True
        if f.first_spp is not None:
            out["first_spp"] = f.first_spp
        return out


@dataclass(frozen=True)
class DiskFull(Stimulus):
    """The master's home has less free space than it needs: every job stands still until `DiskFreed`."""

    free_bytes: int


@dataclass(frozen=True)
class DiskFreed(Stimulus):
    free_bytes: int


@dataclass(frozen=True)
class Tick(Stimulus):
    """Time passes: timeouts, then auctions to resolve, then new calls for proposals."""
