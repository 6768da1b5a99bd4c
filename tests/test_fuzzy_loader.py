"""The rule-file loader: both dialects, and every kind of invalid or hostile file refused clearly."""

from __future__ import annotations

import numpy as np
import pytest
from fuzzy_helpers import DATA, RULES, SIMPLE_IN, SIMPLE_OUT, SIMPLE_RULES, system_xml
from hypothesis import given, settings
from hypothesis import strategies as st

from fuzzy import Engine, RuleFileError, load_rulebase, parse_rulebase
from fuzzy.loader import MAX_BYTES


def _refuse(text: str | bytes, tmp_path) -> RuleFileError:
    path = tmp_path / "bad.xml"
    path.write_bytes(text.encode() if isinstance(text, str) else text)
    with pytest.raises(RuleFileError) as info:
        load_rulebase(path)
    assert info.value.file == str(path)
    assert str(path) in str(info.value)
    return info.value


def test_paper_dialect_rule_base_loads():
    rb = load_rulebase(RULES)
    assert len(rb.rules) == 48
    assert [v.name for v in rb.inputs] == ["C", "S", "Nd", "Op"]
    assert [v.name for v in rb.outputs] == ["Ls", "Rl", "Ibs"]
    assert [v.dynamic for v in rb.inputs] == [True, True, True, False]
    r1 = rb.rules[0]
    assert r1.antecedents[0].labels == ("B", "VB")  # "{B, VB}" means OR


def test_masyro_dialect_with_wrapper_and_any_attribute_order():
    rb = load_rulebase(DATA / "masyro_dialect.xml")
    assert rb.name == "masyro-small"
    assert rb.input("C").sets[0].vertices == (0.0, 0.0, 0.0, 5.0)
    assert rb.input("C").sets[1].vertices == (0.0, 5.0, 5.0, 10.0)
    assert rb.output("Rl").default == 9.0
    assert rb.rules[0].antecedents[1].variable == "Op"
    assert rb.rules[0].consequents[0].label == "VS"


def test_system_as_root_parses_from_bytes():
    rb = parse_rulebase(system_xml(SIMPLE_IN, SIMPLE_OUT, SIMPLE_RULES).encode())
    assert len(rb.rules) == 2 and rb.output("y").universe == (0.0, 10.0)


@pytest.mark.parametrize(
    ("fset", "fault"),
    [
        ('a="3" b="2" c="4" d="5"', "a=3 > b=2"),
        ('a="1" b="5" c="4" d="6"', "b=5 > c=4"),
        ('a="1" b="2" c="7" d="6"', "c=7 > d=6"),
        ('a="1" b="x" c="4" d="6"', "schema"),
        ('a="1" b="NaN" c="4" d="6"', "not a finite number"),
        ('a="1" b="INF" c="4" d="6"', "not a finite number"),
        ('a="0" b="0" c="1e300" d="1.5e300"', "magnitude up to 1e+30"),  # its centroid's terms overflow
        ('a="1" b="2" c="4"', "no 'd' vertex"),
    ],
)
def test_bad_trapezoid_names_file_line_variable_label(tmp_path, fset, fault):
    out = f'<linguisticvar type="out" name="y" default="5">\n  <fset label="Odd" {fset}/>\n</linguisticvar>'
    rules = '<rule><antecedent name="x" label="L"/><consequent name="y" label="Odd"/></rule>'
    err = _refuse(system_xml(SIMPLE_IN, out, rules), tmp_path)
    assert fault in str(err)
    assert (err.variable, err.label) == ("y", "Odd")
    assert err.line == 8


@pytest.mark.parametrize("label", ["L,M", "{L}", "very L", ""])
def test_a_set_label_no_rule_could_name_is_refused_at_its_line(tmp_path, label):
    """A rule's label is split at spaces, commas and braces ("{B, VB}" is B or VB): a set labelled across
    one could never fire, and a rule naming it would be refused as an unknown label elsewhere."""
    out = f'<linguisticvar type="out" name="y" default="5">\n  <fset label="{label}" a="0" b="1" c="2" d="6"/>' \
          '\n  <fset label="L" a="0" b="1" c="2" d="6"/>\n</linguisticvar>'
    rules = '<rule><antecedent name="x" label="L"/><consequent name="y" label="L"/></rule>'
    err = _refuse(system_xml(SIMPLE_IN, out, rules), tmp_path)
    assert err.line == 8 and err.variable == "y"
    assert "one word" in str(err) or (label == "" and "schema" in str(err)), err


