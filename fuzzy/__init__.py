"""QUEKARO's fuzzy expert system: rule bases in XML, vectorised Mamdani inference, exact centroid.

Stands alone: imports numpy, lxml and the standard library only.
"""

from fuzzy.engine import DEFUZZIFIERS, Engine
from fuzzy.errors import FuzzyInputError, RuleFileError
from fuzzy.loader import load_rulebase, parse_rulebase
from fuzzy.rulebase import Antecedent, Consequent, Rule, RuleBase
from fuzzy.terms import Trapezoid
from fuzzy.variables import InputVariable, OutputVariable

__all__ = [
    "DEFUZZIFIERS",
    "Antecedent",
    "Consequent",
    "Engine",
    "FuzzyInputError",
    "InputVariable",
    "OutputVariable",
    "Rule",
    "RuleBase",
    "RuleFileError",
    "Trapezoid",
    "load_rulebase",
    "parse_rulebase",
]
