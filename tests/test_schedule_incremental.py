"""The look-ahead read lazily agrees with the look-ahead computed whole.

The auction reads the projection most costly unit first and stops once no later placement could change the
offers (`master.auction.machine._offers`); it keeps indexes between ticks (the open units, the deadlines,
the agents it watches). Each is checked here against a from-scratch computation: the list schedule against
an earliest-finish rule over every agent, `refine` against its plain form (every agent's units sorted at
every step), and the offers against the offers read off the whole projection, at every call of a
simulated farm's auction.
"""

from __future__ import annotations

import bisect
import dataclasses
import math
import random

import pytest
from auction_support import message, register, submit, tick
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bench.simulate import simulate
from core.model import messages as m
from core.model.geometry import Rect
from core.model.status import UnitStatus
from core.model.units import WorkUnit
from master import auction as au
from master.auction import machine, schedule
from master.auction.state import Job, UnitState

RATES = (0.5, 1.0, 2.0 / 3.0, 2.0)  # few rates: agents of one rate share a heap, and tie
FEW = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])

costs_st = st.lists(st.sampled_from([0.5, 1.0, 1.5, 2.0, 3.0, 7.0]) | st.floats(0.01, 20.0), min_size=0, max_size=40)


@st.composite
def farms(draw, most: int = 8) -> list[au.PlanAgent]:
    n = draw(st.integers(0, most))
    return [au.PlanAgent(f"a{i}", draw(st.sampled_from([0.0, 0.0, 1.0, 2.5]) | st.floats(0.0, 10.0)),
                         draw(st.sampled_from(RATES))) for i in range(n)]


@st.composite
def units_for(draw, agents: list[au.PlanAgent]) -> list[au.ProjectedUnit]:
    names = [a.name for a in agents]
    costs = draw(costs_st)
    return [au.ProjectedUnit(i, c, frozenset(draw(st.lists(st.sampled_from(names), max_size=2))) if names
                             and draw(st.integers(0, 5)) == 0 else frozenset()) for i, c in enumerate(costs)]


def earliest_finish(units: list[au.ProjectedUnit], agents: list[au.PlanAgent]) -> dict[int, au.Placement]:
    """The list schedule by its definition: most costly first, each on the agent, of all, where it would
    finish earliest (ties: the earlier start, then the name)."""
    free = {a.name: a.available for a in agents}
    rate = {a.name: a.rate for a in agents}
    plan = {}
    for unit in sorted(units, key=lambda u: (-u.cost, u.index)):
        options = [(free[n] + rate[n] * unit.cost, free[n], n) for n in free if n not in unit.excluded]
        if options:
            finish, start, name = min(options)
            plan[unit.index], free[name] = au.Placement(name, start, finish), finish
    return plan


# --- the list schedule, whole and a unit at a time ----------------------------------------------------------


@FEW
@given(st.data())
def test_the_list_schedule_places_each_unit_where_it_finishes_first(data) -> None:
    agents = data.draw(farms())
    units = data.draw(units_for(agents))
    assert au.project(units, agents) == earliest_finish(units, agents)


@FEW
@given(st.data())
def test_placing_until_a_watched_agent_leaves_the_schedule_as_placing_one_by_one(data) -> None:
    agents = data.draw(farms())
    costs = sorted(data.draw(costs_st), reverse=True)
    watched = set(data.draw(st.lists(st.sampled_from([a.name for a in agents]), max_size=3))) if agents else set()
    whole = earliest_finish([au.ProjectedUnit(i, c) for i, c in enumerate(costs)], agents)
    fast, slow, at = schedule.ListSchedule(agents), schedule.ListSchedule(agents), 0
    while at < len(costs):
        stop = fast.place_until(costs, at, len(costs), watched)
        for position in range(at, stop):  # on agents not watched
            assert slow.place(costs[position]).agent not in watched
        if stop < len(costs):  # the unit it stopped at goes to a watched agent (or, without agents, nowhere)
            place = fast.place(costs[stop])
            assert place == slow.place(costs[stop]) == whole.get(stop)
            assert place is None or place.agent in watched
        assert fast.heaps == slow.heaps
        at = stop + 1


