"""Shared helpers for the fuzzy tests: paths and a small rule-file writer."""

from __future__ import annotations

from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
RULES = REPO / "rules" / "pathtracing.xml"
DATA = REPO / "tests" / "data" / "rules"


def system_xml(inputs: str, outputs: str, rules: str) -> str:
    """A paper-dialect rule file from its three parts."""
    return f'<?xml version="1.0"?>\n<system name="t">\n{inputs}\n{outputs}\n{rules}\n</system>\n'


SIMPLE_IN = '<linguisticvar type="in" name="x" min="0" max="10">\n' \
    '  <fset label="L" a="0" b="0" c="2" d="6"/>\n  <fset label="H" a="4" b="8" c="10" d="10"/>\n' \
    "</linguisticvar>"
SIMPLE_OUT = '<linguisticvar type="out" name="y" default="5">\n' \
    '  <fset label="L" a="0" b="2" c="2" d="4"/>\n  <fset label="H" a="6" b="8" c="8" d="10"/>\n' \
    "</linguisticvar>"
SIMPLE_RULES = '<rule name="R1"><antecedent name="x" label="L"/><consequent name="y" label="L"/></rule>\n' \
    '<rule name="R2"><antecedent name="x" label="H"/><consequent name="y" label="H"/></rule>'
