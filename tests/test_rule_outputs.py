"""From crisp outputs to render parameters: the documented mapping and its clamps."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from core.model.levels import RULE_LEVELS as LEVELS
from core.rules.outputs import LS_MAX, masyro_render_params, to_render_params
from fuzzy import load_rulebase

REPO = Path(__file__).resolve().parent.parent


def test_op_values_are_the_label_peaks_of_the_files_own_op_sets():
    rulebase = load_rulebase(REPO / "rules" / "pathtracing.xml")
    assert [rulebase.op_value(level) for level in LEVELS] == [0.0, 1.0, 2.0, 3.0, 4.0]
    masyro = load_rulebase(REPO / "tests" / "data" / "rules" / "masyro_fixed.xml")  # Op universe 0..30
    assert [masyro.op_value(level) for level in LEVELS] == [2.5, 10.0, 15.0, 20.0, 27.5]
    with pytest.raises(ValueError, match="'XL'"):
        rulebase.op_value("XL")


def test_masyro_mapping_floors_scales_and_keeps_the_users_value_where_no_rule_fired():
    outputs = {"Rl": np.array([9.0, 4.9, np.nan]), "Ls": np.array([8.5, 1.2, np.nan]),
               "Ibs": np.array([3.9, 0.0, np.nan])}
    depth, spp, band = masyro_render_params(outputs, 8, 100, {"Rl": 9.0, "Ls": 13.0})
    # int(max(0.5, floor(Rl)/9) * 8): 8, int(4/9*8)=3 -> 0.5 floor wins: 4; NaN keeps 8
    assert depth.tolist() == [8, 4, 8]
    assert spp.tolist() == [61, 50, 100]  # int(8/13*100)=61, int(0.5*100)=50, kept
    assert band.tolist() == [3, 0, 0]


def test_factors_weight_the_users_values():
    outputs = {"Rl": np.array([1.0, 0.5, 0.2]), "Ls": np.array([1.0, 0.6, 0.25]), "Ibs": np.array([4.0, 5.4, 12.6])}
    depth, spp, band = to_render_params(outputs, user_depth=8, user_spp=64)
    assert depth.tolist() == [8, 4, 2]
    assert spp.tolist() == [64, 38, 16]
    assert band.tolist() == [4, 5, 13]


def test_clamps_depth_at_one_and_the_users_depth_spp_at_ls_max():
    outputs = {"Rl": np.array([0.0, 1.2]), "Ls": np.array([0.01, 1.2]), "Ibs": np.array([-3.0, 0.4])}
    depth, spp, band = to_render_params(outputs, user_depth=3, user_spp=10)
    assert depth.tolist() == [1, 3]  # never below 1, never above the user's depth
    assert spp.tolist() == [1, 12]  # samples may rise above the user's: the rules move them to the noise
    assert band.tolist() == [0, 0]
    depth, spp, _ = to_render_params(outputs, user_depth=0, user_spp=0)
    assert depth.tolist() == [1, 1] and spp.tolist() == [1, 1]


def test_samples_are_capped_at_ls_max_times_the_users():
    outputs = {"Rl": np.array([1.0, 1.0]), "Ls": np.array([LS_MAX, 50.0]), "Ibs": np.array([2.0, 2.0])}
    _, spp, _ = to_render_params(outputs, user_depth=8, user_spp=64)
    assert LS_MAX == 3.0 and spp.tolist() == [192, 192]


def test_bad_values_are_refused():
    ok = {"Rl": np.array([0.5]), "Ls": np.array([0.5]), "Ibs": np.array([2.0])}
    with pytest.raises(ValueError, match=">= 0"):
        to_render_params(ok, user_depth=-1, user_spp=4)
    with pytest.raises(ValueError, match="Ls"):
        to_render_params({**ok, "Ls": np.array([np.nan])}, user_depth=4, user_spp=4)