def test_the_list_schedule_at_its_edges() -> None:
    assert au.project([au.ProjectedUnit(0, 1.0)], []) == {}  # no agents
    assert schedule.ListSchedule([]).place_until([1.0, 2.0], 0, 2, set()) == 0  # nobody to take them
    one = [au.PlanAgent("a", 3.0, 2.0)]
    assert au.project([au.ProjectedUnit(5, 1.5)], one) == {5: au.Placement("a", 3.0, 6.0)}  # one unit
    equal = [au.PlanAgent(n, 0.0, 1.0) for n in ("c", "a", "b")]  # equal rates and times: by name
    assert [p.agent for p in au.project([au.ProjectedUnit(i, 1.0) for i in range(4)], equal).values()] == \
        ["a", "b", "c", "a"]
    excluded = au.ProjectedUnit(0, 1.0, frozenset({"a"}))  # the earliest agent may not take it
    assert au.project([excluded], equal) == {0: au.Placement("b", 0.0, 1.0)}


# --- when the rest of the schedule cannot reach an agent ------------------------------------------------------


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_never_places_is_never_wrong(data) -> None:
    agents = data.draw(farms(most=10))
    costs = sorted(data.draw(costs_st), reverse=True)
    read = data.draw(st.integers(0, len(costs)))
    names = set(data.draw(st.lists(st.sampled_from([a.name for a in agents]), max_size=3))) if agents else set()
    whole = earliest_finish([au.ProjectedUnit(i, c) for i, c in enumerate(costs)], agents)
    partial = schedule.ListSchedule(agents)
    for cost in costs[:read]:
        partial.place(cost)
    if partial.never_places(names, costs[read:]):
        assert not any(whole[i].agent in names for i in range(read, len(costs)) if i in whole)


def test_never_places_tells_a_far_agent_apart_and_answers_at_its_edges() -> None:
    near = [au.PlanAgent(f"n{i}", 0.0, 1.0) for i in range(4)]
    far = au.PlanAgent("far", 1000.0, 1.0)
    costs = [8.0, 4.0, 2.0, 1.0, 1.0, 0.5]
    ahead = schedule.ListSchedule([*near, far])
    assert ahead.never_places({"far"}, costs)  # the others end it all long before 1000
    assert not ahead.never_places({"n0"}, costs)  # n0 takes the first unit
    assert ahead.never_places(set(), costs) and ahead.never_places({"far"}, [])  # nobody; nothing left
    assert not schedule.ListSchedule([far]).never_places({"far"}, costs)  # the only agent


@FEW
@given(st.lists(st.floats(0.0, 50.0), min_size=1, max_size=40))
def test_bands_halve_and_cover_the_costs(raw: list[float]) -> None:
    costs = sorted(raw, reverse=True)
    bands = schedule._bands(costs)
    assert bands[0][0] == costs[0] and bands[-1][1] == costs[-1]
    assert math.isclose(bands[-1][2], sum(costs), rel_tol=1e-9, abs_tol=1e-12)
    for most, least, _ in bands[:-1]:
        assert least >= most / 2


@FEW
@given(st.dictionaries(st.sampled_from(RATES), st.lists(st.floats(0.0, 20.0), max_size=6)), st.floats(0.0, 30.0),
       st.floats(0.0, 5.0), st.floats(0.0, 40.0))
def test_capacity_is_the_work_the_agents_could_do_by_then(starts, t: float, preload: float, work: float) -> None:
    exact = sum(max(0.0, t - (s + rate * preload)) / rate for rate, group in starts.items() for s in group)
    covers = schedule._Capacity({r: list(g) for r, g in starts.items()}).covers(t, preload, work)
    if covers:
        assert exact >= work
    elif exact > work * 1.001 + 1e-6:
        pytest.fail(f"capacity {exact} covers {work}, said not to")


# --- refine, against its plain form -------------------------------------------------------------------------


