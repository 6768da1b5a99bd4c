"""planning.progressive: the progressive job's decisions, stimulus by stimulus (no rendering)."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from planning.progressive import (
    BUDGET,
    FIRST_PASSES,
    NOISE,
    TIME,
    Finish,
    Goal,
    Idle,
    PassDone,
    PassLanded,
    PassOrder,
    Progressive,
    RenderRound,
    Stop,
    Withdraw,
    budget_passes,
    describe,
)


def done(machine: Progressive, order: PassOrder, relmse_per_sample, seconds_per_spp, elapsed, workers=1):
    """Report one order as merged: the unit's relMSE is its per-sample variance over its spp."""
    spp = machine.units[order.unit].spp + order.spp
    u = order.unit
    return machine.handle(PassDone(u, order.pass_index, spp, spp * seconds_per_spp[u], relmse_per_sample[u] / spp,
                                   elapsed, workers))


def run_round(machine: Progressive, orders, relmse_per_sample, seconds_per_spp, elapsed, workers=1):
    """Report every order as done, in order; the instructions the last one led to."""
    out = []
    for order in orders:
        out = done(machine, order, relmse_per_sample, seconds_per_spp, elapsed, workers)
    return out


def test_first_round_is_the_first_passes_of_every_unit():
    machine = Progressive(Goal(NOISE, 256, noise=0.05), [100, 200])
    [first] = machine.start()
    assert first.orders == tuple(PassOrder(u, k, 4) for k in range(FIRST_PASSES) for u in (0, 1))
    # a cap below the first passes' samples: as many passes of one sample as it allows
    [small] = Progressive(Goal(NOISE, 2, noise=0.05), [10]).start()
    assert small.orders == (PassOrder(0, 0, 1), PassOrder(0, 1, 1))


def test_noise_goal_gives_each_unit_what_it_lacks_at_most_doubling_and_stops_when_all_are_under():
    machine = Progressive(Goal(NOISE, 1024, noise=0.1), [100, 100, 100])
    [first] = machine.start()
    # per-sample relative variance: 1 (needs 100 spp), 4 (400 spp), 0 (a black unit: met at once); the
    # first passes gave each 4 x 8 spp
    v, cost = [1.0, 4.0, 0.0], [0.01] * 3
    [second] = run_round(machine, first.orders, v, cost, 1.0)
    assert isinstance(second, RenderRound)
    assert {o.unit: o.spp for o in second.orders} == {0: 32, 1: 32}  # they lack 68 and 368: at most doubling
    assert {o.pass_index for o in second.orders} == {FIRST_PASSES}
    [third] = run_round(machine, second.orders, v, cost, 2.0)
    assert {o.unit: o.spp for o in third.orders} == {0: 36, 1: 64}  # unit 0: exactly what it lacks
    instructions = third
    elapsed = 3.0
    while isinstance(instructions, RenderRound):
        [instructions] = run_round(machine, instructions.orders, v, cost, elapsed)
        elapsed += 1
    assert isinstance(instructions, Finish)
    assert instructions.units == {0: "met", 1: "met", 2: "met"}
    assert all(math.sqrt(u.relmse) <= 0.1 for u in machine.units)
    assert instructions.reason == "3 of 3 units under relative error 0.1"
    assert machine.handle(Idle(4)) == []  # finished: nothing more


def test_noise_goal_stops_at_the_cap_and_says_which_units():
    machine = Progressive(Goal(NOISE, 64, noise=0.01), [10, 10])
    instructions = machine.start()[0]
    for step in range(20):
        [instructions] = run_round(machine, instructions.orders, [1.0, 0.001], [0.01, 0.01], step)
        if isinstance(instructions, Finish):
            break
    assert instructions.units == {0: "cap", 1: "met"}
    assert machine.units[0].spp == 64
    assert instructions.reason == "1 of 2 units under relative error 0.01, the other 1 at the cap of 64 spp"


def test_time_goal_places_samples_by_neyman_and_never_below_what_a_unit_has():
    machine = Progressive(Goal(TIME, 4096, seconds=10.0), [100, 100, 400])
    first = machine.start()[0]
    # unit 1 is 4x as noisy as unit 0; unit 2 has 4x the area and costs 4x per spp (seconds per spp)
    v, cost = [1.0, 4.0, 1.0], [0.001, 0.001, 0.004]
    [second] = run_round(machine, first.orders, v, cost, 1.0)
    spent = sum(o.spp * cost[o.unit] for o in second.orders)
    assert spent == pytest.approx(1.0, rel=0.05)  # a round as long as the time spent so far
    totals = {u: machine.units[u].spp + sum(o.spp for o in second.orders if o.unit == u) for u in range(3)}
    # n_u proportional to sqrt(a_u v_u / k_u): units 1 and 0 as 2 : 1, unit 2 as unit 0
    assert totals[1] / totals[0] == pytest.approx(2.0, rel=0.05)
    assert totals[2] / totals[0] == pytest.approx(1.0, rel=0.05)


