"""`quekaro bench fuzzy`: speed of the batched engine against pyfuzzylite, and centroid exactness.

Evaluates the path-tracing rule base (48 rules) on random units (C, S, Nd uniform over an observed range
[0, 1], Op uniform over [0, 4]); reports evaluations per second (one evaluation = one unit, all three
outputs) for this engine and for pyfuzzylite on the same rule base and the same units in the same run,
and the largest relative difference between the exact centroid and a numerical integration (trapezoid
rule on `--check-points` samples) of the same aggregate. Prints figures; asserts nothing.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import fuzzylite as fl
import numpy as np

from bench.report import DEFAULT_OUT, command_of, write_report
from core.data import default_rules_path
from fuzzy.defuzzify import centroid, numeric_centroid, plan_centroid
from fuzzy.engine import Engine
from fuzzy.loader import load_rulebase
from fuzzy.rulebase import RuleBase

RANGE = (0.0, 1.0)


def default_rules() -> Path:
    return default_rules_path()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--rules", default=str(default_rules()), help="rule file (default: %(default)s)")
    parser.add_argument("--units", type=int, default=10_000, help="units per batch (default: %(default)s)")
    parser.add_argument("--repeats", type=int, default=7, help="timed batches (default: %(default)s)")
    parser.add_argument("--check-units", type=int, default=20, help="units for the centroid check")
    parser.add_argument("--check-points", type=int, default=1_000_000, help="samples per numerical centroid")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="folder for fuzzy.md")


def rules_file(args: argparse.Namespace) -> Path:
    """The rule file evaluated (bench.commands records its hash)."""
    return Path(args.rules)


def run(args: argparse.Namespace) -> dict:
    rb = load_rulebase(args.rules)
    engine = Engine(rb)
    x, ranges = _random_units(engine, args.units, args.seed)
    times = []
    for _ in range(max(1, args.repeats)):
        t0 = time.perf_counter()
        ours = engine.evaluate(x, ranges)
        times.append(time.perf_counter() - t0)
    result = {
        "units": args.units,
        "rules": len(rb.rules),
        "evals_per_s": args.units / min(times),
        "evals_per_s_median": args.units / statistics.median(times),
        "centroid_max_rel_error": _centroid_error(engine, x, ranges, args.check_units, args.check_points),
        "centroid_check_units": args.check_units,
        "centroid_check_points": args.check_points,
    }
    result.update(_pyfuzzylite(rb, engine, x, ranges, ours))
    text = format_table(result)
    result["report"] = str(write_report(args.out, "fuzzy", "Fuzzy engine against pyfuzzylite", text,
                                        command_of(args, "quekaro bench fuzzy")))
    if not getattr(args, "json", False):
        print(text)
    return result


def _random_units(engine: Engine, n: int, seed: int) -> tuple[np.ndarray, dict[str, tuple[float, float]]]:
    rng = np.random.default_rng(seed)
    x = rng.uniform(*RANGE, size=(n, len(engine.input_names)))
    ranges = {}
    for i, var in enumerate(engine.rulebase.inputs):
        if var.dynamic:
            ranges[var.name] = RANGE
        else:
            x[:, i] = rng.uniform(*var.universe, size=n)
    return x, ranges


def _centroid_error(engine: Engine, x: np.ndarray, ranges: dict, units: int, points: int) -> float:
    acts = engine.activations(x[:units], ranges)
    worst = 0.0
    for out in engine.rulebase.outputs:
        exact = centroid(plan_centroid(out.params), acts[out.name])
        for i, h in enumerate(acts[out.name]):
            if not h.any():
                continue
            ref = numeric_centroid(out.params, h, points)
            worst = max(worst, abs(exact[i] - ref) / max(abs(ref), 1e-300))
    return worst


def _pyfuzzylite(rb: RuleBase, engine: Engine, x: np.ndarray, ranges: dict, ours: dict) -> dict:
    fl_engine = _build_fuzzylite(fl, rb, engine, ranges)
    fl_engine.input_values = x
    t0 = time.perf_counter()
    fl_engine.process()
    elapsed = time.perf_counter() - t0
    theirs = fl_engine.output_values  # (n, outputs) in our output order
    diff = max(
        float(np.nanmax(np.abs(theirs[:, j] - ours[name]))) for j, name in enumerate(engine.output_names)
    )
    rate = len(x) / elapsed
    return {
        "pyfuzzylite_version": fl.__version__,
        "pyfuzzylite_evals_per_s": rate,
        "ratio": _ratio(engine, x, ranges, rate),
        "pyfuzzylite_max_abs_diff": diff,
    }


def _ratio(engine: Engine, x: np.ndarray, ranges: dict, fl_rate: float) -> float:
    # measured again right after pyfuzzylite, so both figures come from the same machine state
    t0 = time.perf_counter()
    engine.evaluate(x, ranges)
    return len(x) / (time.perf_counter() - t0) / fl_rate


def _build_fuzzylite(fl, rb: RuleBase, engine: Engine, ranges: dict):
    inputs = []
    for var in rb.inputs:
        params, (lo, hi) = var.resolve(ranges.get(var.name))
        terms = [fl.Trapezoid(lb, *p) for lb, p in zip(var.labels, params, strict=True)]
        inputs.append(fl.InputVariable(var.name, minimum=lo, maximum=hi, lock_range=True, terms=terms))
    outputs = [
        fl.OutputVariable(
            out.name, minimum=out.universe[0], maximum=out.universe[1], default_value=out.default,
            aggregation=fl.Maximum(), defuzzifier=fl.Centroid(),
            terms=[fl.Trapezoid(s.label, *s.vertices) for s in out.sets],
        )
        for out in rb.outputs
    ]
    fl_engine = fl.Engine(rb.name, input_variables=inputs, output_variables=outputs)
    rules = [fl.Rule.create(_rule_text(rule), fl_engine) for rule in rb.rules]
    fl_engine.rule_blocks = [
        fl.RuleBlock("rules", conjunction=fl.Minimum(), disjunction=fl.Maximum(), implication=fl.Minimum(),
                     activation=fl.General(), rules=rules)
    ]
    return fl_engine


def _rule_text(rule) -> str:
    antes = []
    for a in rule.antecedents:
        alts = " or ".join(f"{a.variable} is {lb}" for lb in a.labels)
        antes.append(f"({alts})" if len(a.labels) > 1 else alts)
    cons = " and ".join(f"{c.variable} is {c.label}" for c in rule.consequents)
    return f"if {' and '.join(antes)} then {cons}"


def format_table(r: dict) -> str:
    fl_rate = r.get("pyfuzzylite_evals_per_s")
    rows = [
        ("rule base", f"{r['rules']} rules, {r['units']} random units"),
        ("this engine (exact centroid)",
         f"{r['evals_per_s']:,.0f} evals/s (median {r['evals_per_s_median']:,.0f})"),
        ("pyfuzzylite", f"{fl_rate:,.0f} evals/s" if fl_rate else r.get("pyfuzzylite_note", "n/a")),
        ("ratio", f"{r['ratio']:.1f}x" if r.get("ratio") else "n/a"),
        ("centroid max rel. error",
         f"{r['centroid_max_rel_error']:.2e} against {r['centroid_check_points']:,}-point integration"
         f" on {r['centroid_check_units']} units"),
    ]
    if "pyfuzzylite_max_abs_diff" in r:
        diff = r["pyfuzzylite_max_abs_diff"]
        rows.append(("max |ours - pyfuzzylite|", f"{diff:.2e} (its centroid samples)"))
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)
