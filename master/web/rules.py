"""The rules that fired for one unit, with their strengths, as the web page shows them on a click.

The agents' tile headers carry the crisp outputs (Rl, Ls, Ibs) and the parameters they chose, not the rules
behind them, so the master evaluates the same rule base itself: the job's rule file (from its bundle) or,
when the job brought none, the default one, with the unit's C, S, Nd, the level's Op and the scene's observed
ranges, as `core.rules.unit_params.Planner` does. Each rule's strength is the min over its antecedents of the
max membership of their labels (fuzzy.engine's AND and OR); tests/test_web_http.py holds these strengths
against `fuzzy.Engine.activations` (an output label's activation is the max strength of the rules
concluding it), so the two cannot drift apart unseen.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from core.rules.unit_params import FEATURES, Planner
from fuzzy.rulebase import Rule, RuleBase
from fuzzy.terms import membership_t


@dataclass(frozen=True)
class FiredRules:
    """What the rules said for one unit: its inputs, the rules with a strength above 0, the crisp outputs."""

    rules_file: str
    level: str
    inputs: dict[str, float]
    fired: list[dict[str, Any]]
    outputs: dict[str, float | None]
    note: str

    def to_dict(self) -> dict[str, Any]:
        return {"rules_file": self.rules_file, "level": self.level, "inputs": self.inputs, "fired": self.fired,
                "outputs": self.outputs, "note": self.note}


@lru_cache(maxsize=16)
def planner_for(rules: Path | None, defuzzifier: str | None) -> Planner:
    """One compiled Planner per rule file and defuzzifier (a job's page asks for many units)."""
    return Planner(rules, defuzzifier)


def rule_text(rule: Rule) -> tuple[str, str]:
    """A rule's IF part and THEN part, as a person reads them (`C is B or VB and Nd is S`)."""
    if_part = " and ".join(f"{a.variable} is {' or '.join(a.labels)}" for a in rule.antecedents) or "always"
    then_part = ", ".join(f"{c.variable} is {c.label}" for c in rule.consequents)
    return if_part, then_part


def memberships(rulebase: RuleBase, inputs: Mapping[str, float],
                ranges: Mapping[str, tuple[float, float]]) -> dict[str, dict[str, float]]:
    """Each input's membership in each of its labels (clamped to its universe or observed range)."""
    degrees = {}
    for var in rulebase.inputs:
        params, (lo, hi) = var.resolve(ranges.get(var.name))
        x = float(np.clip(inputs[var.name], lo, hi)) if var.clamp else float(inputs[var.name])
        mu = membership_t(np.array([x]), params)[:, 0]
        degrees[var.name] = {label: float(m) for label, m in zip(var.labels, mu, strict=True)}
    return degrees


def rule_strengths(rulebase: RuleBase, inputs: Mapping[str, float],
                   ranges: Mapping[str, tuple[float, float]]) -> list[float]:
    """Every rule's strength for one unit: AND is min, a multi-label antecedent is an OR (max)."""
    degrees = memberships(rulebase, inputs, ranges)
    return [min((max(degrees[a.variable][lb] for lb in a.labels) for a in rule.antecedents), default=1.0)
            for rule in rulebase.rules]


def evaluation_rulebase(planner: Planner, ranges: Mapping[str, tuple[float, float]]) -> RuleBase:
    """The rule base the planner evaluates: a MASYRO-dialect file gets its sets rewritten for the scene's
    ranges first (the planner's own `evaluation_engine`, so that both read the same sets)."""
    return planner.evaluation_engine(ranges).rulebase


def fired_rules(planner: Planner, unit: Mapping[str, float], level: str,
                ranges: Mapping[str, tuple[float, float]], note: str = "") -> FiredRules:
    """The rules with a strength above 0 for a unit (strongest first) and the crisp outputs they give."""
    name = planner.rules_path.name
    features = {k: float(unit[k]) for k in FEATURES}
    if level == "off":
        return FiredRules(name, level, features, [], {}, "level off: no rule applies, the user's depth and spp")
    inputs = {**features, "Op": planner.rulebase.op_value(level)}
    rulebase = evaluation_rulebase(planner, ranges)
    strengths = rule_strengths(rulebase, inputs, ranges)
    fired = []
    for rule, strength in zip(rulebase.rules, strengths, strict=True):
        if strength > 0:
            if_part, then_part = rule_text(rule)
            fired.append({"name": rule.name, "strength": round(strength, 4), "if": if_part, "then": then_part})
    fired.sort(key=lambda r: -r["strength"])
    params = planner.plan({k: np.array([v]) for k, v in features.items()}, level, 8, 64, ranges)[0]
    outputs = {k: (float(v) if np.isfinite(v) else None) for k, v in params.outputs.items()}  # NaN: no rule
    return FiredRules(name, level, inputs, fired, outputs, note)