def test_time_goal_ends_when_the_time_is_spent_or_every_unit_is_capped():
    machine = Progressive(Goal(TIME, 4096, seconds=2.0), [10])
    first = machine.start()[0]
    [done] = run_round(machine, first.orders, [1.0], [0.001], 2.5)
    assert isinstance(done, Finish) and done.reason == "the 2 s of rendering are spent (2.5 s)"
    capped = Progressive(Goal(TIME, 8, seconds=100.0), [10])
    orders = capped.start()[0].orders
    [done] = run_round(capped, orders, [1.0], [0.001], 0.1)
    assert isinstance(done, RenderRound) and done.orders == (PassOrder(0, 4, 4),)
    [done] = run_round(capped, done.orders, [1.0], [0.001], 0.2)
    assert isinstance(done, Finish) and done.units == {0: "cap"}
    assert done.reason == "no unit has noise left to lower under the cap of 8 spp (0.2 s)"
    noiseless = Progressive(Goal(TIME, 64, seconds=100.0), [10])
    [done] = run_round(noiseless, noiseless.start()[0].orders, [0.0], [0.001], 0.1)
    assert isinstance(done, Finish)


@pytest.mark.parametrize(("goal", "message"), [
    (dict(kind=NOISE, spp_cap=8), "positive relative error"),
    (dict(kind=NOISE, spp_cap=8, noise=math.inf), "positive relative error"),
    (dict(kind=TIME, spp_cap=8, seconds=0.0), "positive number of seconds"),
    (dict(kind="quality", spp_cap=8), "goal 'quality'"),
    (dict(kind=TIME, spp_cap=0, seconds=1.0), "spp cap 0"),
])
def test_a_goal_out_of_range_is_refused(goal, message):
    with pytest.raises(ValueError, match=message):
        Goal(**goal)


@settings(max_examples=60, deadline=None)
@given(areas=st.lists(st.integers(1, 10_000), min_size=1, max_size=12),
       variance=st.lists(st.floats(0.0, 100.0), min_size=12, max_size=12),
       cost=st.lists(st.floats(1e-6, 1.0), min_size=12, max_size=12),
       cap=st.integers(1, 2048), seconds=st.floats(0.1, 50.0))
def test_time_rounds_never_pass_the_cap_and_each_pass_is_new(areas, variance, cost, cap, seconds):
    machine = Progressive(Goal(TIME, cap, seconds=seconds), areas)
    instructions, elapsed, seen = machine.start()[0], 0.0, set()
    for _ in range(40):
        assert all(o.spp >= 1 and (o.unit, o.pass_index) not in seen for o in instructions.orders)
        seen |= {(o.unit, o.pass_index) for o in instructions.orders}
        elapsed += sum(o.spp * cost[o.unit] for o in instructions.orders)
        [instructions] = run_round(machine, instructions.orders, variance, cost, elapsed)
        assert all(u.spp <= cap for u in machine.units)
        if isinstance(instructions, Finish):
            break
    assert isinstance(instructions, Finish)


def test_a_round_decides_only_when_every_unit_has_what_it_asked_and_idle_workers_take_extra_passes():
    """The tail: the round's last pass is slow; an idle worker renders the same unit's next pass, and the
    round goes on as soon as that one lands. The slow pass is withdrawn when the extra one lands, so the
    unit gets the samples it asked for, not twice them."""
    machine = Progressive(Goal(NOISE, 1024, noise=0.01), [100, 100])
    orders = machine.start()[0].orders
    slow, rest = orders[-1], orders[:-1]
    assert run_round(machine, rest, [1.0, 1.0], [0.01, 0.01], 1.0) == []  # unit 1 still waits for one pass
    assert machine.handle(Idle(0)) == []
    [extra] = machine.handle(Idle(3))
    assert extra.orders == (PassOrder(slow.unit, FIRST_PASSES, slow.spp),)  # one unit waits: one extra pass
    assert machine.handle(Idle(3)) == []  # at most two passes of a unit out at once
    assert machine.handle(PassLanded(slow.unit, extra.orders[0].pass_index)) == [Withdraw((slow,))]
    assert machine.handle(Idle(3)) == []  # it waits only for the merge now: no extra pass
    [next_round] = done(machine, extra.orders[0], [1.0, 1.0], [0.01, 0.01], 2.0)
    assert isinstance(next_round, RenderRound)
    assert machine.handle(PassLanded(slow.unit, slow.pass_index)) == []  # withdrawn: lands on nothing
    assert machine.units[slow.unit].credited == FIRST_PASSES * slow.spp