def test_masyro_typo_d_smaller_than_c_is_refused():
    with pytest.raises(RuleFileError) as info:
        load_rulebase(DATA / "invalid" / "trapezoid_d_lt_c.xml")
    err = info.value
    assert (err.variable, err.label, err.line) == ("Ls", "B", 9)
    assert "c=9 > d=1" in str(err)


@pytest.mark.parametrize(
    ("rules", "variable", "label", "fault"),
    [
        ('<rule><antecedent name="z" label="L"/><consequent name="y" label="L"/></rule>', "z", "L",
         "unknown input variable"),
        ('<rule><antecedent name="x" label="{L, Q}"/><consequent name="y" label="L"/></rule>', "x", "Q",
         "unknown label"),
        ('<rule><antecedent name="x" label="L"/><consequent name="y" label="M"/></rule>', "y", "M",
         "unknown label"),
        ('<rule><antecedent name="x" label="L"/><consequent name="x" label="L"/></rule>', "x", "L",
         "unknown output variable"),
        ('<rule><antecedent name="x" varname="x" label="L"/><consequent name="y" label="L"/></rule>', "x", None,
         "exactly one of name/varname"),
    ],
)
def test_bad_rule_references(tmp_path, rules, variable, label, fault):
    err = _refuse(system_xml(SIMPLE_IN, SIMPLE_OUT, rules), tmp_path)
    assert fault in str(err)
    assert (err.variable, err.label) == (variable, label)
    assert err.line is not None


THREE_OUT = '<linguisticvar type="out" name="y" default="5">\n' \
    '  <fset label="L" a="0" b="2" c="2" d="4"/>\n  <fset label="M" a="2" b="4" c="4" d="6"/>\n' \
    '  <fset label="H" a="6" b="8" c="8" d="10"/>\n</linguisticvar>'


@pytest.mark.parametrize("defuzzifier", ["centroid", "centre-of-sums"])
def test_a_consequent_naming_two_labels_concludes_each_as_two_rules_would(tmp_path, defuzzifier):
    """`label="{L, M}"` in a consequent: each label at the rule's strength, the same outputs as two rules
    of the same antecedents (the shipped file's level S floor, between two labels)."""
    one = '<rule name="R1"><antecedent name="x" label="L"/><consequent name="y" label="{L, M}"/></rule>\n' \
        '<rule name="R2"><antecedent name="x" label="H"/><consequent name="y" label="H"/></rule>'
    two = '<rule name="R1"><antecedent name="x" label="L"/><consequent name="y" label="L"/></rule>\n' \
        '<rule name="R1n"><antecedent name="x" label="L"/><consequent name="y" label="M"/></rule>\n' \
        '<rule name="R2"><antecedent name="x" label="H"/><consequent name="y" label="H"/></rule>'
    x = np.linspace(-1, 11, 241)[:, None]
    outs = [Engine(parse_rulebase(system_xml(SIMPLE_IN, THREE_OUT, r).encode()), defuzzifier).evaluate(x)["y"]
            for r in (one, two)]
    np.testing.assert_array_equal(outs[0], outs[1])
    only_l = Engine(parse_rulebase(system_xml(SIMPLE_IN, THREE_OUT, SIMPLE_RULES).encode()), defuzzifier)
    assert outs[0][0] > only_l.evaluate(x[:1])["y"][0]  # M's share moves x = -1 (L only) above L's peak
    err = _refuse(system_xml(SIMPLE_IN, THREE_OUT, one.replace("{L, M}", "{L, Q}")), tmp_path)
    assert "unknown label" in str(err) and (err.variable, err.label) == ("y", "Q")


