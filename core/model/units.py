"""Work units: the rectangles the master auctions, with the features the fuzzy rules read (C, S, Nd)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from core.errors import MessageError
from core.model.fields import constrained
from core.model.geometry import Rect

# Units an agent holds at once (rendering, waiting, uploading), master and agent alike: its next batch is
# awarded while one renders. 2 is one unit a call, as before units were batched on agents.
SLOTS = 8

SPP_MAX = 1 << 20  # most samples per pixel a job asks for and a unit renders (the job's and messages' limit)


def batched(level: str, first_spp: int | None, passes: bool = False, spill: bool = False) -> bool:
    """Whether a job's units render in batches on an agent: at a rule level, not as two-pass (adaptive)
    units; a progressive job's passes at any level, unless they spill (one film would mix their spills).
    Level off is otherwise plain Mitsuba's render call, one a unit."""
    return first_spp is None and not spill and (passes or level != "off")


def batch_size(slots: int) -> int:
    """Units an agent renders in one call, and wins in one auction round: half its slots, so that the next
    batch is awarded while one renders (2 slots: one unit a call)."""
    return max(1, slots // 2)


class UnitError(MessageError):
    """A unit description (e.g. from a message or a job file) that is malformed."""


@dataclass(frozen=True, kw_only=True)
class WorkUnit:
    """One work unit: its rectangle and the features the fuzzy engine and the auction use. The same
    object is planned, stored, announced in calls for proposals and rendered.

    `C` is the unit's complexity (mean per-sample noise of its pixels), `S` its size in pixels
    (its area), `Nd` the largest absolute difference between its C and a neighbour's C, `cost` its
    estimated relative render time (sum of per-pixel time per sample), `neighbours` the indices of
    the units that share a border of positive length with it. `spp` is the mean samples per pixel the
    plan gives the unit (an adaptive job's share of the level's samples: planning.budgets), None where
    the agent's rules choose. `depth_floor` is the shallowest depth the rules may cut the unit to without
    losing a measurable share of its light, as far as it was worth measuring (planning.depthcut: never
    below the true one), or the user's depth where no unit may be cut (a participating medium; a farm
    job whose rules cut none: planning.jobplan.Floors.HELD), None where depth is not cut (level off,
    adaptive jobs, unbounded depth, a job in one process whose rules cut none). `depth` is the depth every
    pass of the unit renders at in a progressive job at a rule level (the plan's rules chose it once, so that
    all its passes estimate one image), None where the job's depth or the agent's rules set it.
    """

    index: int = constrained(lo=0, hi=10**7)
    rect: Rect
    C: float = constrained(lo=0.0, hi=1e12)
    S: int = constrained(lo=0, hi=1 << 32)
    Nd: float = constrained(lo=0.0, hi=1e12)
    cost: float = constrained(lo=0.0, hi=1e12)  # seconds on a reference agent of speed 1
    # The partition's adjacency: the planner's business, not the agents' (so never on the wire).
    neighbours: tuple[int, ...] = constrained(wire=False, default=())
    spp: int | None = constrained(lo=1, hi=SPP_MAX, default=None)
    depth_floor: int | None = constrained(lo=1, hi=1 << 16, default=None)
    depth: int | None = constrained(lo=-1, hi=1024, default=None)

    def __post_init__(self) -> None:
        area = self.rect.area
        if type(self.S) is not int or area != self.S:
            raise UnitError(f"unit {self.index}: S={self.S} differs from its rectangle's area {area}")
        for name in ("C", "Nd", "cost"):
            value = getattr(self, name)
            if not math.isfinite(value) or value < 0:
                raise UnitError(f"unit {self.index}: field {name!r} must be finite and >= 0, got {value!r}")

    @property
    def work(self) -> float:
        """The unit's render time relative to its job's other units, as the master can know it: its cost
        times its planned spp where the plan sets one (cost is at 1 spp; shares differ up to several fold),
        else its cost (every unit's spp is then its agent's rules' choice)."""
        return self.cost * self.spp if self.spp is not None else self.cost

    def to_dict(self) -> dict[str, Any]:
        return {
            "index": self.index,
            "rect": self.rect.as_list(),
            "C": self.C,
            "S": self.S,
            "Nd": self.Nd,
            "cost": self.cost,
            "neighbours": list(self.neighbours),
            **({"spp": self.spp} if self.spp is not None else {}),
            **({"depth_floor": self.depth_floor} if self.depth_floor is not None else {}),
            **({"depth": self.depth} if self.depth is not None else {}),
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> WorkUnit:
        """Rebuild a unit from `to_dict`'s output; a missing or malformed field raises UnitError naming it."""
        if not isinstance(data, dict):
            raise UnitError(f"unit must be a JSON object, got {type(data).__name__}")
        try:
            return cls(
                index=int(_field(data, "index")),
                rect=Rect.from_list(_field(data, "rect")),
                C=float(_field(data, "C")),
                S=int(_field(data, "S")),
                Nd=float(_field(data, "Nd")),
                cost=float(_field(data, "cost")),
                neighbours=tuple(int(n) for n in data.get("neighbours", ())),
                spp=None if data.get("spp") is None else int(data["spp"]),
                depth_floor=None if data.get("depth_floor") is None else int(data["depth_floor"]),
                depth=None if data.get("depth") is None else int(data["depth"]),
            )
        except UnitError:
            raise
        except (TypeError, ValueError) as exc:
            raise UnitError(f"malformed unit {data!r}: {exc}") from exc


def _field(data: dict[str, Any], name: str) -> Any:
    if name not in data:
        raise UnitError(f"unit is missing field {name!r}")
    return data[name]