def plain_refine(plan, units, agents, max_moves=64, gap=0.002):
    """`refine` with every agent's units sorted anew at each step and no agent passed over."""
    unit_of = {u.index: u for u in units}
    agent_of = {a.name: a for a in agents}
    if not plan:
        return {}
    good_enough = au.fluid_finish([unit_of[i].cost for i in plan], agent_of.values()) * (1 + gap)
    owned = {name: [] for name in agent_of}
    finish = {a.name: a.available for a in agent_of.values()}
    for index, place in plan.items():
        owned[place.agent].append(index)
        finish[place.agent] = max(finish[place.agent], place.finish)
    for _ in range(max_moves):
        last = max(finish, key=lambda n: (finish[n], n))
        if finish[last] <= good_enough:
            break
        step = plain_best_step(last, owned, finish, unit_of, agent_of)
        if step is None:
            break
        index, other, back = step
        for i, src, dst in [(index, last, other)] + ([(back, other, last)] if back is not None else []):
            owned[src].remove(i)
            owned[dst].append(i)
            finish[src] -= agent_of[src].rate * unit_of[i].cost
            finish[dst] += agent_of[dst].rate * unit_of[i].cost
    out = {}
    for name, indices in owned.items():
        t = agent_of[name].available
        for index in sorted(indices, key=lambda i: (-unit_of[i].cost, i)):
            end = t + agent_of[name].rate * unit_of[index].cost
            out[index] = au.Placement(name, t, end)
            t = end
    return out


def plain_best_step(last, owned, finish, unit_of, agent_of):
    top, rate_a = finish[last], agent_of[last].rate
    best = None
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
            options = [(u.cost, None)]
            at = bisect.bisect_left(costs, u.cost - ideal)
            options += [(u.cost - ranked[j][0], ranked[j][1]) for j in (at - 1, at) if 0 <= j < len(ranked)]
            for d, back in options:
                if d <= 0 or (back is not None and last in unit_of[back].excluded):
                    continue
                worst = max(top - rate_a * d, fin_b + rate_b * d)
                if worst < top - 1e-9 and (best is None or worst < best[0]):
                    best = (worst, index, other, back)
    return None if best is None else best[1:]


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_refine_takes_the_steps_of_its_plain_form(data) -> None:
    agents = data.draw(farms())
    units = data.draw(units_for(agents))
    plan = au.project(units, agents)
    moves = data.draw(st.sampled_from([1, 2, 64]))
    assert au.refine(plan, units, agents, moves) == plain_refine(plan, units, agents, moves)


# --- the job's indexes --------------------------------------------------------------------------------------


def spec(index: int, cost: float) -> WorkUnit:
    return WorkUnit(index=index, rect=Rect(0, 0, 1, 1), C=0.0, S=1, Nd=0.0, cost=cost)


@FEW
@given(st.lists(st.floats(0.0, 9.0), min_size=1, max_size=12), st.lists(st.tuples(st.integers(0, 11),
       st.sampled_from(list(UnitStatus)), st.booleans(), st.floats(0.0, 20.0)), max_size=40), st.floats(0.0, 20.0))
def test_the_jobs_indexes_follow_its_units(costs, moves, now: float) -> None:
    job = Job(m.JobInfo(job_id="j", scene_url="http://s/s", scene_hash="0" * 64, width=1, height=1, spp=1,
                        depth=1, level="off", ranges={}), {}, order=0)
    for i, c in enumerate(costs):
        job.add(UnitState(spec(i, c)))
    for index, status, fails, deadline in moves:
        unit = job.units.get(index)
        if unit is None:
            continue
        if fails:
            unit.failed_on.add("x")  # as the auction fails a unit: while it is awarded, never open
            if unit.status in (UnitStatus.PENDING, UnitStatus.ANNOUNCED):
                job.moved(index, unit.status, UnitStatus.AWARDED)
                unit.status = UnitStatus.AWARDED
        job.moved(index, unit.status, status)
        unit.status = status
        if status == UnitStatus.AWARDED:
            unit.attempts += 1
            job.set_deadline(unit, deadline)
        else:
            unit.deadline = math.inf
    opened = [u for u in job.units.values() if u.status in (UnitStatus.PENDING, UnitStatus.ANNOUNCED)]
    assert job.open_order == sorted((-u.spec.work, u.spec.index) for u in opened)
    assert job.open_costs == [-c for c, _ in job.open_order]
    assert job.open_failed == {u.spec.index for u in opened if u.failed_on}
    awarded = [u for u in job.units.values() if u.status == UnitStatus.AWARDED]
    assert job.next_due() == min((u.deadline for u in awarded if math.isfinite(u.deadline)), default=None)
    late = sorted(u.spec.index for u in awarded if now > u.deadline)
    assert [u.spec.index for u in job.pop_late(now)] == late