def test_a_pass_that_lands_short_of_its_round_withdraws_nothing():
    """A budget of 16 in passes 1, 7, 4, 2, 2: landings short of it withdraw nothing; an extra pass for the
    last one, landing first, withdraws that one."""
    machine = Progressive(Goal(BUDGET, 16), [10])
    orders = machine.start()[0].orders
    assert [o.spp for o in orders] == [1, 7, 4, 2, 2]
    assert [machine.handle(PassLanded(0, o.pass_index)) for o in orders[:-1]] == [[]] * 4
    [extra] = machine.handle(Idle(2))
    assert extra.orders == (PassOrder(0, 5, 2),)
    assert machine.handle(PassLanded(0, 5)) == [Withdraw((orders[-1],))]
    assert sum(machine.units[0].landed.values()) == 16


@settings(max_examples=60, deadline=None)
@given(st.sampled_from([BUDGET, NOISE]), st.integers(4, 40),
       st.lists(st.tuples(st.sampled_from(["land", "merge", "idle"]), st.integers(0, 50)), max_size=120))
def test_landed_samples_never_pass_the_cap_whatever_lands_first(kind, cap, events):
    """Any interleaving of landings, merges and idle workers' extra passes (a farm's tail): no unit ever
    holds more samples, landed or merged, than its budget or the spp cap."""
    machine = Progressive(Goal(kind, cap, noise=0.01 if kind == NOISE else None), [50, 80])
    for step in machine.start():
        assert isinstance(step, RenderRound)
    for what, pick in events:
        if machine.finished is not None:
            break
        units = machine.units
        if what == "idle":
            machine.handle(Idle(1 + pick % 3))
        elif what == "land":
            out = [(u, k) for u, unit in enumerate(units) for k in sorted(unit.out)]
            if out:
                machine.handle(PassLanded(*out[pick % len(out)]))
        else:
            landed = [(u, k) for u, unit in enumerate(units) for k in sorted(unit.landed)]
            if landed:
                u, k = landed[pick % len(landed)]
                spp = units[u].credited + units[u].landed[k]
                machine.handle(PassDone(u, k, spp, spp * 0.01, 1.0 / spp, 1.0, 2))
        for unit in machine.units:
            assert unit.credited + sum(unit.landed.values()) <= cap, (unit, cap)
def test_a_pass_rendered_with_fewer_samples_than_ordered_still_ends_its_round():
    """A stratified sampler renders its own count (a square): the round counts the passes, not the spp."""
    machine = Progressive(Goal(NOISE, 256, noise=0.5), [10])
    orders = machine.start()[0].orders
    out = []
    for order in orders:
        out = machine.handle(PassDone(0, order.pass_index, machine.units[0].spp + order.spp - 1, 1.0, 0.01, 1.0))
    assert isinstance(out[0], Finish)


def test_time_rounds_are_as_long_as_the_time_spent_times_the_workers():
    machine = Progressive(Goal(TIME, 100_000, seconds=100.0), [100])
    first = machine.start()[0].orders
    [second] = run_round(machine, first, [1.0], [0.01], 2.0, workers=8)
    assert sum(o.spp for o in second.orders) * 0.01 == pytest.approx(16.0, rel=0.02)


def test_a_budget_job_renders_each_units_own_samples_in_passes_and_ends_when_all_have_them():
    machine = Progressive(Goal(BUDGET, 64), [10, 10, 10], budgets=[64, 10, 3])
    [first] = machine.start()
    by_unit = {u: [o.spp for o in first.orders if o.unit == u] for u in range(3)}
    assert by_unit == {0: [2, 31, 15, 8, 8], 1: [1, 4, 2, 1, 2], 2: [1, 1, 1]}
    # a small first pass (1/32 of the budget: the whole image shows early), then the rest halving
    assert [budget_passes(b) for b in (0, 1, 2, 16, 17, 1024)] == [
        [], [1], [1, 1], [1, 7, 4, 2, 2], [1, 8, 4, 2, 2], [32, 496, 248, 124, 124]]  # 0: a resumed unit's none left
    out = run_round(machine, first.orders, [1.0] * 3, [0.01] * 3, 2.0)
    assert out == [Finish("every unit has its samples (2.0 s)", {0: "budget", 1: "budget", 2: "budget"})]
    with pytest.raises(ValueError, match="budgets"):
        Progressive(Goal(BUDGET, 64), [10], budgets=[0])


