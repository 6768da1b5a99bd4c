"""Progressive rendering's decisions: which units get another pass, at how many samples, and when a job
stops. A pure state machine (`Progressive.handle`: a typed stimulus in, typed instructions out, no I/O);
the one-process pipeline drives it, and the farm's auction will.

Every unit first renders FIRST_PASSES passes of `first_spp`, so that its noise can be estimated between
them (core.image.passes). Then, by the goal:
- `noise` TAU: each unit whose estimated relative error sqrt(relMSE) is above TAU gets the samples its
  estimate says it lacks, at most doubling its count, never past the spp cap; the job stops when every
  unit is under TAU or at the cap.
- `time` SECONDS: rounds of growing length (each at most the time spent so far) place samples where the
  image's relMSE falls most per second: each unit's total n_u in proportion to sqrt(a_u v_u / k_u) (area,
  per-sample relative variance, seconds per spp; never below what it has), until the time is spent or
  every unit is at the cap.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

FIRST_PASSES = 4  # passes before a unit's noise is first estimated
FIRST_SHARE = 64  # the first passes render spp_cap / FIRST_SHARE samples each, at least 1 and at most
FIRST_SPP_MAX = 8  # FIRST_SPP_MAX: a time goal's first round must not outlast its time
ROUND_MIN_S = 0.5  # the first time-goal round's length, at least
NOISE, TIME = "noise", "time"


@dataclass(frozen=True)
class Goal:
    """What a progressive job renders to: `kind` NOISE (relative error `noise` per unit) or TIME (`seconds`
    of rendering), never past `spp_cap` samples per pixel in any unit."""

    kind: str
    spp_cap: int
    noise: float | None = None
    seconds: float | None = None

    def __post_init__(self) -> None:
        if self.kind == NOISE and not (self.noise is not None and 0 < self.noise < math.inf):
            raise ValueError(f"a noise goal needs a positive relative error, not {self.noise!r}")
        if self.kind == TIME and not (self.seconds is not None and 0 < self.seconds < math.inf):
            raise ValueError(f"a time goal needs a positive number of seconds, not {self.seconds!r}")
        if self.kind not in (NOISE, TIME) or self.spp_cap < 1:
            raise ValueError(f"goal {self.kind!r} with spp cap {self.spp_cap}")

    @property
    def first_spp(self) -> int:
        return min(max(1, self.spp_cap // FIRST_SHARE), FIRST_SPP_MAX)


# ---- stimuli ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PassDone:
    """A unit's pass has been merged: the unit's samples per pixel, seconds of render and estimated relMSE
    (None while unknown) now, all passes together."""

    unit: int
    spp: int
    seconds: float
    relmse: float | None


@dataclass(frozen=True)
class RoundDone:
    """Every pass ordered in the last round is done (each reported by a PassDone); `elapsed` seconds of
    rendering so far."""

    elapsed: float


# ---- instructions -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PassOrder:
    """Render unit `unit`'s pass number `pass_index` at `spp` samples per pixel."""

    unit: int
    pass_index: int
    spp: int


@dataclass(frozen=True)
class RenderRound:
    """Render these passes, then report each (PassDone) and the round (RoundDone)."""

    orders: tuple[PassOrder, ...]


@dataclass(frozen=True)
class Finish:
    """Stop: the job's image is its units' merged passes. `reason` says why; `units` each unit's verdict."""

    reason: str
    units: dict[int, str] = field(default_factory=dict)


# ---- the machine --------------------------------------------------------------------------------------


@dataclass
class UnitNoise:
    """What the machine knows of one unit."""

    area: int
    spp: int = 0
    passes: int = 0
    seconds: float = 0.0
    relmse: float | None = None

    @property
    def variance(self) -> float:
        """Per-sample relative variance v: relMSE(n) = v / n."""
        return (self.relmse or 0.0) * self.spp


class Progressive:
    """The decisions of one progressive job over units of the given pixel areas (index: position)."""

    def __init__(self, goal: Goal, areas: list[int]) -> None:
        self.goal = goal
        self.units = [UnitNoise(a) for a in areas]
        self.finished: Finish | None = None

    def start(self) -> list[RenderRound | Finish]:
        """The first round: FIRST_PASSES passes of every unit (fewer where the cap comes first)."""
        spp = min(self.goal.first_spp, self.goal.spp_cap)
        passes = max(1, min(FIRST_PASSES, self.goal.spp_cap // spp))
        orders = tuple(PassOrder(u, k, spp) for k in range(passes) for u in range(len(self.units)))
        return [RenderRound(orders)]

    def handle(self, stimulus: PassDone | RoundDone) -> list[RenderRound | Finish]:
        """The one entry: a stimulus in, the instructions it leads to out."""
        if self.finished is not None:
            return []
        if isinstance(stimulus, PassDone):
            unit = self.units[stimulus.unit]
            unit.spp, unit.seconds, unit.relmse = stimulus.spp, stimulus.seconds, stimulus.relmse
            unit.passes += 1
            return []
        orders = self._noise_round() if self.goal.kind == NOISE else self._time_round(stimulus.elapsed)
        if orders:
            return [RenderRound(orders)]
        self.finished = Finish(self._reason(stimulus.elapsed), self._verdicts())
        return [self.finished]

    # -- the noise goal --

    def _noise_round(self) -> tuple[PassOrder, ...]:
        orders = []
        for index, unit in enumerate(self.units):
            room = self.goal.spp_cap - unit.spp
            if room <= 0 or self._met(unit):
                continue
            lacking = unit.variance / self.goal.noise ** 2 - unit.spp if unit.relmse is not None else unit.spp
            spp = min(max(math.ceil(lacking), self.goal.first_spp), unit.spp, room)
            orders.append(PassOrder(index, unit.passes, spp))
        return tuple(orders)

    def _met(self, unit: UnitNoise) -> bool:
        return unit.relmse is not None and math.sqrt(unit.relmse) <= self.goal.noise

    # -- the time goal --

    def _time_round(self, elapsed: float) -> tuple[PassOrder, ...]:
        left = self.goal.seconds - elapsed
        if left <= 0:
            return ()
        budget = min(left, max(elapsed, ROUND_MIN_S))
        targets = self._neyman(budget)
        orders = []
        for index, (unit, target) in enumerate(zip(self.units, targets, strict=True)):
            spp = min(int(target) - unit.spp, self.goal.spp_cap - unit.spp)
            if spp >= 1:
                orders.append(PassOrder(index, unit.passes, spp))
        return tuple(orders)

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

    def _reason(self, elapsed: float) -> str:
        capped = sum(u.spp >= self.goal.spp_cap for u in self.units)
        if self.goal.kind == NOISE:
            met = sum(self._met(u) for u in self.units)
            return (f"{met} of {len(self.units)} units under relative error {self.goal.noise:g}, {capped} at the "
                    f"cap of {self.goal.spp_cap} spp")
        if elapsed >= self.goal.seconds:
            return f"the {self.goal.seconds:g} s of rendering are spent ({elapsed:.1f} s)"
        return f"no unit has noise left to lower under the cap of {self.goal.spp_cap} spp ({elapsed:.1f} s)"

    def _verdicts(self) -> dict[int, str]:
        def verdict(unit: UnitNoise) -> str:
            if self.goal.kind == NOISE and self._met(unit):
                return "met"
            return "cap" if unit.spp >= self.goal.spp_cap else "time"
        return {i: verdict(u) for i, u in enumerate(self.units)}
