"""A progressive job in the auction: its units' passes are auctioned as units of their own.

Pass `k` of unit `u` (of a job of `n` units) is the work unit of index k n + u: the unit's rectangle and
features at the pass's spp, seeded by that index, so that the contract net, the store and the agents
handle a pass as any unit. `PassBook` is what the auction keeps of the job: the decisions
(planning.progressive.Progressive), the units the passes copy, and when its first pass was awarded.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from core.model.units import WorkUnit
from planning.progressive import BUDGET, Goal, PassOrder, Progressive, UnitSoFar


@dataclass(frozen=True)
class ResumedPasses:
    """A progressive job taken up again after a master restart: its units (`templates`, the plan's), what
    each had of its passes (planning.progressive.UnitSoFar), and the seconds its passes had run."""

    templates: tuple[WorkUnit, ...]
    so_far: tuple[UnitSoFar, ...]
    elapsed: float


@dataclass
class PassBook:
    machine: Progressive
    units: tuple[WorkUnit, ...]
    # When its first pass was awarded (None: not yet): a time goal's seconds count from there, not from the
    # submission, so that a job queued behind others (a sequence's later frames) gets its time.
    started: float | None

    @classmethod
    def open(cls, goal: Goal, units: tuple[WorkUnit, ...], started: float | None,
             pass_samples: int = 1) -> PassBook:
        """The job's book (`started`: None for a new job, when a resumed one's passes began); a budget job's
        passes hold at least `pass_samples` samples each where their unit has them
        (planning.progressive.budget_passes)."""
        if [u.index for u in units] != list(range(len(units))):
            raise ValueError("a progressive job's units are indexed 0 .. n - 1")
        # A budget job's units render their own samples where the plan's rules pinned them (a rule level).
        budgets = [u.spp for u in units] if goal.kind == BUDGET and None not in {u.spp for u in units} else None
        return cls(Progressive(goal, [u.rect.area for u in units], budgets, pass_samples=pass_samples), units,
                   started)

    def pass_unit(self, order: PassOrder) -> WorkUnit:
        """The work unit that renders `order`: its unit's, at the pass's spp (and the unit's pinned depth)."""
        return dataclasses.replace(self.units[order.unit], index=self.pass_index(order),
                                   spp=order.spp)

    def pass_index(self, order: PassOrder) -> int:
        """The work unit index that renders `order` (`pass_unit`'s)."""
        return order.pass_index * len(self.units) + order.unit

    @property
    def merges(self) -> bool:
        """Whether decisions need each pass merged (its noise): not a budget job's, which counts passes."""
        return self.machine.goal.kind != BUDGET

    def origin(self, index: int) -> tuple[int, int]:
        """(unit, pass) of a pass's work unit index."""
        return pass_origin(index, len(self.units))


def pass_origin(index: int, units: int) -> tuple[int, int]:
    """(unit, pass) of the work unit `index` of a progressive job of `units` units."""
    pass_index, unit = divmod(index, units)
    return unit, pass_index
