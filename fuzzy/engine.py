"""Vectorised Mamdani inference: many work units evaluated in one call with numpy.

`Engine(rulebase, defuzzifier)` compiles a rule base once; `evaluate(inputs, ranges)` gives each output's
crisp value per unit, and `activations` each output label's clip level. The union of the clipped sets is
defuzzified by `centroid` (exact) or, for compatibility with MASYRO, `centre-of-sums` (`DEFUZZIFIERS`).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from fuzzy.defuzzify import centre_of_sums_t, centroid_t, plan_centroid
from fuzzy.errors import FuzzyInputError
from fuzzy.rulebase import RuleBase
from fuzzy.terms import membership_t

Inputs = np.ndarray | Mapping[str, np.ndarray]
Ranges = Mapping[str, tuple[float, float]] | None
# units per internal batch: keeps temporaries in cache and off the page-faulting mmap path
CHUNK = 4096
DEFUZZIFIERS = ("centroid", "centre-of-sums")
_ALIASES = {"centroid": "centroid", "centre-of-sums": "centre-of-sums", "center-of-sums": "centre-of-sums"}


def default_defuzzifier(rulebase: RuleBase) -> str:
    """MASYRO's published inference is a centre of sums; the paper dialect's default is the exact centroid."""
    return "centre-of-sums" if rulebase.dialect == "masyro" else "centroid"


class Engine:
    """A compiled rule base; `evaluate` runs it on a batch of units."""

    def __init__(self, rulebase: RuleBase, defuzzifier: str | None = None) -> None:
        """`defuzzifier` None: the rule file's dialect's own (`default_defuzzifier`)."""
        defuzzifier = defuzzifier or default_defuzzifier(rulebase)
        if defuzzifier not in _ALIASES:
            choices = ", ".join(DEFUZZIFIERS)
            raise ValueError(f"unknown defuzzifier {defuzzifier!r}; expected one of {choices}")
        self.rulebase = rulebase
        self.defuzzifier = _ALIASES[defuzzifier]
        self.input_names = tuple(v.name for v in rulebase.inputs)
        self.output_names = tuple(v.name for v in rulebase.outputs)
        self._compile()

    def _compile(self) -> None:
        rb = self.rulebase
        # each distinct (variable, label subset) used by an antecedent becomes one column
        self._groups: list[tuple[int, np.ndarray]] = []
        keys: dict[tuple[str, tuple[str, ...]], int] = {}
        rule_terms: list[list[int]] = []
        for rule in rb.rules:
            terms = []
            for ante in rule.antecedents:
                key = (ante.variable, tuple(sorted(set(ante.labels))))
                if key not in keys:
                    var = rb.input(ante.variable)
                    keys[key] = len(self._groups)
                    idx = np.array([var.labels.index(lb) for lb in key[1]], dtype=np.intp)
                    self._groups.append((self.input_names.index(ante.variable), idx))
                terms.append(keys[key])
            rule_terms.append(terms)
        width = max(len(t) for t in rule_terms)
        pad = len(self._groups)  # a column of ones: AND with "true"
        self._rule_terms = np.array([t + [pad] * (width - len(t)) for t in rule_terms], dtype=np.intp)
        # per output and label: the rules concluding it (none: the zero row after the rules). Kept per
        # label, not padded to the longest list: one label concluded by many rules (Rl's VB) would
        # otherwise make every label of its output gather that many rows.
        self._label_rules = [
            [np.array([r for r, rule in enumerate(rb.rules)
                       if any(c.variable == out.name and c.label == lb for c in rule.consequents)]
                      or [len(rb.rules)], dtype=np.intp)
             for lb in out.labels]
            for out in rb.outputs
        ]
        self._plans = [plan_centroid(out.params) for out in rb.outputs]

    def activations(self, inputs: Inputs, ranges: Ranges = None) -> dict[str, np.ndarray]:
        """Activation (n, L) of every output label: the clip level of each set before defuzzifying."""
        x = self._as_matrix(inputs)
        return {name: h.T for name, h in self._activations_t(x, self._observed_ranges(x, ranges)).items()}

    def evaluate(self, inputs: Inputs, ranges: Ranges = None) -> dict[str, np.ndarray]:
        """Crisp value of every output for every unit: name -> (n,) float64 array.

        `inputs` is (n, len(input_names)) in `input_names` order, one row of that length, or a mapping
        name -> (n,) array. `ranges` gives the observed (lo, hi) of dynamic input variables; one left out
        is taken from the inputs themselves (their min and max).

        Per unit: each input is clamped to its universe (or observed range) and its memberships computed;
        an antecedent naming several labels takes their max (OR); a rule's strength is the min of its
        antecedents (AND); a label's activation is the max of the strengths of the rules concluding it.
        An output no rule fires for takes its variable's default (MASYRO's dialect declares none: NaN,
        which the planner reads as 'keep the user's value'); otherwise never NaN and never a silent 0.
        NaN inputs raise `FuzzyInputError` (naming the variable and row); infinite ones are clamped like
        any out-of-range value. Crisp outputs are clamped into their universe.
        """
        x = self._as_matrix(inputs)
        ranges = self._observed_ranges(x, ranges)
        parts = [self._evaluate_chunk(x[i : i + CHUNK], ranges) for i in range(0, max(len(x), 1), CHUNK)]
        return {name: np.concatenate([p[name] for p in parts]) for name in self.output_names}

    def _evaluate_chunk(self, x: np.ndarray, ranges: dict[str, tuple[float, float]]) -> dict[str, np.ndarray]:
        result = {}
        acts = self._activations_t(x, ranges)
        for out, plan in zip(self.rulebase.outputs, self._plans, strict=True):
            h = acts[out.name]
            exact = self.defuzzifier == "centroid"
            crisp = centroid_t(plan, h) if exact else centre_of_sums_t(out.params, h)
            crisp = np.where(np.isnan(crisp), np.nan if out.default is None else out.default, crisp)
            result[out.name] = np.clip(crisp, *out.universe)
        return result

    def _observed_ranges(self, x: np.ndarray, ranges: Ranges) -> dict[str, tuple[float, float]]:
        """The given ranges, plus the inputs' own min and max for dynamic variables left out."""
        ranges = dict(ranges or {})
        for i, var in enumerate(self.rulebase.inputs):
            if var.dynamic and var.name not in ranges:
                ranges[var.name] = (float(x[:, i].min()), float(x[:, i].max())) if len(x) else (0.0, 0.0)
        return ranges

    def _activations_t(self, x: np.ndarray, ranges: dict[str, tuple[float, float]]) -> dict[str, np.ndarray]:
        # units on the last axis: numpy's inner loops then run over the units, not over a few rules
        n = x.shape[0]
        degrees = np.empty((len(self._groups) + 1, n))
        self._group_degrees(x, ranges, degrees)
        degrees[-1] = 1.0
        strengths = np.empty((len(self.rulebase.rules) + 1, n))
        rules = strengths[:-1]  # (R, n): AND (min) of each rule's terms, one term column at a time
        np.take(degrees, self._rule_terms[:, 0], axis=0, out=rules)
        for t in range(1, self._rule_terms.shape[1]):
            np.minimum(rules, degrees[self._rule_terms[:, t]], out=rules)
        strengths[-1] = 0.0
        acts = {}
        for out, per_label in zip(self.rulebase.outputs, self._label_rules, strict=True):
            h = np.empty((len(per_label), n))
            for label, idx in enumerate(per_label):
                np.max(strengths[idx], axis=0, out=h[label])
            acts[out.name] = h
        return acts

    def _group_degrees(self, x: np.ndarray, ranges: dict[str, tuple[float, float]], out: np.ndarray) -> None:
        mus = []
        for i, var in enumerate(self.rulebase.inputs):
            params, (lo, hi) = var.resolve(ranges.get(var.name))
            mus.append(membership_t(np.clip(x[:, i], lo, hi) if var.clamp else x[:, i], params))
        for g, (var_i, idx) in enumerate(self._groups):
            np.max(mus[var_i][idx], axis=0, out=out[g])

    def _as_matrix(self, inputs: Inputs) -> np.ndarray:
        if isinstance(inputs, Mapping):
            unknown = set(inputs) - set(self.input_names)
            if unknown:
                raise FuzzyInputError(f"unknown input variable(s): {', '.join(sorted(unknown))}")
            missing = [n for n in self.input_names if n not in inputs]
            if missing:
                raise FuzzyInputError(f"missing input variable(s): {', '.join(missing)}")
            cols = [np.atleast_1d(np.asarray(inputs[n], dtype=np.float64)) for n in self.input_names]
            if len({c.shape for c in cols}) != 1 or cols[0].ndim != 1:
                raise FuzzyInputError("inputs must be 1-D arrays of one common length")
            x = np.stack(cols, axis=1)
        else:
            x = np.asarray(inputs, dtype=np.float64)
            if x.ndim == 1 and x.shape[0] == len(self.input_names):
                x = x[None, :]
            if x.ndim != 2 or x.shape[1] != len(self.input_names):
                raise FuzzyInputError(
                    f"inputs must be shaped (n, {len(self.input_names)}) in the order "
                    f"{', '.join(self.input_names)}; got {x.shape}"
                )
        bad = np.isnan(x)
        if bad.any():
            row, col = (int(v) for v in np.argwhere(bad)[0])
            raise FuzzyInputError(f"input {self.input_names[col]!r} is NaN (row {row})")
        return x
