"""The rule base as data: variables and Mamdani rules, independent of the XML it was read from."""

from __future__ import annotations

from dataclasses import dataclass

from fuzzy.variables import InputVariable, OutputVariable


@dataclass(frozen=True)
class Antecedent:
    """`variable is label1 or label2 ...` (several labels mean OR, as the paper's `C is {B, VB}`)."""

    variable: str
    labels: tuple[str, ...]


@dataclass(frozen=True)
class Consequent:
    """`variable is label`."""

    variable: str
    label: str


@dataclass(frozen=True)
class Rule:
    """IF all antecedents (AND = min) THEN every consequent, clipped at the rule's strength."""

    name: str
    antecedents: tuple[Antecedent, ...]
    consequents: tuple[Consequent, ...]
    line: int | None = None


@dataclass(frozen=True)
class RuleBase:
    """A whole system: named inputs, outputs and rules, as loaded from one file."""

    name: str
    inputs: tuple[InputVariable, ...]
    outputs: tuple[OutputVariable, ...]
    rules: tuple[Rule, ...]
    source: str | None = None

    def input(self, name: str) -> InputVariable:
        return next(v for v in self.inputs if v.name == name)

    def output(self, name: str) -> OutputVariable:
        return next(v for v in self.outputs if v.name == name)

    def summary(self) -> str:
        """One line: rules, inputs and outputs (used by `quekaro rules check`)."""
        ins = ", ".join(f"{v.name}{'*' if v.dynamic else ''}" for v in self.inputs)
        outs = ", ".join(v.name for v in self.outputs)
        return f"{len(self.rules)} rules; inputs {ins}; outputs {outs} (* = sets built at run time)"
