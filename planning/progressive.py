"""Progressive rendering's decisions: which units get another pass, at how many samples, and when a job
stops. A pure state machine (`Progressive.handle`: a typed stimulus in, typed instructions out, no I/O);
the one-process pipeline drives it, and the farm's auction will.

A `budget` job renders each unit's own samples (the user's spp, or the rules' at a rule level) in passes
(`budget_passes`: a small first one, so that the whole image shows early, then halving ones, the last
small, so that the job's end waits on little), and ends when every unit has them. Otherwise every unit
first renders FIRST_PASSES passes of `first_spp`, so that its noise can be estimated between them
(core.image.passes). Then, by the goal:
- `noise` TAU: each unit whose estimated relative error sqrt(relMSE) is above TAU gets the samples its
  estimate says it lacks, at most doubling its count, never past the spp cap; the job stops when every
  unit is under TAU or at the cap.
- `time` SECONDS: rounds of growing length (each at most the time spent so far, times the workers) place
  samples where the image's relMSE falls most per second: each unit's total n_u in proportion to
  sqrt(a_u v_u / k_u) (area, per-sample relative variance, seconds per spp; never below what it has),
  until the time is spent or every unit is at the cap.
A round is over when every unit has merged the samples it asked of it, from whichever passes: idle workers
take extra passes of the units it still waits for (`Idle`), so one slow pass does not hold the job. When a
unit's landed passes (`PassLanded`, a tile stored before its merge) hold what the round asks of it, its
passes still out are withdrawn (`Withdraw`): a unit never gets more samples than it was asked, so the spp
cap holds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

from core.model.job import RenderOptions
from core.wording import count

FIRST_PASSES = 4  # passes before a unit's noise is first estimated
# A budget job's passes per unit: a first of 1/FIRST_PART of it, then halves of the rest, the last two equal
# (1024 spp: 32, 496, 248, 124, 124). Simulated on bench hosts' job (8-64 agents of mixed speeds), halving
# passes came within 1-2 % of the bound the units' bands set, where 4 or 8 equal passes stayed 3-5 % below
# it; the small first pass cost nothing there (0.992 / 0.985 / 0.976 at 8 / 32 / 64 agents against
# 0.989 / 0.976 / 0.965 halving from the start; issue 61's notes) and shows the whole image at ~1/32 of
# the job, not half of it.
BUDGET_PASSES = 5
FIRST_PART = 32
# In one process there is no agents' tail to shorten, and each pass is a render call of its own: a budget
# there renders in the fewest passes between which its noise is estimated, the first small (Ctrl-C keeps
# the image from then on).
ONE_PROCESS_PASSES = 2
FIRST_SHARE = 64  # the first passes render spp_cap / FIRST_SHARE samples each, at least 1 and at most
FIRST_SPP_MAX = 8  # FIRST_SPP_MAX: a time goal's first round must not outlast its time
ROUND_MIN_S = 0.5  # the first time-goal round's length, at least
NOISE, TIME, BUDGET = "noise", "time", "budget"


@dataclass(frozen=True)
class Goal:
    """What a progressive job renders to: `kind` NOISE (relative error `noise` per unit), TIME (`seconds` of
    rendering) or BUDGET (each unit's own samples), never past `spp_cap` samples per pixel in any unit."""

    kind: str
    spp_cap: int
    noise: float | None = None
    seconds: float | None = None

    def __post_init__(self) -> None:
        if self.kind == NOISE and not (self.noise is not None and 0 < self.noise < math.inf):
            raise ValueError(f"a noise goal needs a positive relative error, not {self.noise!r}")
        if self.kind == TIME and not (self.seconds is not None and 0 < self.seconds < math.inf):
            raise ValueError(f"a time goal needs a positive number of seconds, not {self.seconds!r}")
        if self.kind not in (NOISE, TIME, BUDGET) or self.spp_cap < 1:
            raise ValueError(f"goal {self.kind!r} with spp cap {self.spp_cap}")

    @classmethod
    def of(cls, options: RenderOptions, spp_cap: int) -> Goal:
        """A progressive job's goal from its options (`--noise` or `--time`), its spp the cap."""
        kind = NOISE if options.noise is not None else TIME if options.time is not None else BUDGET
        return cls(kind, spp_cap, options.noise, options.time)

    def to_dict(self) -> dict[str, Any]:
        """The goal as a job's report gives it."""
        return {"goal": self.kind, "noise": self.noise, "time": self.seconds, "spp_cap": self.spp_cap}

    @property
    def first_spp(self) -> int:
        return min(max(1, self.spp_cap // FIRST_SHARE), FIRST_SPP_MAX)


def report_part(report: dict[str, Any]) -> dict[str, Any] | None:
    """A job report's progressive part (`render_calls.progressive`), None for a job not in passes."""
    return (report.get("render_calls") or {}).get("progressive")


def describe(progressive: dict[str, Any]) -> str:
    """A report's progressive part (`render_calls.progressive`: the goal, why it stopped, its passes) in one
    line, as `quekaro render` and `quekaro result` print it."""
    kind, cap = progressive["goal"], progressive["spp_cap"]
    goal = ("each unit's own samples" if kind == BUDGET else
            f"relative error {progressive['noise']:g} a unit, at most {cap} spp" if kind == NOISE else
            f"{progressive['time']:g} s of rendering, at most {cap} spp")
    passes = count(progressive["passes"], "pass", "passes")
    return f"passes: {goal}; stopped: {progressive.get('reason') or 'not yet'} ({passes})"


def budget_passes(budget: int, parts: int = BUDGET_PASSES, least: int = 1) -> list[int]:
    """A budget's passes: at most `parts`, none below `least` spp where the budget allows; the first
    1/FIRST_PART of it, the rest halving, the last taking what is left (64: 2, 31, 15, 8, 8; in two parts
    2, 62; at least 8: 8, 28, 14, 14)."""
    if budget <= 0:
        return []
    first = min(budget, max(least, budget // FIRST_PART, 1))
    if parts <= 1 or first >= budget:
        return [budget]
    return [first, *_halving(budget - first, parts - 1, least)]


def _halving(budget: int, parts: int, least: int) -> list[int]:
    """`budget` in halving passes, at most `parts`, none below `least` where it allows, the last taking
    what is left (16: 8, 4, 2, 1, 1)."""
    sizes: list[int] = []
    left = budget
    while left > 0:
        last = len(sizes) == parts - 1 or left // 2 < least
        size = left if last else max(1, left // 2)
        sizes.append(size)
        left -= size
    return sizes


# ---- stimuli ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PassDone:
    """Pass `pass_index` of `unit` is merged: the unit's samples per pixel, seconds of render and estimated
    relMSE (None while unknown) now, all its merged passes together; `elapsed` seconds since the job's
    first pass was ordered; `workers` render at once (agents on a farm, 1 in one process)."""

    unit: int
    pass_index: int
    spp: int
    seconds: float
    relmse: float | None
    elapsed: float
    workers: int = 1


@dataclass(frozen=True)
class PassLanded:
    """Pass `pass_index` of `unit` is stored, not merged yet: its samples count toward the round now, so
    that a pass still out that the unit no longer needs is withdrawn before it lands too."""

    unit: int
    pass_index: int


@dataclass(frozen=True)
class Stop:
    """The user stopped the job (Ctrl-C) `elapsed` seconds after its first pass was ordered: it ends on the
    passes merged so far, if every unit has one."""

    elapsed: float


@dataclass(frozen=True)
class UnitSoFar:
    """One unit of a job taken up again (a master restart): its merged passes (`passes`, their samples per
    pixel `spp` as rendered and `credited` as ordered, `seconds`, estimated `relmse`), the passes still out
    (pass index -> spp ordered) and the next pass index, never used before (a pass's seed must not repeat)."""

    spp: int = 0
    credited: int = 0
    passes: int = 0
    seconds: float = 0.0
    relmse: float | None = None
    out: dict[int, int] = field(default_factory=dict)
    next_pass: int = 0


@dataclass(frozen=True)
class Idle:
    """`slots` workers are idle and nothing ordered waits for them: extra passes of the units the round
    still waits for (a slow worker's pass is then no longer the job's tail)."""

    slots: int


# ---- instructions -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PassOrder:
    """Render unit `unit`'s pass number `pass_index` at `spp` samples per pixel."""

    unit: int
    pass_index: int
    spp: int


@dataclass(frozen=True)
class RenderRound:
    """Render these passes and report each (PassDone); the next decision comes when every unit has merged
    the samples this round asked of it, from whichever passes."""

    orders: tuple[PassOrder, ...]


@dataclass(frozen=True)
class Withdraw:
    """Cancel these passes, still out: their unit has landed what its round asks of it."""

    orders: tuple[PassOrder, ...]


@dataclass(frozen=True)
class Finish:
    """Stop (cancel the passes still out): the job's image is its units' merged passes. `reason` says why;
    `units` each unit's verdict."""

    reason: str
    units: dict[int, str] = field(default_factory=dict)


# ---- the machine --------------------------------------------------------------------------------------

EXTRA_IN_FLIGHT = 2  # passes of one unit out at once, an idle worker's extra pass included


@dataclass
class UnitNoise:
    """What the machine knows of one unit: merged samples and their noise, the passes out (pass index ->
    spp ordered), and what the round asks of it: `target` spp ordered of passes merged (`credited`; a
    stratified sampler may render a little more or less than it is asked)."""

    area: int
    credited: int = 0
    spp: int = 0
    passes: int = 0
    seconds: float = 0.0
    relmse: float | None = None
    target: int = 0
    out: dict[int, int] = field(default_factory=dict)
    next_pass: int = 0
    landed: dict[int, int] = field(default_factory=dict)

    @property
    def variance(self) -> float:
        """Per-sample relative variance v: relMSE(n) = v / n."""
        return (self.relmse or 0.0) * self.spp

    def order(self, spp: int) -> PassOrder:
        made = PassOrder(0, self.next_pass, spp)
        self.out[self.next_pass] = spp
        self.next_pass += 1
        return made


class Progressive:
    """The decisions of one progressive job over units of the given pixel areas (index: position); a budget
    job's `budgets` are each unit's samples per pixel (None: the goal's spp_cap for every unit), in at most
    `budget_parts` passes of at least `pass_samples` samples each (a unit's pixels x spp) where it has them."""

    def __init__(self, goal: Goal, areas: list[int], budgets: list[int] | None = None,
                 budget_parts: int = BUDGET_PASSES, pass_samples: int = 1) -> None:
        self.goal = goal
        self.budget_parts = budget_parts  # a budget job's passes per unit (`budget_passes`)
        self.units = [UnitNoise(a) for a in areas]
        self.least = [max(1, -(-pass_samples // max(1, a))) for a in areas]  # a budget pass's spp, at least
        self.budgets = list(budgets) if budgets is not None else [goal.spp_cap] * len(areas)
        if len(self.budgets) != len(areas) or min(self.budgets, default=1) < 1:
            raise ValueError(f"budgets {self.budgets[:8]} for {len(areas)} units")
        self.finished: Finish | None = None
        self.workers = 1

    def start(self) -> list[RenderRound | Finish]:
        """The first round: FIRST_PASSES passes of every unit (fewer where the cap comes first); a budget
        job's whole samples."""
        if self.goal.kind == BUDGET:
            return [RenderRound(tuple(self._budget_orders()))]
        firsts = [self._first_passes(index) for index in range(len(self.units))]
        rounds = max(map(len, firsts), default=0)
        return [RenderRound(tuple(each[k] for k in range(rounds) for each in firsts if k < len(each)))]

    def _first_passes(self, index: int) -> list[PassOrder]:
        """A unit's first FIRST_PASSES passes of `first_spp` (fewer where the cap comes first), its target."""
        spp = min(self.goal.first_spp, self.goal.spp_cap)
        passes = max(1, min(FIRST_PASSES, self.goal.spp_cap // spp))
        self.units[index].target = passes * spp
        return [self._order(index, spp) for _ in range(passes)]

    def resume(self, so_far: list[UnitSoFar], elapsed: float) -> list[RenderRound | Finish]:
        """In place of `start` for a job taken up again after `elapsed` seconds, each unit as it was (`so_far`):
        the round waits for the passes still out, and orders what a unit lacks (a budget job's samples, or
        the first passes of a unit with none); a job whose round had ended decides now."""
        if len(so_far) != len(self.units):
            raise ValueError(f"{len(so_far)} units resumed for {len(self.units)}")
        orders: list[PassOrder] = []
        for index, (unit, had) in enumerate(zip(self.units, so_far, strict=True)):
            unit.spp, unit.credited, unit.passes, unit.seconds, unit.relmse = (
                had.spp, had.credited, had.passes, had.seconds, had.relmse)
            unit.out, unit.next_pass = dict(had.out), max(had.next_pass, max(had.out, default=-1) + 1)
            unit.target = unit.credited + sum(unit.out.values())
            if self.goal.kind == BUDGET:
                orders += [self._order(index, spp) for spp in
                           budget_passes(self.budgets[index] - unit.target, self.budget_parts, self.least[index])]
                unit.target = max(unit.target, self.budgets[index])
            elif unit.target == 0:
                orders += self._first_passes(index)
        if orders:
            return [RenderRound(tuple(orders))]
        if any(u.credited < u.target for u in self.units):
            return []
        return self._decide(elapsed)

    def handle(self, stimulus: PassDone | PassLanded | Idle | Stop) -> list[RenderRound | Withdraw | Finish]:
        """The one entry: a stimulus in, the instructions it leads to out. A Stop while a unit has no pass
        merged gives nothing: there is no image to keep."""
        if self.finished is not None:
            return []
        if isinstance(stimulus, Stop):
            return self._stop(stimulus.elapsed)
        if isinstance(stimulus, Idle):
            extra = self._extra(stimulus.slots)
            return [RenderRound(extra)] if extra else []
        if isinstance(stimulus, PassLanded):
            return self._landed(stimulus)
        unit = self.units[stimulus.unit]
        unit.spp, unit.seconds, unit.relmse = stimulus.spp, stimulus.seconds, stimulus.relmse
        unit.passes += 1
        if stimulus.pass_index in unit.landed:
            unit.credited += unit.landed.pop(stimulus.pass_index)
        else:  # merged without a landing reported (one process)
            unit.credited += unit.out.pop(stimulus.pass_index, 0)
        self.workers = max(1, stimulus.workers)
        if any(u.credited < u.target for u in self.units):
            return []
        return self._decide(stimulus.elapsed)

    def _budget_orders(self) -> list[PassOrder]:
        """Each unit's budget in `budget_passes`, pass by pass over the units (a batch holds one pass of a
        unit; the auction awards the largest first)."""
        sizes = [budget_passes(b, self.budget_parts, least) for b, least in zip(self.budgets, self.least, strict=True)]
        orders = [self._order(index, each[k]) for k in range(self.budget_parts) for index, each in enumerate(sizes)
                  if k < len(each)]
        for unit, budget in zip(self.units, self.budgets, strict=True):
            unit.target = budget
        return orders

    def _order(self, index: int, spp: int) -> PassOrder:
        return replace(self.units[index].order(spp), unit=index)

    def _decide(self, elapsed: float) -> list[RenderRound | Finish]:
        wanted = (self._noise_round() if self.goal.kind == NOISE else self._time_round(elapsed)
                  if self.goal.kind == TIME else [])
        if not wanted:
            self.finished = Finish(self._reason(elapsed), self._verdicts())
            return [self.finished]
        orders = []
        for index, spp in wanted:
            unit = self.units[index]
            unit.target = unit.credited + spp
            orders.append(self._order(index, spp))
        return [RenderRound(tuple(orders))]

    def _landed(self, landed: PassLanded) -> list[Withdraw]:
        """A pass stored: once the unit's landed samples hold what the round asks, its passes still out
        (an idle worker's extra pass, or the slow one it doubled) are withdrawn."""
        unit = self.units[landed.unit]
        if landed.pass_index not in unit.out:
            return []
        unit.landed[landed.pass_index] = unit.out.pop(landed.pass_index)
        if not unit.out or unit.credited + sum(unit.landed.values()) < unit.target:
            return []
        spare = tuple(PassOrder(landed.unit, k, spp) for k, spp in sorted(unit.out.items()))
        unit.out.clear()
        return [Withdraw(spare)]

    def _extra(self, slots: int) -> tuple[PassOrder, ...]:
        """Up to `slots` extra passes of the units furthest from what the round asks of them, each the size
        of a pass it has out, at most EXTRA_IN_FLIGHT out per unit."""
        waiting = [i for i, u in enumerate(self.units)
                   if u.credited + sum(u.landed.values()) < u.target and 0 < len(u.out) < EXTRA_IN_FLIGHT]
        short = sorted(waiting, key=lambda i: (self.units[i].credited - self.units[i].target, i))
        return tuple(self._order(i, max(self.units[i].out.values())) for i in short[:max(0, slots)])

    # -- the noise goal --

    def _noise_round(self) -> list[tuple[int, int]]:
        wanted = []
        for index, unit in enumerate(self.units):
            room = self.goal.spp_cap - unit.spp
            if room <= 0 or self._met(unit):
                continue
            lacking = unit.variance / self.goal.noise ** 2 - unit.spp if unit.relmse is not None else unit.spp
            wanted.append((index, min(max(math.ceil(lacking), self.goal.first_spp), unit.spp, room)))
        return wanted

    def _met(self, unit: UnitNoise) -> bool:
        return unit.relmse is not None and math.sqrt(unit.relmse) <= self.goal.noise

    # -- the time goal --

    def _time_round(self, elapsed: float) -> list[tuple[int, int]]:
        left = self.goal.seconds - elapsed
        if left <= 0:
            return []
        budget = min(left, max(elapsed, ROUND_MIN_S)) * self.workers
        wanted = []
        for index, (unit, target) in enumerate(zip(self.units, self._neyman(budget), strict=True)):
            spp = min(int(target) - unit.spp, self.goal.spp_cap - unit.spp)
            if spp >= 1:
                wanted.append((index, spp))
        return wanted

    def _neyman(self, budget: float) -> list[float]:
        """Each unit's total spp after `budget` more seconds: n_u = max(spp_u, lam sqrt(a_u v_u / k_u)),
        lam such that sum k_u (n_u - spp_u) = budget (k_u: its seconds per spp), found by water-filling."""
        cost = [max(u.seconds / u.spp, 1e-9) if u.spp else 1e-9 for u in self.units]
        weight = [math.sqrt(u.area * u.variance / k) for u, k in zip(self.units, cost, strict=True)]
        free = {i for i, w in enumerate(weight) if w > 0 and self.units[i].spp < self.goal.spp_cap}
        while free:
            spend = budget + sum(cost[i] * self.units[i].spp for i in free)
            lam = spend / sum(cost[i] * weight[i] for i in free)
            below = {i for i in free if lam * weight[i] < self.units[i].spp}
            if not below:
                return [lam * weight[i] if i in free else u.spp for i, u in enumerate(self.units)]
            free -= below
        return [u.spp for u in self.units]

    # -- the end --

    def _stop(self, elapsed: float) -> list[Finish]:
        if any(u.spp == 0 for u in self.units):
            return []
        spp = sorted(u.spp for u in self.units)
        held = f"{spp[0]} spp a unit" if spp[0] == spp[-1] else f"{spp[0]}-{spp[-1]} spp a unit"
        self.finished = Finish(f"Ctrl-C after {elapsed:.1f} s, with {held}",
                               {i: "met" if self.goal.kind == NOISE and self._met(u) else "stopped"
                                for i, u in enumerate(self.units)})
        return [self.finished]

    def _reason(self, elapsed: float) -> str:
        if self.goal.kind == BUDGET:
            return f"every unit has its samples ({elapsed:.1f} s)"
        if self.goal.kind == NOISE:  # it ends when each unit is under the error or at the cap
            met, units = sum(self._met(u) for u in self.units), len(self.units)
            above = f", the other {units - met} at the cap of {self.goal.spp_cap} spp" if met < units else ""
            return f"{met} of {count(units, 'unit')} under relative error {self.goal.noise:g}{above}"
        noisy = any(u.spp < self.goal.spp_cap and u.variance > 0 for u in self.units)
        if elapsed >= self.goal.seconds or noisy:  # noisy: what is left buys no unit another sample
            return f"the {self.goal.seconds:g} s of rendering are spent ({elapsed:.1f} s)"
        return f"no unit has noise left to lower under the cap of {self.goal.spp_cap} spp ({elapsed:.1f} s)"

    def _verdicts(self) -> dict[int, str]:
        def verdict(unit: UnitNoise) -> str:
            if self.goal.kind == BUDGET:
                return "budget"
            if self.goal.kind == NOISE and self._met(unit):
                return "met"
            return "cap" if unit.spp >= self.goal.spp_cap else "time"
        return {i: verdict(u) for i, u in enumerate(self.units)}
