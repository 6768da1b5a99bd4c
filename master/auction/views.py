"""What the auction lets the rest of the master read: frozen views, never its live records."""

from __future__ import annotations

from dataclasses import dataclass

from core.model.geometry import Rect


@dataclass(frozen=True)
class AwardView:
    """A unit's current award: who holds it, under which conversation, and what its tile must cover."""

    job_id: str
    index: int
    agent: str
    conversation: str
    rect: Rect  # the unit's rectangle, band excluded
    image: tuple[int, int]  # the job's image (width, height)


@dataclass(frozen=True)
class AgentView:
    """An agent as the master knows it. `heard_s_ago`: seconds since its last message, in auction time."""

    name: str
    lost: bool
    credits: int
    speed: float
    holding: tuple[str, ...]  # "job/unit" of the units it holds, sorted
    heard_s_ago: float
    blocklisted_for: tuple[str, ...]  # running jobs that no longer offer it units
    threads: int | None = None  # its render threads, as its Register told
    draining: bool = False  # drained by the user: awarded nothing new
    host: str | None = None  # the machine it runs on, as its Register told


@dataclass(frozen=True)
class JobView:
    job_id: str
    status: str
    error: str
    counts: dict[str, int]  # units per status
    blocklist: tuple[str, ...]
