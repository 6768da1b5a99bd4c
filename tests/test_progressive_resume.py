"""planning.progressive after a master restart: a machine resumed from what the store keeps of each unit
(`UnitSoFar`) decides as the machine that never stopped, and never reuses a pass index."""

from __future__ import annotations

import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_progressive import done

from planning.progressive import BUDGET, NOISE, TIME, Finish, Goal, Progressive, RenderRound, UnitSoFar

AREAS = [64, 64, 32, 16]
VARIANCE = [0.5, 2.0, 8.0, 0.1]  # relMSE per sample of each unit
COST = [0.01, 0.02, 0.01, 0.005]  # seconds per spp


def so_far(machine: Progressive) -> list[UnitSoFar]:
    """What the store keeps of each unit: merged passes, the passes out, the pass indices used."""
    return [UnitSoFar(u.spp, u.credited, u.passes, u.seconds, u.relmse, dict(u.out), u.next_pass)
            for u in machine.units]


def run(machine: Progressive, first: list, stop: int | None, rng: random.Random, elapsed: float = 1.0):
    """Merge passes, oldest order first, shuffled a little, until the job ends or `stop` merges are done:
    (instructions seen, the orders still out)."""
    out, pending, merges = [], list(first), 0
    while pending and (stop is None or merges < stop):
        order = pending.pop(rng.randrange(min(3, len(pending))))
        step = done(machine, order, VARIANCE, COST, elapsed)
        out += step
        pending += [o for i in step if isinstance(i, RenderRound) for o in i.orders]
        merges += 1
    return out, pending


@settings(max_examples=60, deadline=None)
@given(kind=st.sampled_from([BUDGET, NOISE, TIME]), cut=st.integers(0, 40), seed=st.integers(0, 10**6))
def test_a_resumed_machine_decides_as_the_one_that_never_stopped(kind, cut, seed):
    goal = Goal(kind, 256, noise=0.05 if kind == NOISE else None, seconds=30.0 if kind == TIME else None)
    budgets = [64, 16, 200, 3] if kind == BUDGET else None
    original = Progressive(goal, AREAS, budgets)
    [first] = original.start()
    _, pending = run(original, list(first.orders), cut, random.Random(seed))
    if original.finished is not None:
        return
    resumed = Progressive(goal, AREAS, budgets)
    assert resumed.resume(so_far(original), 1.0) == []  # it waits for the passes out, as the original does
    rest_a, _ = run(original, list(pending), None, random.Random(seed + 1))
    rest_b, _ = run(resumed, list(pending), None, random.Random(seed + 1))
    assert rest_a == rest_b and isinstance(rest_a[-1], Finish)


def test_a_budget_job_lacking_passes_orders_them_with_new_indices():
    goal = Goal(BUDGET, 64)
    machine = Progressive(goal, [16, 16], budgets=[16, 8])
    had = [UnitSoFar(spp=8, credited=8, passes=1, seconds=0.1, out={1: 4}, next_pass=5),
           UnitSoFar()]
    [round_] = machine.resume(had, 2.0)
    by_unit = {u: [(o.pass_index, o.spp) for o in round_.orders if o.unit == u] for u in (0, 1)}
    # 16 - 8 - 4 out; 8: each in budget_passes (a small first, then halving)
    assert by_unit == {0: [(5, 1), (6, 1), (7, 1), (8, 1)], 1: [(0, 1), (1, 3), (2, 2), (3, 1), (4, 1)]}
    assert [u.target for u in machine.units] == [16, 8]


def test_a_noise_job_whose_round_had_ended_decides_at_once_and_a_unit_with_nothing_starts_over():
    goal = Goal(NOISE, 256, noise=0.05)
    machine = Progressive(goal, [16, 16])
    met = UnitSoFar(spp=16, credited=16, passes=4, seconds=0.1, relmse=0.0001, next_pass=4)
    [finish] = machine.resume([met, met], 3.0)
    assert isinstance(finish, Finish) and finish.units == {0: "met", 1: "met"}
    fresh = Progressive(goal, [16, 16])
    [round_] = fresh.resume([met, UnitSoFar()], 3.0)
    assert {o.unit for o in round_.orders} == {1} and len(round_.orders) == 4
    with pytest.raises(ValueError, match="1 units resumed for 2"):
        Progressive(goal, [16, 16]).resume([met], 0.0)
