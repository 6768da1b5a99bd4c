"""The rule base as data: variables and Mamdani rules, independent of the XML it was read from."""

from __future__ import annotations

from dataclasses import dataclass

from fuzzy.levels import RULE_LEVELS
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
    dialect: str = "paper"  # "paper" (QUEKARO's XML) or "masyro" (MASYRO 2006): each keeps its meaning

    def op_value(self, level: str, levels: tuple[str, ...] = RULE_LEVELS) -> float:
        """The crisp Op of a level name: the middle of that label's plateau in the file's own Op sets; for
        a file whose Op sets do not name the levels, the level's rank spread evenly over the Op universe."""
        op = self.input("Op")
        if level not in levels:
            raise ValueError(f"unknown optimisation level {level!r}; expected one of {', '.join(levels)}")
        if op.dynamic or op.universe is None:
            raise ValueError(f"{self.source}: the Op input must have sets written in the file")
        if level in op.labels:
            _, b, c, _ = next(s for s in op.sets if s.label == level).vertices
            return 0.5 * (b + c)
        lo, hi = op.universe
        return lo + (hi - lo) * levels.index(level) / (len(levels) - 1)

    def input(self, name: str) -> InputVariable:
        return next(v for v in self.inputs if v.name == name)

    def output(self, name: str) -> OutputVariable:
        return next(v for v in self.outputs if v.name == name)

    def summary(self) -> str:
        """One line: rules, inputs and outputs (used by `quekaro rules check`)."""
        ins = ", ".join(f"{v.name}{'*' if v.dynamic else ''}" for v in self.inputs)
        outs = ", ".join(v.name for v in self.outputs)
        return f"{len(self.rules)} rules; inputs {ins}; outputs {outs} (* = sets built at run time)"
