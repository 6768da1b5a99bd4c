"""The rule base as data: variables and Mamdani rules, independent of the XML it was read from."""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Mapping
from dataclasses import dataclass

from fuzzy.terms import Trapezoid
from fuzzy.variables import InputVariable, OutputVariable, checked_range, masyro_sets, widen_degenerate

# The inputs whose sets MASYRO's agent rebuilt for each job from the observed range (RuleBase.for_ranges).
MASYRO_REBUILT = ("C", "S", "Nd")

OP_LABELS = ("VS", "S", "N", "B", "VB")  # the paper's Op input, lowest level first


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

    def op_value(self, level: str, levels: tuple[str, ...] = OP_LABELS) -> float:
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

    def for_ranges(self, ranges: Mapping[str, tuple[float, float]]) -> RuleBase:
        """The rule base a job evaluates. MASYRO's agent rebuilt the sets of C, Nd and S for each job from
        the zones' observed range before it ran the rules (its src/RenderAgent.py): a MASYRO-dialect file
        gets the same for those of them named in `ranges` (fuzzy.variables.masyro_sets). The paper's dialect
        builds its dynamic sets in the engine: itself, unchanged."""
        if self.dialect != "masyro":
            return self
        inputs = []
        for var in self.inputs:
            if var.name in ranges and var.name in MASYRO_REBUILT:
                lo, hi = widen_degenerate(*checked_range(var.name, ranges[var.name]))
                rows = masyro_sets(len(var.labels), lo, hi)
                sets = tuple(Trapezoid(label, *row) for label, row in zip(var.labels, rows, strict=True))
                var = dataclasses.replace(var, sets=sets, universe=(float(rows[0, 0]), float(rows[-1, 3])))
            inputs.append(var)
        return dataclasses.replace(self, inputs=tuple(inputs))

    def input(self, name: str) -> InputVariable:
        return next(v for v in self.inputs if v.name == name)

    def output(self, name: str) -> OutputVariable:
        return next(v for v in self.outputs if v.name == name)

    def digest(self) -> str:
        """Hex sha256 of what the rule base computes: its dialect, variables and the set of (antecedents,
        output, label) it concludes. Names, comments, layout, rule order and how conclusions are grouped
        into rules (one rule concluding {S, N}, or two of the same antecedents) leave it unchanged, since
        the engine's AND (min) and its per-label aggregation (max) do not see them."""
        conclusions = sorted({
            (tuple(sorted({(a.variable, tuple(sorted(set(a.labels)))) for a in rule.antecedents})),
             c.variable, c.label)
            for rule in self.rules for c in rule.consequents})
        canonical = {"dialect": self.dialect, "inputs": [dataclasses.asdict(v) for v in self.inputs],
                     "outputs": [dataclasses.asdict(v) for v in self.outputs], "rules": conclusions}
        return hashlib.sha256(json.dumps(canonical, sort_keys=True).encode()).hexdigest()

    def summary(self) -> str:
        """One line: rules, inputs and outputs (used by `quekaro rules check`)."""
        built = {v.name for v in self.inputs if v.dynamic or (self.dialect == "masyro" and v.name in MASYRO_REBUILT)}
        ins = ", ".join(f"{v.name}{'*' if v.name in built else ''}" for v in self.inputs)
        outs = ", ".join(v.name for v in self.outputs)
        how = "MASYRO's dialect (a <fuzzyset> element)" if self.dialect == "masyro" else "the paper's dialect"
        return f"{len(self.rules)} rules; inputs {ins}; outputs {outs} (* = sets built at run time); {how}"