# --- the offers, against those read off the whole projection ------------------------------------------------


def whole_offers(a: au.Auction, job, agents, queueing: bool, now: float):
    """The offers as read off the whole projection, refined in the end game (every pending unit tried on
    every free agent)."""
    rates = a._rates(job)
    usable = rates.keys()
    units = [au.ProjectedUnit(u.spec.index, u.spec.work, machine._excluded(u, usable))
             for u in job.having(UnitStatus.PENDING, UnitStatus.ANNOUNCED)]
    plan_agents = [au.PlanAgent(n, a._available(a._agents[n], now), r) for n, r in rates.items()]
    plan = earliest_finish(units, plan_agents)
    if a.config.refine_moves and len(units) <= a.config.refine_below * max(1, len(plan_agents)):
        plan = plain_refine(plan, units, plan_agents, a.config.refine_moves)
    pending = sorted(job.having(UnitStatus.PENDING), key=lambda u: (-u.spec.work, u.spec.index))
    free = {x.name for x in agents}
    offered, room = {}, {}
    for agent in agents:
        mine = tuple(u.spec.index for u in pending if worth(a, agent.name, u, plan, rates, now, free, usable))
        if mine:
            offered[agent.name], room[agent.name] = mine, a._room(agent, queueing, job)
    return {n: machine._own_first(units, n, plan, room[n])[:min(a.config.max_cfp_units,
                                                                max(len(offered), room[n]))]
            for n, units in offered.items()}, room


def worth(a, name, unit, plan, rates, now, free, usable) -> bool:
    place = plan.get(unit.spec.index)
    if place is None or name in machine._excluded(unit, usable):
        return False
    if place.agent == name:
        return True
    return place.agent in free and place.start <= now and \
        rates[name] * unit.spec.work <= (place.finish - now) * (1 + a.config.finish_tolerance) + 1e-9


@pytest.fixture
def offers_checked(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Every call of the auction's offers checked against `whole_offers`; the calls counted."""
    lazy, calls = au.Auction._offers, []

    def checked(self, job, agents, queueing, now):
        got = lazy(self, job, agents, queueing, now)
        assert got == whole_offers(self, job, agents, queueing, now)
        calls.append(len(agents))
        return got

    monkeypatch.setattr(au.Auction, "_offers", checked)
    return calls


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                 HealthCheck.function_scoped_fixture])
@given(st.lists(st.floats(0.2, 12.0), min_size=1, max_size=24),
       st.lists(st.sampled_from([0.5, 1.0, 1.5, 1.5, 2.0]), min_size=1, max_size=9),
       st.booleans(), st.integers(1, 4), st.integers(0, 3))
def test_a_simulated_farms_offers_are_those_of_the_whole_projection(offers_checked, costs, speeds, passes: bool,
                                                                    slots: int, seed: int) -> None:
    simulate(costs, speeds, config=au.Config(slots=slots), seed=seed, passes=passes, jitter=0.3)
    assert offers_checked


