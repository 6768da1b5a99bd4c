"""From crisp outputs to render parameters: the documented mapping and its clamps."""

from __future__ import annotations

import numpy as np
import pytest

from fuzzy.render_params import LEVELS, LS_MAX, op_value, to_render_params


def test_op_values_are_the_label_peaks():
    assert [op_value(level) for level in LEVELS] == [0.0, 1.0, 2.0, 3.0, 4.0]
    with pytest.raises(ValueError, match="unknown optimisation level 'XL'"):
        op_value("XL")


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
