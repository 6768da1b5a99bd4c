"""The look-ahead: a projected list schedule of a job's open units over its agents (plain functions).

`project` places each unit, most costly first, on the agent where it would finish earliest; `refine`
shortens that schedule in the end game by moves and swaps; `fluid_finish` is the lower bound it stops at.
"""

from __future__ import annotations

import bisect
import heapq
from collections.abc import Iterable
from dataclasses import dataclass


@dataclass(frozen=True)
class PlanAgent:
    """An agent as the projection sees it: when it is next free, and its seconds per unit of cost."""

    name: str
    available: float
    rate: float


@dataclass(frozen=True)
class ProjectedUnit:
    """A unit to place: its index, cost, and the agents that may not take it (it failed on them)."""

    index: int
    cost: float
    excluded: frozenset[str] = frozenset()


@dataclass(frozen=True)
class Placement:
    agent: str
    start: float
    finish: float


def project(units: Iterable[ProjectedUnit], agents: Iterable[PlanAgent]) -> dict[int, Placement]:
    """List schedule of `units`, most costly first, each on the agent where it would finish earliest (ties:
    the earlier start, then the name). Units that no agent may take are left out.

    Agents of one rate are interchangeable, so each unit only compares the earliest free agent of every
    rate (a heap per rate): O(units x rates x log agents), not units x agents.
    """
    heaps: dict[float, list[tuple[float, str]]] = {}
    for agent in agents:
        heaps.setdefault(agent.rate, []).append((agent.available, agent.name))
    for heap in heaps.values():
        heapq.heapify(heap)
    plan: dict[int, Placement] = {}
    for unit in sorted(units, key=lambda u: (-u.cost, u.index)):
        best: tuple[float, float, str, float] | None = None  # finish, start, name, rate
        for rate, heap in heaps.items():
            entry = _first_allowed(heap, unit.excluded)
            if entry is not None:
                candidate = (entry[0] + rate * unit.cost, entry[0], entry[1], rate)
                best = candidate if best is None or candidate < best else best
        if best is None:
            continue
        finish, start, name, rate = best
        heap = heaps[rate]
        if heap[0] == (start, name):
            heapq.heapreplace(heap, (finish, name))
        else:  # a unit with exclusions took an agent below the root (rare): O(agents)
            heap.remove((start, name))
            heap.append((finish, name))
            heapq.heapify(heap)
        plan[unit.index] = Placement(name, start, finish)
    return plan


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
    owned: dict[str, list[int]] = {name: [] for name in agent_of}
    finish = {a.name: a.available for a in agent_of.values()}
    for index, place in plan.items():
        owned[place.agent].append(index)
        finish[place.agent] = max(finish[place.agent], place.finish)
    for _ in range(max_moves):
        last = max(finish, key=lambda n: (finish[n], n))
        if finish[last] <= good_enough:
            break
        step = _best_step(last, owned, finish, unit_of, agent_of)
        if step is None:
            break
        index, other, back = step
        _move(index, last, other, owned, finish, unit_of, agent_of)
        if back is not None:
            _move(back, other, last, owned, finish, unit_of, agent_of)
    out: dict[int, Placement] = {}
    for name, indices in owned.items():
        t = agent_of[name].available
        for index in sorted(indices, key=lambda i: (-unit_of[i].cost, i)):
            end = t + agent_of[name].rate * unit_of[index].cost
            out[index] = Placement(name, t, end)
            t = end
    return out


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


def _best_step(
    last: str,
    owned: dict[str, list[int]],
    finish: dict[str, float],
    unit_of: dict[int, ProjectedUnit],
    agent_of: dict[str, PlanAgent],
) -> tuple[int, str, int | None] | None:
    """The move (unit, to agent, None) or swap (unit, with agent, its unit) that lowers the later finish of
    `last` and the other agent the most. A swap trading cost d ends at max(top - ra d, fb + rb d), lowest at
    d* = (top - fb) / (ra + rb): only the other agent's two units nearest to that difference are tried
    (a bisection in its sorted costs), so a step costs O(units of last x agents x log units)."""
    top, rate_a = finish[last], agent_of[last].rate
    best: tuple[float, int, str, int | None] | None = None
    for other, theirs in owned.items():
        if other == last:
            continue
        rate_b, fin_b = agent_of[other].rate, finish[other]
        ranked = sorted((unit_of[i].cost, i) for i in theirs)
        costs = [c for c, _ in ranked]
        ideal = (top - fin_b) / (rate_a + rate_b)
        for index in owned[last]:
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


def _move(
    index: int,
    src: str,
    dst: str,
    owned: dict[str, list[int]],
    finish: dict[str, float],
    unit_of: dict[int, ProjectedUnit],
    agent_of: dict[str, PlanAgent],
) -> None:
    owned[src].remove(index)
    owned[dst].append(index)
    finish[src] -= agent_of[src].rate * unit_of[index].cost
    finish[dst] += agent_of[dst].rate * unit_of[index].cost


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
