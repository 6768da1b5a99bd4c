"""`quekaro rules check FILE` and `quekaro rules eval FILE ...`: for people writing rule files.

`check` prints a one-line summary (exit 0) or the error with file, line, variable and label (exit 2).
`eval` prints the crisp outputs as CSV on stdout, one row per input row, under a header of output names.
"""

from __future__ import annotations

import argparse
import csv
import sys

from fuzzy import DEFUZZIFIERS, Engine, FuzzyInputError, RuleBase, RuleFileError, load_rulebase
from fuzzy.rulebase import MASYRO_REBUILT


def register(sub: argparse._SubParsersAction) -> None:
    rules = sub.add_parser("rules", help="check and evaluate fuzzy rule files")
    rules_sub = rules.add_subparsers(dest="rules_command", metavar="ACTION", required=True)

    check = rules_sub.add_parser("check", help="validate a rule file and summarise it")
    check.add_argument("file", metavar="FILE")
    check.set_defaults(func=run_check)

    ev = rules_sub.add_parser("eval", help="evaluate a rule file on inputs; CSV of crisp outputs on stdout")
    ev.add_argument("file", metavar="FILE")
    ev.add_argument("--defuzzifier", choices=DEFUZZIFIERS, default=None,
                    help="default: the file's own, as a render uses it (centroid; MASYRO's files centre of sums)")
    ev.add_argument("--range", action="append", default=[], metavar="NAME=LO:HI",
                    help="observed range of a dynamic input variable (default: the inputs' own min and max); "
                         "in a MASYRO file, of C, S or Nd, whose sets MASYRO rebuilds per job as a render does "
                         "(default there too: the inputs' own min and max)")
    source = ev.add_mutually_exclusive_group(required=True)
    source.add_argument("--set", action="append", metavar="NAME=VALUE", help="one input value (one row)")
    source.add_argument("--csv", metavar="INPUTS.csv", help="a CSV file with a header of input names")
    ev.set_defaults(func=run_eval)


class _UsageError(ValueError):
    """A malformed --set/--range/--csv value."""


def run_check(args: argparse.Namespace) -> int:
    try:
        rb = load_rulebase(args.file)
    except RuleFileError as exc:
        print(f"quekaro: error: {exc}", file=sys.stderr)
        return 2
    print(f"{args.file}: ok: {rb.summary()}")
    return 0


def run_eval(args: argparse.Namespace) -> int:
    try:
        rulebase = load_rulebase(args.file)
        ranges = _parse_ranges(args.range, rulebase)
        inputs = _read_csv(args.csv) if args.csv else _parse_sets(args.set)
        if rulebase.dialect == "masyro":  # as the planner: the inputs' own min and max where not given
            ranges = {**_own_ranges(inputs, rulebase), **ranges}
        engine = Engine(rulebase.for_ranges(ranges), args.defuzzifier)
        outputs = engine.evaluate(inputs, ranges)
    except (RuleFileError, FuzzyInputError, _UsageError) as exc:
        print(f"quekaro: error: {exc}", file=sys.stderr)
        return 2
    writer = csv.writer(sys.stdout, lineterminator="\n")
    writer.writerow(engine.output_names)
    for row in zip(*(outputs[name] for name in engine.output_names), strict=True):
        writer.writerow([repr(float(v)) for v in row])
    return 0


def _number(text: str, what: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise _UsageError(f"{what}: {text!r} is not a number") from None


def _parse_ranges(items: list[str], rulebase: RuleBase) -> dict[str, tuple[float, float]]:
    """--range NAME=LO:HI at most once per input whose sets a range builds: the paper dialect's dynamic
    inputs, a MASYRO file's C, S and Nd (as a render rebuilds them: RuleBase.for_ranges). A range the file
    would not read (a misspelt name, a static variable) is refused, not left out unsaid."""
    masyro = rulebase.dialect == "masyro"
    dynamic = [v.name for v in rulebase.inputs if (v.name in MASYRO_REBUILT if masyro else v.dynamic)]
    ranges: dict[str, tuple[float, float]] = {}
    for text in items:
        name, sep, rest = text.partition("=")
        lo, sep2, hi = rest.partition(":")
        if not (sep and sep2 and name):
            raise _UsageError(f"--range {text!r}: expected NAME=LO:HI")
        if name not in dynamic:
            raise _UsageError(f"--range {name}: not an input whose sets a range builds in this rule file "
                              f"(those are: {', '.join(dynamic) or 'none'})")
        if name in ranges:
            raise _UsageError(f"--range {name} given twice")
        ranges[name] = (_number(lo, f"--range {name}"), _number(hi, f"--range {name}"))
    return ranges


def _own_ranges(inputs: dict[str, list[float]], rulebase: RuleBase) -> dict[str, tuple[float, float]]:
    """The (min, max) of each given input whose sets MASYRO rebuilds (the planner's default ranges)."""
    names = {v.name for v in rulebase.inputs} & set(MASYRO_REBUILT)
    return {k: (min(v), max(v)) for k, v in inputs.items() if k in names and v}


def _parse_sets(items: list[str]) -> dict[str, list[float]]:
    values: dict[str, list[float]] = {}
    for text in items:
        name, sep, value = text.partition("=")
        if not (sep and name):
            raise _UsageError(f"--set {text!r}: expected NAME=VALUE")
        if name in values:
            raise _UsageError(f"--set {name} given twice")
        values[name] = [_number(value, f"--set {name}")]
    return values


def _read_csv(path: str) -> dict[str, list[float]]:
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:  # -sig: the BOM spreadsheets write
            reader = csv.reader(fh)
            header = [h.strip() for h in next(reader, [])]
            if not header:
                raise _UsageError(f"{path}: empty CSV (need a header of input names)")
            twice = sorted({h for h in header if header.count(h) > 1})
            if twice:
                raise _UsageError(f"{path}:1: column {', '.join(twice)} given twice")
            cols: dict[str, list[float]] = {h: [] for h in header}
            for lineno, row in enumerate(reader, 2):
                if not row:
                    continue
                if len(row) != len(header):
                    raise _UsageError(f"{path}:{lineno}: {len(row)} fields, header has {len(header)}")
                for h, v in zip(header, row, strict=True):
                    cols[h].append(_number(v.strip(), f"{path}:{lineno} column {h}"))
    except OSError as exc:
        raise _UsageError(f"{path}: cannot read: {exc.strerror or exc}") from None
    except UnicodeDecodeError as exc:
        raise _UsageError(f"{path}: not UTF-8 text: {exc.reason} at byte {exc.start}") from None
    return cols
