"""The look-ahead: a projected list schedule of a job's open units over its agents (no state kept between
calls).

`project` places each unit, most costly first, on the agent where it would finish earliest (`ListSchedule`:
the same, one unit at a time, for a caller that needs only the first places); `refine` shortens that
schedule in the end game by moves and swaps; `fluid_finish` is the lower bound it stops at.
"""

from __future__ import annotations

import bisect
import heapq
import itertools
import math
import operator
from collections.abc import Collection, Iterable, Sequence
from typing import NamedTuple


class PlanAgent(NamedTuple):
    """An agent as the projection sees it: when it is next free, and its seconds per unit of cost."""

    name: str
    available: float
    rate: float


class ProjectedUnit(NamedTuple):
    """A unit to place: its index, cost, and the agents that may not take it (it failed on them)."""

    index: int
    cost: float
    excluded: frozenset[str] = frozenset()


class Placement(NamedTuple):
    agent: str
    start: float
    finish: float


def project(units: Iterable[ProjectedUnit], agents: Iterable[PlanAgent]) -> dict[int, Placement]:
    """List schedule of `units`, most costly first, each on the agent where it would finish earliest (ties:
    the earlier start, then the name). Units that no agent may take are left out."""
    schedule, plan = ListSchedule(agents), {}
    for unit in sorted(units, key=lambda u: (-u.cost, u.index)):
        place = schedule.place(unit.cost, unit.excluded)
        if place is not None:
            plan[unit.index] = place
    return plan


class ListSchedule:
    """`project`'s list schedule, built one unit at a time by a caller that gives the units most costly first
    (ties: the lower index). A unit's place depends only on the units placed before it, so a caller that
    needs the first places alone stops early and pays for those (`never_places` tells it when the rest
    cannot reach an agent).

    Agents of one rate are interchangeable, so each unit only compares the earliest free agent of every
    rate (a heap per rate): O(rates x log agents) a unit, not O(agents).
    """

    def __init__(self, agents: Iterable[tuple[str, float, float]]) -> None:
        """`agents`: PlanAgents, or their (name, available, rate)."""
        self.heaps: dict[float, list[tuple[float, str]]] = {}  # rate -> (when free, name) of its agents
        for name, available, rate in agents:
            self.heaps.setdefault(rate, []).append((available, name))
        for heap in self.heaps.values():
            heapq.heapify(heap)

    def place(self, cost: float, excluded: frozenset[str] = frozenset()) -> Placement | None:
        """The place of the next unit, of `cost`, that the `excluded` agents may not take (None: no agent
        may), taken."""
        best: tuple[float, float, str, float] | None = None  # finish, start, name, rate
        for rate, heap in self.heaps.items():
            entry = _first_allowed(heap, excluded) if excluded else heap[0]
            if entry is not None:
                candidate = (entry[0] + rate * cost, entry[0], entry[1], rate)
                if best is None or candidate < best:
                    best = candidate
        if best is None:
            return None
        finish, start, name, rate = best
        heap = self.heaps[rate]
        if heap[0] == (start, name):
            heapq.heapreplace(heap, (finish, name))
        else:  # a unit with exclusions took an agent below the root (rare): O(agents)
            heap.remove((start, name))
            heap.append((finish, name))
            heapq.heapify(heap)
        return Placement(name, start, finish)

    def place_until(self, costs: Sequence[float], at: int, stop: int, watched: Collection[str]) -> int:
        """`place` the units of `costs[at:stop]` (none excluding an agent) while each goes to an agent not
        `watched`: the position of the first that would go to a watched one, not placed (else `stop`)."""
        groups = list(self.heaps.items())
        for position in range(at, stop):
            cost, best = costs[position], None
            for rate, heap in groups:
                start, name = heap[0]
                candidate = (start + rate * cost, start, name, rate)
                if best is None or candidate < best:
                    best = candidate
            if best is None or best[2] in watched:
                return position
            heapq.heapreplace(self.heaps[best[3]], (best[0], best[2]))
        return stop

    def never_places(self, names: Collection[str], costs: Sequence[float]) -> bool:
        """Whether no unit yet to place goes to any of `names`, where `costs` are those units' costs, most
        costly first, and none excludes an agent.

        Until the first such unit, of cost w, the other agents take the units before it, of work W; then one
        of them would still finish it by T(W, w), the time by which they, each from its time + rate x w,
        could have done W (had each of them more than its share, they would hold more than W). T grows with
        W and w, so the units are taken in bands of halving cost: an agent of `names` that would finish
        even a band's least costly unit after T(the work up to the band's end, its most costly) is never
        the earliest for a unit of the band.
        """
        if not names or not costs:
            return True
        bands = _bands(costs)
        theirs = [(start, rate) for rate, heap in self.heaps.items() for start, name in heap if name in names]
        if not theirs:
            return True
        reach = [min(start + rate * least for start, rate in theirs) for _, least, _ in bands]
        if any(r <= self._floor(work, most) for r, (most, _, work) in zip(reach, bands, strict=True)):
            return False  # a quick test: T is no earlier than that floor
        others = _Capacity({rate: [start for start, name in heap if name not in names]
                            for rate, heap in self.heaps.items()})
        return all(others.covers(r - 1e-9 * (1.0 + abs(r)), most, work)
                   for r, (most, _, work) in zip(reach, bands, strict=True))

    def _floor(self, work: float, cost: float) -> float:
        """A time no later than `never_places`'s T(work, cost): every agent working from the soonest start."""
        pace = sum(len(heap) / max(rate, MIN_RATE) for rate, heap in self.heaps.items())
        return min(heap[0][0] + rate * cost for rate, heap in self.heaps.items()) + work / pace