@pytest.mark.parametrize(("label", "fault"), [
    ("{L, H", "is not one label or a set of labels"),
    ("{L,}", "is not one label or a set of labels"),
    ("L, ,H", "is not one label or a set of labels"),
    ("H}", "is not one label or a set of labels"),
    ("{L, L}", "names a label twice"),
])
def test_a_malformed_label_set_is_refused(tmp_path, label, fault):
    """A brace left open, an empty item or a label twice read as a set before (`{L,}` as L)."""
    rules = f'<rule><antecedent name="x" label="{label}"/><consequent name="y" label="L"/></rule>'
    err = _refuse(system_xml(SIMPLE_IN, SIMPLE_OUT, rules), tmp_path)
    assert fault in str(err) and (err.variable, err.label) == ("x", label)


def test_rule_without_consequent(tmp_path):
    err = _refuse(system_xml(SIMPLE_IN, SIMPLE_OUT, '<rule name="R9"><antecedent name="x" label="L"/></rule>'),
                  tmp_path)
    assert "R9" in str(err)


@pytest.mark.parametrize(
    ("outputs", "fault", "label"),
    [
        ('<linguisticvar type="out" name="y" default="5"/>', "no fuzzy sets", None),
        ('<linguisticvar type="out" name="y" default="5"><fset label="L" a="0" b="1" c="1" d="2"/>'
         '<fset label="L" a="1" b="2" c="2" d="3"/></linguisticvar>', "duplicate label", "L"),
        ('<linguisticvar type="out" name="y"><fset label="L" a="0" b="1" c="1" d="2"/></linguisticvar>',
         "declares no default", None),
        ('<linguisticvar type="out" name="y" default="50"><fset label="L" a="0" b="1" c="1" d="2"/>'
         "</linguisticvar>", "outside the universe", None),
        ('<linguisticvar type="out" name="y" default="NaN"><fset label="L" a="0" b="1" c="1" d="2"/>'
         "</linguisticvar>", "not a finite number", None),
    ],
)
def test_bad_output_variables(tmp_path, outputs, fault, label):
    rules = '<rule><antecedent name="x" label="L"/><consequent name="y" label="L"/></rule>'
    err = _refuse(system_xml(SIMPLE_IN, outputs, rules), tmp_path)
    assert fault in str(err)
    assert err.variable == "y" and err.label == label


def test_dynamic_variable_rejects_vertices_and_outputs_cannot_be_dynamic(tmp_path):
    dyn = '<linguisticvar type="in" name="x" dynamic="true"><fset label="L" a="0" b="0" c="1" d="2"/>' \
          "</linguisticvar>"
    err = _refuse(system_xml(dyn, SIMPLE_OUT, SIMPLE_RULES), tmp_path)
    assert "only a label" in str(err) and err.variable == "x"
    out = '<linguisticvar type="out" name="y" dynamic="true" default="1"><fset label="L"/></linguisticvar>'
    err = _refuse(system_xml(SIMPLE_IN, out, SIMPLE_RULES), tmp_path)
    assert "only input variables can be dynamic" in str(err)


def test_schema_violation_unknown_element(tmp_path):
    err = _refuse(system_xml(SIMPLE_IN, SIMPLE_OUT, SIMPLE_RULES + "\n<script/>"), tmp_path)
    assert "schema" in str(err) and err.line is not None


def test_wrapper_without_system(tmp_path):
    err = _refuse("<rules><other/></rules>", tmp_path)
    assert "<system>" in str(err)


@pytest.mark.parametrize("name", ["billion_laughs", "external_entity"])
def test_entity_declarations_refused_before_parsing(name):
    with pytest.raises(RuleFileError) as info:
        load_rulebase(DATA / "invalid" / f"{name}.xml")
    assert "DOCTYPE" in str(info.value) and info.value.line == 2


def test_not_xml_refused_with_line():
    with pytest.raises(RuleFileError) as info:
        load_rulebase(DATA / "invalid" / "not_xml.xml")
    assert "not well-formed XML" in str(info.value) and info.value.line == 1


def test_huge_file_refused_without_parsing(tmp_path):
    filler = b"<!--" + b"x" * (MAX_BYTES + 10) + b"-->"
    err = _refuse(system_xml(SIMPLE_IN, SIMPLE_OUT, SIMPLE_RULES).encode() + filler, tmp_path)
    assert "larger than" in str(err)


