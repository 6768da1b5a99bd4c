"""The master's auction: a pure state machine (`machine.Auction`) with one entry, `handle(stimulus, now)`.

Stimuli in (`stimuli`), instructions out (`instructions`), frozen views for readers (`views`), the
look-ahead schedule (`schedule`) and its records (`state`). Outside this package only the names below
are used: tests/test_layers.py fails on any other read of the auction.
"""

from master.auction.instructions import (
    AgentBack,
    AgentBlocklisted,
    AgentForgotten,
    AgentJoined,
    AgentLost,
    AgentSilent,
    BidRefused,
    Instruction,
    JobCancelled,
    JobDone,
    JobFailed,
    JobsPaused,
    JobsResumed,
    MessageIgnored,
    PassesOrdered,
    PassesSettled,
    Record,
    RefuseTile,
    SendToAgent,
    UnitAwarded,
    UnitDone,
    UnitFailed,
    UnitRequeued,
)
from master.auction.machine import Auction
from master.auction.passes import ResumedPasses, pass_origin
from master.auction.schedule import Placement, PlanAgent, ProjectedUnit, fluid_finish, project, refine
from master.auction.state import Config, Transition
from master.auction.stimuli import (
    DiskFreed,
    DiskFull,
    JobCancelRequested,
    JobSubmitted,
    MessageReceived,
    PassMerged,
    Stimulus,
    Tick,
    TileStored,
)
from master.auction.views import AgentView, AwardView, JobView

__all__ = [
    "AgentBack",
    "AgentBlocklisted",
    "AgentForgotten",
    "AgentJoined",
    "AgentLost",
    "AgentSilent",
    "AgentView",
    "Auction",
    "AwardView",
    "BidRefused",
    "Config",
    "DiskFreed",
    "DiskFull",
    "Instruction",
    "JobCancelRequested",
    "JobCancelled",
    "JobDone",
    "JobFailed",
    "JobSubmitted",
    "JobView",
    "JobsPaused",
    "JobsResumed",
    "MessageIgnored",
    "MessageReceived",
    "PassMerged",
    "PassesOrdered",
    "PassesSettled",
    "Placement",
    "PlanAgent",
    "ProjectedUnit",
    "Record",
    "RefuseTile",
    "ResumedPasses",
    "SendToAgent",
    "Stimulus",
    "Tick",
    "TileStored",
    "Transition",
    "UnitAwarded",
    "UnitDone",
    "UnitFailed",
    "UnitRequeued",
    "fluid_finish",
    "pass_origin",
    "project",
    "refine",
]