def _bands(costs: Sequence[float], most: int = 24) -> list[tuple[float, float, float]]:
    """`costs` (most costly first) cut where the cost halves (at most `most` bands, the last taking the rest):
    each band's first and last cost, and the work of the costs up to its end."""
    totals = list(itertools.accumulate(costs))
    bands, at = [], 0
    while at < len(costs):
        end = len(costs) if len(bands) == most - 1 else \
            bisect.bisect_right(costs, -costs[at] / 2, lo=at, key=operator.neg)
        bands.append((costs[at], costs[end - 1], totals[end - 1]))
        at = end
    return bands


class _Capacity:
    """The work agents could do by a time, each from its start + rate x a preload (`never_places`): per
    rate, their starts sorted, with prefix sums."""

    def __init__(self, starts: dict[float, list[float]]) -> None:
        self.groups = []
        for rate, group in starts.items():
            ranked = sorted(group)
            self.groups.append((rate, ranked, [0.0, *itertools.accumulate(ranked)]))

    def covers(self, t: float, preload: float, work: float) -> bool:
        """Whether they could have done `work` by `t` (with a margin for the sums' rounding)."""
        done = slack = 0.0
        for rate, starts, sums in self.groups:
            x = t - rate * preload
            n = bisect.bisect_left(starts, x)
            done += (n * x - sums[n]) / max(rate, MIN_RATE)
            slack += (n * abs(x) + abs(sums[n])) / max(rate, MIN_RATE)
        return done - 1e-9 * slack >= work * (1.0 + 1e-9)


def refine(
    plan: dict[int, Placement],
    units: Iterable[ProjectedUnit],
    agents: Iterable[PlanAgent],
    max_moves: int = 64,
    gap: float = 0.002,
) -> dict[int, Placement]:
    """A shorter schedule than `plan` where one is found: units move, or swap, off the agent that finishes
    last while that lowers the later finish of the pair (the best such step first, `max_moves` at most),
    until the schedule ends within `gap` of the fluid bound (`fluid_finish`). Each agent then takes its
    units most costly first. List scheduling alone ends ~5 % above the ideal with a few units per agent
    (the last units do not fill the gaps); this recovers most of it.
    """
    unit_of = {u.index: u for u in units}
    agent_of = {a.name: a for a in agents}
    if not plan:
        return {}
    good_enough = fluid_finish([unit_of[i].cost for i in plan], agent_of.values()) * (1 + gap)
    book, moved = _Book(plan, unit_of, agent_of), False
    for _ in range(max_moves):
        last = max((f, n) for n, f in book.finish.items())[1]
        if book.finish[last] <= good_enough:
            break
        step = _best_step(last, book)
        if step is None:
            break
        index, other, back = step
        book.move(index, last, other)
        if back is not None:
            book.move(back, other, last)
        moved = True
    if book.listed and not moved:
        return dict(plan)  # each agent's units already back to back, most costly first
    out: dict[int, Placement] = {}
    for name, indices in book.owned.items():
        t = agent_of[name].available
        for index in sorted(indices, key=lambda i: (-unit_of[i].cost, i)):
            end = t + agent_of[name].rate * unit_of[index].cost
            out[index] = Placement(name, t, end)
            t = end
    return out


class _Book:
    """`refine`'s schedule as it changes: each agent's units (in the order they came to it), when it
    finishes, its least costly unit, and (`ranked`, sorted when first asked) its units' (cost, index).
    `listed`: whether the plan given already had each agent's units back to back from its time, most costly
    first (as `project` places them)."""

    def __init__(self, plan: dict[int, Placement], unit_of: dict[int, ProjectedUnit],
                 agent_of: dict[str, PlanAgent]) -> None:
        self.unit_of, self.agent_of, self.listed = unit_of, agent_of, True
        self.owned: dict[str, list[int]] = {name: [] for name in agent_of}
        self.finish = {a.name: a.available for a in agent_of.values()}
        self.cheapest = dict.fromkeys(agent_of, math.inf)
        self._ranked: dict[str, list[tuple[float, int]]] = {}
        for index, place in plan.items():
            name, cost = place.agent, unit_of[index].cost
            mine = self.owned[name]
            self.listed = self.listed and place.start == (self.finish[name] if mine else agent_of[name].available) \
                and place.finish == place.start + agent_of[name].rate * cost \
                and (not mine or (-unit_of[mine[-1]].cost, mine[-1]) < (-cost, index))
            mine.append(index)
            self.finish[name] = max(self.finish[name], place.finish)
            self.cheapest[name] = min(self.cheapest[name], cost)

    def ranked(self, name: str) -> list[tuple[float, int]]:
        if name not in self._ranked:
            self._ranked[name] = sorted((self.unit_of[i].cost, i) for i in self.owned[name])
        return self._ranked[name]

    def move(self, index: int, src: str, dst: str) -> None:
        cost = self.unit_of[index].cost
        self.owned[src].remove(index)
        self.owned[dst].append(index)
        self.cheapest[src] = min((self.unit_of[i].cost for i in self.owned[src]), default=math.inf)
        self.cheapest[dst] = min(self.cheapest[dst], cost)
        if src in self._ranked:
            self._ranked[src].remove((cost, index))
        if dst in self._ranked:
            bisect.insort(self._ranked[dst], (cost, index))
        self.finish[src] -= self.agent_of[src].rate * cost
        self.finish[dst] += self.agent_of[dst].rate * cost