def test_a_budget_pass_holds_at_least_the_samples_asked_where_its_unit_has_them():
    """A farm's passes hold at least `pass_samples` samples (master.auction Config.pass_samples): a small
    unit renders whole in one pass, a large one halves down to that size, the budget always met."""
    assert budget_passes(64, 5, 8) == [8, 28, 14, 14] and budget_passes(64, 5, 16) == [16, 24, 24]
    assert budget_passes(11, 5, 65) == [11] and budget_passes(16, 5, 1) == budget_passes(16)
    # cbox 512 px at level VB on a farm: 90 px units of 11 spp (89 k samples) are one pass each; a
    # 32768-pixel unit of 64 spp has passes of at least 8 spp (2^18 samples); a large unit keeps its five.
    machine = Progressive(Goal(BUDGET, 64), [8100, 32768, 600 * 600], budgets=[11, 64, 64], pass_samples=1 << 18)
    [first] = machine.start()
    by_unit = {u: [o.spp for o in first.orders if o.unit == u] for u in range(3)}
    assert by_unit == {0: [11], 1: [8, 28, 14, 14], 2: [2, 31, 15, 8, 8]}
    out = run_round(machine, first.orders, [1.0] * 3, [0.01] * 3, 2.0)
    assert out == [Finish("every unit has its samples (2.0 s)", {0: "budget", 1: "budget", 2: "budget"})]


def test_in_two_parts_a_budget_renders_in_two_passes_a_unit_as_one_process_does():
    """No agents' tail to shorten in one process: the fewest passes between which the noise is estimated, the
    first small (a Ctrl-C keeps the image from then on)."""
    assert [budget_passes(b, 2) for b in (1, 2, 16, 17, 64)] == [[1], [1, 1], [1, 15], [1, 16], [2, 62]]
    machine = Progressive(Goal(BUDGET, 64), [10, 10], budgets=[64, 5], budget_parts=2)
    [first] = machine.start()
    assert [(o.unit, o.spp) for o in first.orders] == [(0, 2), (1, 1), (0, 62), (1, 4)]  # pass by pass
    out = run_round(machine, first.orders, [1.0] * 2, [0.01] * 2, 1.0)
    assert out == [Finish("every unit has its samples (1.0 s)", {0: "budget", 1: "budget"})]


def test_a_reports_progressive_part_reads_as_one_line_for_each_goal():
    part = {"spp_cap": 64, "noise": None, "time": None, "reason": "every unit has its samples (1.0 s)", "passes": 9}
    assert describe({**part, "goal": BUDGET}) == \
        "passes: each unit's own samples; stopped: every unit has its samples (1.0 s) (9 passes)"
    assert describe({**part, "goal": NOISE, "noise": 0.05, "reason": "2 of 2 units under relative error 0.05"}) == \
        "passes: relative error 0.05 a unit, at most 64 spp; stopped: 2 of 2 units under relative error 0.05 (9 passes)"
    assert describe({**part, "goal": TIME, "time": 3.0, "reason": None}).startswith(
        "passes: 3 s of rendering, at most 64 spp; stopped: not yet")
    assert describe({**part, "goal": BUDGET, "passes": 1}).endswith("(1 pass)")  # not "1 passes"


def test_a_time_goal_with_too_little_left_for_a_sample_says_its_time_is_spent():
    """The last round's time buys no unit one more sample: the time is what ends the job, not the noise
    (a loaded machine reached 4 s less a few ms and read "no unit has noise left")."""
    machine = Progressive(Goal(TIME, 100000, seconds=4.0), [100, 100])
    [first] = machine.start()
    [end] = run_round(machine, first.orders, [1.0, 1.0], [1.0, 1.0], 4.0 - 1e-4)
    assert isinstance(end, Finish) and end.reason.startswith("the 4 s of rendering are spent"), end
    quiet = Progressive(Goal(TIME, 100000, seconds=4.0), [100])
    [first] = quiet.start()
    [end] = run_round(quiet, first.orders, [0.0], [1.0], 1.0)  # a black unit: nothing to lower
    assert end.reason.startswith("no unit has noise left"), end


def test_ctrl_c_ends_a_job_on_its_passes_once_every_unit_has_one_and_only_then():
    """Stop before a unit has a pass keeps nothing; after, the job ends there: a unit under the error is met,
    the others stopped, and nothing more is decided."""
    machine = Progressive(Goal(NOISE, 1024, noise=0.05), [10, 10, 10])
    orders = machine.start()[0].orders
    firsts = [next(o for o in orders if o.unit == u) for u in (0, 1)]
    run_round(machine, firsts, [0.0001, 1.0, 1.0], [0.01] * 3, 1.0)
    assert machine.handle(Stop(1.5)) == [] and machine.finished is None  # unit 2 has no pass
    done(machine, next(o for o in orders if o.unit == 2), [0.0001, 1.0, 1.0], [0.01] * 3, 2.0)
    [finish] = machine.handle(Stop(2.3))
    assert finish.units == {0: "met", 1: "stopped", 2: "stopped"}
    assert finish.reason == f"Ctrl-C after 2.3 s, with {orders[0].spp} spp a unit"  # one first pass each
    assert machine.handle(Idle(2)) == [] and machine.handle(Stop(3.0)) == []