def test_offers_with_excluded_agents_one_unit_and_equal_rates(offers_checked) -> None:
    """Units that failed on agents (excluded from them while another may take them), and agents of one
    speed: the offers are still those of the whole projection."""
    info = m.JobInfo(job_id="j", scene_url="http://s/s", scene_hash="0" * 64, width=1, height=1, spp=1, depth=1,
                     level="off", ranges={})
    a = au.Auction(au.Config(slots=2), rng=random.Random(5))
    submit(a, info, [spec(i, c) for i, c in enumerate([4.0, 3.0, 3.0, 1.0, 1.0, 0.5])],
           failures=[(0, "b", "oom"), (1, "a", "oom"), (1, "b", "oom")])
    for name in ("a", "b", "c"):
        register(a, name, 0.0, speed=1.0)
    out = tick(a, 0.0)
    called = {s.to: [u.index for u in s.message.units] for s in out
              if isinstance(s, au.SendToAgent) and isinstance(s.message, m.CallForProposal)}
    assert 0 not in called.get("b", []) and 1 not in called.get("a", []) + called.get("b", [])
    one = au.Auction(au.Config(slots=2), rng=random.Random(5))  # one unit
    submit(one, dataclasses.replace(info, job_id="k"), [spec(0, 2.0)])
    register(one, "a", 0.0)
    assert [s.to for s in tick(one, 0.0) if isinstance(s, au.SendToAgent)] == ["a"]
    assert offers_checked


def test_no_agents_no_offers(offers_checked) -> None:
    a = au.Auction(au.Config(), rng=random.Random(1))
    info = m.JobInfo(job_id="j", scene_url="http://s/s", scene_hash="0" * 64, width=1, height=1, spp=1, depth=1,
                     level="off", ranges={})
    submit(a, info, [spec(0, 1.0)])
    assert tick(a, 0.0) == [] and a.projection("j", 0.0) == {} and offers_checked == []


# --- the agents the ticks watch -----------------------------------------------------------------------------


def test_next_deadline_is_the_earliest_of_everything_due(monkeypatch: pytest.MonkeyPatch) -> None:
    """In a farm that loses, silences and forgets agents, next_deadline is the earliest time due, as read
    off every round, agent and award."""
    lazy = au.Auction.next_deadline

    def checked(self):
        got = lazy(self)
        c = self.config
        times = [r.deadline for r in self._rounds.values()]
        times += [x.last_seen + (c.forget_lost_s if x.lost else c.heartbeat_timeout_s) for x in self._agents.values()]
        times += [x.silent_until for x in self._agents.values() if x.silent_until is not None]
        times += [u.deadline for j in self._running() for u in j.having(UnitStatus.AWARDED)]
        assert got == min((t for t in times if math.isfinite(t)), default=None)
        return got

    monkeypatch.setattr(au.Auction, "next_deadline", checked)
    info = m.JobInfo(job_id="j", scene_url="http://s/s", scene_hash="0" * 64, width=1, height=1, spp=1, depth=1,
                     level="off", ranges={})
    a = au.Auction(au.Config(forget_lost_s=40.0), rng=random.Random(2))
    submit(a, info, [spec(i, 1.0) for i in range(3)])
    for name in ("a", "b", "c"):
        register(a, name, 0.0)
    a.next_deadline()
    tick(a, 0.0)  # calls for proposals: nobody answers
    for now in (1.0, 2.5, 5.0, 9.0, 20.0, 30.0, 45.0, 70.0):
        if now < 40.0:
            message(a, "a", m.Heartbeat(conversation="h", busy=()), now)
        tick(a, now)
        a.next_deadline()
    assert list(a._agents) == ["a"] and a._agents["a"].lost  # b and c forgotten, a lost (since 30)
    assert a.next_deadline() == 70.0


def test_a_larger_farm_in_passes_offers_as_the_whole_projection(offers_checked) -> None:
    """Mixed speeds, some agents far behind (late), the list schedule read lazily over hundreds of units."""
    rng = random.Random(4)
    costs = [rng.lognormvariate(0.0, 0.5) * 20 for _ in range(60)]
    simulate(costs, [1.5, 0.5, 1.25, 0.75] * 6, seed=4, passes=True, jitter=0.5, delivery=0.013)
    assert len(offers_checked) > 100