def test_missing_file(tmp_path):
    with pytest.raises(RuleFileError, match="cannot read"):
        load_rulebase(tmp_path / "nope.xml")


_VALID = RULES.read_bytes()


@settings(max_examples=150, deadline=None)
@given(st.integers(0, len(_VALID)), st.integers(0, 40), st.binary(max_size=40))
def test_fuzzed_rule_files_load_or_are_refused_never_crash(start, length, junk):
    data = _VALID[:start] + junk + _VALID[start + length :]
    try:
        rb = parse_rulebase(data, "fuzzed.xml")
    except RuleFileError as exc:
        assert exc.file == "fuzzed.xml"
    else:
        assert rb.rules and rb.outputs


# ---- MASYRO's own rule file (TheProjecter/masyro06, src/init/fuzzyMasyro.xml, GPL v2) ------------------
# masyro_original.xml is that file verbatim; masyro_fixed.xml mends its one typo (Ls B: d=1 -> 11).
# The expected outputs come from a port of MASYRO's published engine (trunk/src/Util_fuzzy.py: min for
# AND, max per label, each label's trapezoid clipped at that height, centre of sums), run on the file's
# own sets; the typo is not involved in these rows.


def test_masyros_published_file_is_refused_naming_its_typo():
    path = DATA / "masyro_original.xml"
    with pytest.raises(RuleFileError) as info:
        load_rulebase(path)
    err = info.value
    assert (err.file, err.line, err.variable, err.label) == (str(path), 41, "Ls", "B")
    assert "c=9 > d=1" in str(err)


@pytest.mark.parametrize(("inputs", "expected"), [
    ({"C": 45.0, "Nd": 40.0, "S": 140000.0, "Op": 25.0}, {"Ls": 5.0, "Rl": 3.0, "Ibs": 3.8889}),
    ({"C": 80.0, "Nd": 80.0, "S": 90000.0, "Op": 5.0}, {"Ls": 11.3034, "Rl": 8.1517, "Ibs": 26.1111}),
])
def test_masyros_mended_file_evaluates_as_masyros_engine(inputs, expected):
    rulebase = load_rulebase(DATA / "masyro_fixed.xml")
    assert rulebase.dialect == "masyro" and len(rulebase.rules) == 86
    out = Engine(rulebase, "centre-of-sums").evaluate({k: [v] for k, v in inputs.items()})
    for name, value in expected.items():
        assert out[name][0] == pytest.approx(value, abs=1e-4)


def test_masyro_inputs_outside_their_sets_fire_nothing_and_outputs_have_no_value():
    rulebase = load_rulebase(DATA / "masyro_fixed.xml")
    # C=100 lies above every C set: MASYRO gives membership 0 (the paper dialect would clamp to VB), so
    # no rule naming C fires; Ibs comes from Nd alone (the engine's port: Ibs 7.5611, Ls and Rl missing).
    out = Engine(rulebase, "centre-of-sums").evaluate({"C": [100.0], "Nd": [50.0], "S": [1e5], "Op": [15.0]})
    assert np.isnan(out["Ls"][0]) and np.isnan(out["Rl"][0])
    assert out["Ibs"][0] == pytest.approx(7.5611, abs=1e-4)


def test_masyros_file_plans_units_keeping_the_users_values_where_no_rule_fires():
    from core.rules.unit_params import Planner

    planner = Planner(DATA / "masyro_fixed.xml")
    assert planner.engine.defuzzifier == "centre-of-sums"
    features = {"C": np.array([0.1, 0.5, 0.9]), "S": np.array([3000.0, 3000.0, 9000.0]),
                "Nd": np.array([0.0, 0.2, 0.4])}
    params = planner.plan(features, "VB", user_depth=8, user_spp=128)
    assert all(1 <= p.depth <= 8 and 64 <= p.spp <= 128 for p in params)  # factors in [0.5, 1]
    assert params[0].spp >= params[2].spp or params[0].depth >= params[2].depth  # simple units keep more
    low = planner.plan(features, "VS", user_depth=8, user_spp=128)
    assert sum(p.spp for p in low) >= sum(p.spp for p in params)  # VS optimises least