def fluid_finish(costs: Iterable[float], agents: Iterable[PlanAgent]) -> float:
    """The earliest end of `costs` if work could be split at will: the time T at which the agents, each
    working from its availability at 1 / rate cost per second, have done it all (a lower bound)."""
    work = sum(costs)
    ranked = sorted((a.available, 1.0 / max(a.rate, MIN_RATE)) for a in agents)
    t, pace = ranked[0][0], 0.0
    for i, (start, speed) in enumerate(ranked):
        if pace > 0 and t + work / pace <= start:
            break
        work -= pace * (start - t)
        t, pace = start, pace + speed
        if i == len(ranked) - 1:
            break
    return t + work / pace


def _best_step(last: str, book: _Book) -> tuple[int, str, int | None] | None:
    """The move (unit, to agent, None) or swap (unit, with agent, its unit) that lowers the later finish of
    `last` and the other agent the most (the first such in the book's order, where several do). A swap
    trading cost d ends at max(top - ra d, fb + rb d), lowest at d* = (top - fb) / (ra + rb): only the other
    agent's two units nearest to that difference are tried (a bisection in its sorted costs), so a step
    costs O(units of last x agents x log units). An agent none of whose steps could be the best is passed
    over at once (`_hopeless`)."""
    unit_of, mine = book.unit_of, book.owned[last]
    if not mine:
        return None
    top, rate_a = book.finish[last], book.agent_of[last].rate
    costs_a = [unit_of[i].cost for i in mine]
    span = (min(costs_a), max(costs_a))
    best: tuple[float, int, str, int | None] | None = None
    for other in book.owned:
        if other == last or _hopeless(book, other, top, rate_a, span, best):
            continue
        rate_b, fin_b, ranked = book.agent_of[other].rate, book.finish[other], book.ranked(other)
        costs = [c for c, _ in ranked]
        ideal = (top - fin_b) / (rate_a + rate_b)
        for index in mine:
            u = unit_of[index]
            if other in u.excluded:
                continue
            options: list[tuple[float, int | None]] = [(u.cost, None)]  # d = the unit's cost: a move
            at = bisect.bisect_left(costs, u.cost - ideal)
            options += [(u.cost - ranked[j][0], ranked[j][1]) for j in (at - 1, at) if 0 <= j < len(ranked)]
            for d, back in options:
                if d <= 0 or (back is not None and last in unit_of[back].excluded):
                    continue
                worst = max(top - rate_a * d, fin_b + rate_b * d)
                if worst < top - 1e-9 and (best is None or worst < best[0]):
                    best = (worst, index, other, back)
    return None if best is None else best[1:]


def _hopeless(book: _Book, other: str, top: float, rate_a: float, span: tuple[float, float],
              best: tuple[float, int, str, int | None] | None) -> bool:
    """Whether no step with `other` can end before `top` (less 1e-9) and before the `best` so far, `span`
    the least and most costly of last's units: no swap trades a positive cost (its units cost no less than
    any of last's) and no move ends in time; or every trade d ends no earlier than max(top - ra d,
    fb + rb d) >= (rb top + ra fb) / (ra + rb), past `best` (with a margin for rounding)."""
    rate_b, fin_b = book.agent_of[other].rate, book.finish[other]
    if book.cheapest[other] >= span[1] and fin_b + rate_b * span[0] >= top - 1e-9:
        return True
    floor = (rate_b * top + rate_a * fin_b) / (rate_a + rate_b)
    return best is not None and floor > best[0] + 1e-9 * (1.0 + abs(top) + abs(fin_b))


def _first_allowed(heap: list[tuple[float, str]], excluded: frozenset[str]) -> tuple[float, str] | None:
    if not excluded:
        return heap[0] if heap else None
    allowed = [entry for entry in heap if entry[1] not in excluded]
    return min(allowed) if allowed else None


def round_rate(rate: float) -> float:
    # Rates learnt from sums of bids differ in the last bits between agents of one speed; rounding lets
    # them share a heap in `project`.
    return float(f"{rate:.9g}")



MIN_RATE, MAX_RATE = 1e-9, 1e9  # seconds per unit of cost: the projection's arithmetic stays finite
