"""bench/rules/pathtracing-retune.xml, the retune on trial: it changes levels N, B and VB's samples only,
keeps the shipped file's expertise tests, and spends by C alone at those levels, in the levels' order."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from fuzzy_helpers import REPO, RULES

# The shipped file's expertise, run here on the retune (pytest runs imported tests with this module's
# `engine`). Not imported: its rule count and the published rules' labels, which the retune changes at
# N, B and VB on purpose.
from test_fuzzy_rulebase import (  # noqa: F401
    RANGES,
    test_centre_of_sums_agrees_in_direction,
    test_every_label_combination_fires_every_output,
    test_higher_complexity_raises_samples_and_never_depth,
    test_higher_optimisation_lowers_samples_and_depth,
    test_neighbour_difference_widens_the_band_and_raises_samples,
    test_no_unit_gets_fewer_samples_at_vs_than_at_s,
    test_random_units_never_fall_back_to_the_default,
    test_vs_moves_samples_above_the_users_value,
)

from fuzzy import Engine, load_rulebase

RETUNE = REPO / "bench" / "rules" / "pathtracing-retune.xml"
GRID = np.linspace(0.0, 1.0, 21)


@pytest.fixture(scope="module")
def engine() -> Engine:
    return Engine(load_rulebase(RETUNE))


@pytest.fixture(scope="module")
def shipped() -> Engine:
    return Engine(load_rulebase(RULES))


def _units(engine: Engine, level: str, nd: np.ndarray = GRID) -> np.ndarray:
    """Every (C, S, Nd) of the grid at `level`'s crisp Op, as the planner evaluates it."""
    units = np.array(list(itertools.product(GRID, GRID, nd)))
    return np.column_stack([units, np.full(len(units), engine.rulebase.op_value(level))])


@pytest.mark.parametrize("level", ["VS", "S", "N", "B", "VB"])
def test_only_the_samples_of_n_b_and_vb_differ_from_the_shipped_file(engine, shipped, level):
    x = _units(engine, level)
    mine, theirs = engine.evaluate(x, RANGES), shipped.evaluate(x, RANGES)
    np.testing.assert_allclose(mine["Rl"], theirs["Rl"], atol=1e-12)  # depth: R1-R11 as shipped
    np.testing.assert_allclose(mine["Ibs"], theirs["Ibs"], atol=1e-12)
    if level in ("VS", "S"):
        np.testing.assert_allclose(mine["Ls"], theirs["Ls"], atol=1e-12)
    else:
        assert np.abs(mine["Ls"] - theirs["Ls"]).max() > 0.05


@pytest.mark.parametrize("level", ["N", "B", "VB"])
def test_samples_follow_c_alone_with_a_spread_of_a_few_times(engine, level):
    """Away from a strong neighbour difference (where the shipped R25 raises a complex unit's samples),
    a unit's samples do not depend on its size, rise with C, and the most complex units get 3-6x the
    samples of the simplest (the shipped file: about 13x at N)."""
    x = _units(engine, level, nd=np.array([0.0]))
    ls = engine.evaluate(x, RANGES)["Ls"].reshape(len(GRID), len(GRID))  # [C, S]
    assert np.ptp(ls, axis=1).max() < 1e-12, "the unit's size moves its samples"
    by_c = ls[:, 0]
    # Where two C labels mix, the centroid of their consequents' union may dip (up to 0.008 of the
    # user's spp on this grid) before it rises.
    assert np.all(np.diff(by_c) >= -0.01), by_c
    assert 3.0 <= by_c[-1] / by_c[0] <= 6.0, by_c


def test_each_level_spends_no_more_than_the_one_below(engine):
    """S >= N >= B >= VB for every unit of the grid away from a strong neighbour difference, to 0.01 of
    the user's spp (centroids of unions). On a strong boundary the shipped R25 gives a complex unit Ls B
    at every level from S to VB, and that boost moves a lower level's smaller centroid further: there a
    level may spend up to 0.06 of the user's spp more than the one below it (about 4 of 64 spp)."""
    nd = _units(engine, "S")[:, 2]
    ls = {level: engine.evaluate(_units(engine, level), RANGES)["Ls"] for level in ("S", "N", "B", "VB")}
    calm = nd <= 0.5
    for lighter, heavier in itertools.pairwise(("S", "N", "B", "VB")):
        gap = ls[lighter] - ls[heavier]
        assert float(gap[calm].min()) > -0.01, (lighter, heavier)
        assert float(gap.min()) > -0.06, (lighter, heavier)
