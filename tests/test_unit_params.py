"""core.rules.unit_params: unit features + level -> depth, spp, band per unit, with the real rule base."""

from __future__ import annotations

import json

import numpy as np
import pytest
from fuzzy_helpers import DATA, RULES

from core.data import default_rules_path
from core.model.geometry import Rect
from core.model.units import SPP_MAX, WorkUnit
from core.rules.outputs import LS_MAX
from core.rules.unit_params import DEPTH_STEPS, Planner, RenderParams, quantise_depth_factor
from fuzzy import RuleFileError

FEATURES = {"C": np.array([1.0, 5.0, 9.0, 5.0]), "S": np.array([100, 400, 900, 400.0]),
            "Nd": np.array([0.0, 2.0, 8.0, 0.5])}


@pytest.fixture(scope="module")
def planner() -> Planner:
    return Planner()


def test_default_rules_are_the_repository_file():
    assert default_rules_path() == RULES.resolve()


def test_level_off_keeps_the_users_values(planner):
    plans = planner.plan(FEATURES, "off", user_depth=6, user_spp=32, min_band=2)
    assert plans == [RenderParams(6, 32, 2)] * 4
    assert planner.plan(FEATURES, "off", user_depth=6, user_spp=32, min_band=0) == [RenderParams(6, 32, 0)] * 4


def test_plans_are_bounded_and_banded(planner):
    for level in ("VS", "S", "N", "B", "VB"):
        for p in planner.plan(FEATURES, level, user_depth=8, user_spp=32, min_band=3):
            assert p.depth in (8, 6, 4)  # quantised to 1, 3/4, 1/2 of the user's depth
            assert 1 <= p.spp <= LS_MAX * 32 and p.band >= 3
            assert set(p.outputs) == {"Rl", "Ls", "Ibs"}


def test_a_job_at_the_most_spp_plans_units_its_messages_carry(planner):
    """The rules may raise a unit's spp to LS_MAX x the user's; at the job's own limit (SPP_MAX) that would
    be a count no award or tile may carry, so the unit stays at SPP_MAX, the others below it."""
    for level in ("VS", "S"):
        spp = [p.spp for p in planner.plan(FEATURES, level, user_depth=8, user_spp=SPP_MAX)]
        assert max(spp) == SPP_MAX and min(spp) < SPP_MAX, (level, spp)
        WorkUnit(index=0, rect=Rect(0, 0, 4, 4), C=1.0, S=16, Nd=0.0, cost=1.0, spp=max(spp))


def test_depth_is_quantised_to_few_steps():
    assert DEPTH_STEPS == (1.0, 0.75, 0.5)
    rl = np.array([1.2, 1.0, 0.875, 0.8, 0.7, 0.62, 0.2, 0.0])
    assert quantise_depth_factor(rl).tolist() == [1.0, 1.0, 1.0, 0.75, 0.75, 0.5, 0.5, 0.5]


def test_higher_level_renders_less(planner):
    total = {lv: sum(p.spp * p.depth for p in planner.plan(FEATURES, lv, 8, 64)) for lv in ("VS", "S", "B", "VB")}
    assert total["VS"] > total["S"] > total["B"] > total["VB"]


def test_complex_unit_gets_more_samples_and_wider_band_where_neighbours_differ(planner):
    """C is cost per sample, which predicts relative noise: the rules move samples there."""
    for level in ("VS", "S", "N", "B"):
        p = planner.plan(FEATURES, level, 8, 64)
        assert p[2].spp > p[0].spp, level
        assert p[2].band > p[0].band, level


def test_simple_units_pay_for_the_complex_ones_at_level_vs(planner):
    p = planner.plan(FEATURES, "VS", 8, 64)
    assert p[0].spp < 64 < p[2].spp  # the budget moves, the user's depth stays
    assert {x.depth for x in p} == {8}


def test_explicit_ranges_change_the_labels(planner):
    same = planner.plan(FEATURES, "B", 8, 64)
    wide = planner.plan(FEATURES, "B", 8, 64, ranges={"C": (0, 100), "S": (0, 1000), "Nd": (0, 100)})
    assert [p.outputs for p in same] != [p.outputs for p in wide]
    assert same == planner.plan(FEATURES, "B", 8, 64, ranges={"C": (1, 9), "S": (100, 900), "Nd": (0, 8)})


def test_every_unit_alike_is_fine(planner):
    alike = {k: np.full(5, 3.0) for k in ("C", "S", "Nd")}
    plans = planner.plan(alike, "S", 8, 64)
    assert len(plans) == 5 and all(p == plans[0] for p in plans)
    assert plans[0].outputs["Ibs"] > 0 and plans[0].spp >= 1


def test_min_band_and_to_dict_is_json():
    planner = Planner(min_band=5)
    plans = planner.plan(FEATURES, "VB", 8, 64)
    assert min(p.band for p in plans) >= 5
    assert min(p.band for p in planner.plan(FEATURES, "VB", 8, 64, min_band=7)) >= 7  # the larger floor
    assert json.loads(json.dumps(plans[0].to_dict()))["depth"] == plans[0].depth


def test_bad_calls(planner):
    with pytest.raises(ValueError, match="lack Nd"):
        planner.plan({"C": [1.0], "S": [1.0]}, "S", 8, 64)
    with pytest.raises(ValueError, match="unknown optimisation level"):
        planner.plan(FEATURES, "max", 8, 64)
    assert planner.plan({k: [] for k in ("C", "S", "Nd")}, "S", 8, 64) == []
    with pytest.raises(ValueError, match="needs inputs"):
        Planner(DATA / "masyro_dialect.xml")
    with pytest.raises(RuleFileError):
        Planner(DATA / "invalid" / "billion_laughs.xml")
