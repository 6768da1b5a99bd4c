"""Mamdani inference: hand cases, the no-rule default, NaN, clamping, dynamic sets, random rule bases."""

from __future__ import annotations

import numpy as np
import pytest
from fuzzy_helpers import SIMPLE_IN, SIMPLE_OUT, SIMPLE_RULES, system_xml
from hypothesis import given, settings
from hypothesis import strategies as st

from fuzzy import Engine, FuzzyInputError, parse_rulebase
from fuzzy.variables import spread_sets, widen_degenerate


def _engine(rules: str = SIMPLE_RULES, inputs: str = SIMPLE_IN, defuzzifier: str = "centroid") -> Engine:
    return Engine(parse_rulebase(system_xml(inputs, SIMPLE_OUT, rules).encode()), defuzzifier)


def test_hand_computed_single_rule():
    # x = 1: L has membership 1, H 0 -> y is the centroid of L = (0, 2, 2, 4): 2
    assert _engine().evaluate(np.array([[1.0]]))["y"][0] == pytest.approx(2.0)


def test_two_rules_half_fired():
    # x = 5: L = (6 - 5) / 4 = 0.25, H = (5 - 4) / 4 = 0.25 -> symmetric clipped sets around 5
    assert _engine().evaluate({"x": [5.0]})["y"][0] == pytest.approx(5.0)


def test_inputs_exactly_at_set_boundaries():
    acts = _engine().activations({"x": [2.0, 4.0, 6.0, 8.0]})["y"]
    np.testing.assert_allclose(acts, [[1, 0], [0.5, 0], [0, 0.5], [0, 1]])


def test_no_rule_fires_gives_the_declared_default():
    only_high = '<rule><antecedent name="x" label="H"/><consequent name="y" label="H"/></rule>'
    for defuzzifier in ("centroid", "centre-of-sums"):
        out = _engine(only_high, defuzzifier=defuzzifier).evaluate({"x": [0.0, 1.0, 9.0]})["y"]
        assert out[0] == out[1] == 5.0  # the default, not NaN and not 0
        assert out[2] == pytest.approx(8.0)


def test_nan_input_is_an_error_naming_variable_and_row():
    with pytest.raises(FuzzyInputError, match=r"'x' is NaN \(row 1\)"):
        _engine().evaluate({"x": [1.0, float("nan")]})


def test_out_of_universe_inputs_are_clamped():
    eng = _engine()
    out = eng.evaluate({"x": [-100.0, 0.0, 1e300, np.inf, 10.0, -np.inf]})["y"]
    assert out[0] == out[1] == out[5]
    assert out[2] == out[3] == out[4]


def test_input_shape_errors():
    eng = _engine()
    with pytest.raises(FuzzyInputError, match="missing"):
        eng.evaluate({})
    with pytest.raises(FuzzyInputError, match="unknown"):
        eng.evaluate({"x": [1.0], "q": [2.0]})
    with pytest.raises(FuzzyInputError, match="shaped"):
        eng.evaluate(np.zeros((3, 2)))
    assert eng.evaluate(np.zeros((0, 1)))["y"].shape == (0,)


def test_unknown_defuzzifier():
    with pytest.raises(ValueError, match="unknown defuzzifier"):
        _engine(defuzzifier="mean-of-max")


def test_spread_sets_partition_of_unity():
    params = spread_sets(5, 10.0, 20.0)
    np.testing.assert_allclose(params[:, 1], [10, 12.5, 15, 17.5, 20])
    from fuzzy.terms import membership

    mu = membership(np.linspace(10, 20, 101), params)
    np.testing.assert_allclose(mu.sum(axis=1), 1.0)


DYN = '<linguisticvar type="in" name="x" dynamic="true">' \
      '<fset label="L"/><fset label="M"/><fset label="H"/></linguisticvar>'
DYN_RULES = (
    '<rule><antecedent name="x" label="L"/><consequent name="y" label="L"/></rule>'
    '<rule><antecedent name="x" label="H"/><consequent name="y" label="H"/></rule>'
)


