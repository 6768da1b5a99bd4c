"""Defuzzifiers: hand-computed cases, degenerate sets, and the exact centroid against integration."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fuzzy.defuzzify import centre_of_sums, centroid, numeric_centroid, plan_centroid
from fuzzy.terms import membership

TWO_TRIANGLES = np.array([[0, 1, 1, 2], [1, 2, 2, 3]], dtype=float)
APART = np.array([[0, 2, 2, 4], [6, 8, 8, 10]], dtype=float)


def _both(params, h):
    h = np.atleast_2d(np.asarray(h, dtype=float))
    return centroid(plan_centroid(params), h)[0], centre_of_sums(params, h)[0]


def test_single_full_triangle():
    assert _both(APART, [1, 0]) == pytest.approx((2.0, 2.0), abs=1e-15)


def test_disjoint_sets_hand_computed():
    # triangle area 2 at 2; H clipped at 0.5: area 1.5 at 8 -> 16 / 3.5
    assert _both(APART, [1, 0.5]) == pytest.approx((16 / 3.5, 16 / 3.5), rel=1e-14)


def test_overlapping_sets_hand_computed():
    # union: A on [0, 1.5], 0.5 on [1.5, 2.5], B's falling edge on [2.5, 3]: area 1.5, moment 2.125
    exact, sums = _both(TWO_TRIANGLES, [1, 0.5])
    assert exact == pytest.approx(17 / 12, rel=1e-14)
    # centre of sums: areas 1 and 0.75, centroids 1 and 2
    assert sums == pytest.approx(2.5 / 1.75, rel=1e-14)


def test_symmetric_overlap_is_centred():
    assert _both(TWO_TRIANGLES, [0.3, 0.3]) == pytest.approx((1.5, 1.5), rel=1e-14)


def test_vertical_edges_are_integrated_exactly():
    rects = np.array([[0, 0, 2, 2], [2, 2, 4, 4]], dtype=float)
    assert _both(rects, [0.5, 1]) == pytest.approx((7 / 3, 7 / 3), rel=1e-14)


def test_singleton_set_falls_back_to_its_point():
    params = np.array([[3, 3, 3, 3], [5, 6, 6, 7]], dtype=float)
    assert _both(params, [0.7, 0]) == pytest.approx((3.0, 3.0))
    exact, _ = _both(params, [0.7, 0.2])
    assert exact == pytest.approx(6.0)  # the singleton has no area: only the triangle counts


def test_zero_height_aggregate_is_nan_for_the_engine_to_default():
    exact, sums = _both(APART, [0, 0])
    assert np.isnan(exact) and np.isnan(sums)


def test_degenerate_trapezoid_memberships():
    params = np.array([[1, 1, 3, 4], [1, 2, 3, 3], [2, 2, 2, 2]], dtype=float)
    mu = membership(np.array([0.5, 1.0, 2.0, 3.0, 3.5, 4.0]), params)
    np.testing.assert_allclose(mu[:, 0], [0, 1, 1, 1, 0.5, 0])
    np.testing.assert_allclose(mu[:, 1], [0, 0, 1, 1, 0, 0])
    np.testing.assert_allclose(mu[:, 2], [0, 0, 1, 0, 0, 0])


@st.composite
def sloped_sets(draw, min_width=0.05):
    """1-5 trapezoids on [0, 10] whose edges all have width (no vertical edge inside)."""
    n = draw(st.integers(1, 5))
    rows = []
    for _ in range(n):
        a = draw(st.floats(0, 6))
        w1, w2 = draw(st.floats(min_width, 1.5)), draw(st.floats(min_width, 1.5))
        top = draw(st.floats(0, 1.5))
        rows.append([a, a + w1, a + w1 + top, a + w1 + top + w2])
    # a clip level h makes edge pieces h times narrower: keep them wider than the reference's grid step
    h = draw(st.lists(st.one_of(st.just(0.0), st.floats(1e-2, 1)), min_size=n, max_size=n))
    return np.array(rows), np.array(h)


@settings(max_examples=40, deadline=None)
@given(sloped_sets())
def test_exact_centroid_matches_fine_integration(case):
    params, h = case
    if not h.any():
        return
    exact = centroid(plan_centroid(params), h[None, :])[0]
    assert exact == pytest.approx(numeric_centroid(params, h, 400_001), rel=1e-7)


@st.composite
def any_sets(draw):
    """Trapezoids including every degenerate shape (a=b, c=d, a=b=c=d), on a coarse grid."""
    n = draw(st.integers(1, 5))
    rows = [sorted(draw(st.lists(st.integers(0, 8), min_size=4, max_size=4))) for _ in range(n)]
    h = draw(st.lists(st.sampled_from([0.0, 0.25, 0.5, 1.0, 1e-9]), min_size=n, max_size=n))
    return np.array(rows, dtype=float), np.array(h)


@settings(max_examples=150, deadline=None)
@given(any_sets())
def test_centroid_finite_and_inside_the_hull_for_any_sets(case):
    params, h = case
    for value in _both(params, h):
        if not h.any():
            assert np.isnan(value)
            continue
        assert np.isfinite(value)
        assert params[:, 0].min() - 1e-12 <= value <= params[:, 3].max() + 1e-12


@settings(max_examples=100, deadline=None)
@given(any_sets(), st.floats(0, 1))
def test_one_set_alone_centroid_equals_its_analytic_centroid(case, level):
    # with a single set the union is the set: both defuzzifiers must agree for any clip level
    params, _ = case
    params = params[:1]
    if params[0, 3] == params[0, 0] or level == 0:
        return
    exact, sums = _both(params, [level])
    assert exact == pytest.approx(sums, rel=1e-12)


def test_tiny_activation_keeps_the_shape():
    # a clip level far below rounding of x: the clipped triangle is a flat sliver centred on 1
    params = np.array([[0, 1, 1, 2]], dtype=float)
    assert _both(params, [1e-300]) == pytest.approx((1.0, 1.0), rel=1e-12)


def test_batch_equals_one_by_one():
    rng = np.random.default_rng(3)
    params = np.array([[0, 0, 1, 3], [1, 3, 3, 5], [3, 5, 5, 8], [5, 8, 8, 12], [8, 12, 16, 16]], dtype=float)
    h = rng.random((50, 5)) * (rng.random((50, 5)) < 0.6)
    plan = plan_centroid(params)
    batch = centroid(plan, h)
    single = np.array([centroid(plan, row[None, :])[0] for row in h])
    np.testing.assert_allclose(batch, single, rtol=1e-14)