def test_dynamic_sets_follow_the_observed_range():
    eng = _engine(DYN_RULES, DYN)
    acts = eng.activations({"x": [100.0, 150.0, 200.0]}, ranges={"x": (100.0, 200.0)})["y"]
    np.testing.assert_allclose(acts, [[1, 0], [0, 0], [0, 1]])
    # a unit just outside the observed range is clamped to its edge, not left unfired
    acts = eng.activations({"x": [99.0, 201.0]}, ranges={"x": (100.0, 200.0)})["y"]
    np.testing.assert_allclose(acts, [[1, 0], [0, 1]])


def test_dynamic_range_defaults_to_the_inputs_and_degenerate_range_is_normal():
    eng = _engine(DYN_RULES, DYN)
    acts = eng.activations({"x": [3.0, 3.0, 3.0]})["y"]  # min == max: every unit is "M"
    np.testing.assert_allclose(acts, 0.0)
    assert eng.evaluate({"x": [3.0]})["y"][0] == 5.0  # M concludes nothing here: the default
    assert widen_degenerate(0.0, 0.0) == (-0.5, 0.5)
    assert widen_degenerate(1e6, 1e6) == (1e6 - 5e5, 1e6 + 5e5)


def test_dynamic_range_errors():
    eng = _engine(DYN_RULES, DYN)
    with pytest.raises(FuzzyInputError, match="max"):
        eng.evaluate({"x": [1.0]}, ranges={"x": (2.0, 1.0)})
    with pytest.raises(FuzzyInputError, match="not finite"):
        eng.evaluate({"x": [1.0]}, ranges={"x": (0.0, np.nan)})


def test_or_antecedent_takes_the_max():
    rules = '<rule><antecedent name="x" label="{L, H}"/><consequent name="y" label="H"/></rule>'
    acts = _engine(rules).activations({"x": [1.0, 5.0, 9.0]})["y"]
    np.testing.assert_allclose(acts[:, 1], [1.0, 0.25, 1.0])


@st.composite
def rule_bases(draw):
    """A random valid rule file (2 inputs, 1-2 outputs, 1-6 rules), with degenerate sets allowed."""

    def sets(prefix):
        n = draw(st.integers(1, 4))
        rows = []
        for i in range(n):
            a, b, c, d = sorted(draw(st.lists(st.integers(0, 20), min_size=4, max_size=4)))
            rows.append(f'<fset label="{prefix}{i}" a="{a}" b="{b}" c="{c}" d="{d}"/>')
        return n, "".join(rows)

    ins, outs, info = [], [], {}
    for name in ("u", "v"):
        n, body = sets("L")
        ins.append(f'<linguisticvar type="in" name="{name}" min="0" max="20">{body}</linguisticvar>')
        info[name] = n
    n_out = draw(st.integers(1, 2))
    for name in ("p", "q")[:n_out]:
        n, body = sets("O")
        default = draw(st.integers(0, 20))
        outs.append(f'<linguisticvar type="out" name="{name}" min="0" max="20" default="{default}">{body}'
                    "</linguisticvar>")
        info[name] = n
    rules = []
    for _ in range(draw(st.integers(1, 6))):
        var = draw(st.sampled_from(["u", "v"]))
        labels = draw(st.sets(st.integers(0, info[var] - 1), min_size=1))
        out = draw(st.sampled_from(("p", "q")[:n_out]))
        label = draw(st.integers(0, info[out] - 1))
        rules.append(f'<rule><antecedent name="{var}" label="{" ".join(f"L{i}" for i in labels)}"/>'
                     f'<consequent name="{out}" label="O{label}"/></rule>')
    return system_xml("".join(ins), "".join(outs), "".join(rules))


@settings(max_examples=60, deadline=None)
@given(rule_bases(), st.lists(st.tuples(st.floats(-5, 25), st.floats(-5, 25)), min_size=1, max_size=20),
       st.sampled_from(["centroid", "centre-of-sums"]))
def test_outputs_finite_and_inside_the_universe_for_any_rule_base(xml, rows, defuzzifier):
    eng = Engine(parse_rulebase(xml.encode()), defuzzifier)
    for name, values in eng.evaluate(np.array(rows)).items():
        lo, hi = eng.rulebase.output(name).universe
        assert np.isfinite(values).all()
        assert ((values >= lo) & (values <= hi)).all()
