"""`quekaro rules check FILE` and `quekaro rules eval FILE ...`: for people writing rule files.

`check` prints a one-line summary (exit 0) or the error with file, line, variable and label (exit 2).
`eval` prints the crisp outputs as CSV on stdout, one row per input row, under a header of output names.
"""

from __future__ import annotations

import argparse
import csv
import sys

from fuzzy import Engine, FuzzyInputError, RuleFileError, load_rulebase


def register(sub: argparse._SubParsersAction) -> None:
    rules = sub.add_parser("rules", help="check and evaluate fuzzy rule files")
    rules_sub = rules.add_subparsers(dest="rules_command", metavar="ACTION", required=True)

    check = rules_sub.add_parser("check", help="validate a rule file and summarise it")
    check.add_argument("file", metavar="FILE")
    check.set_defaults(func=run_check)

    ev = rules_sub.add_parser("eval", help="evaluate a rule file on inputs; CSV of crisp outputs on stdout")
    ev.add_argument("file", metavar="FILE")
    ev.add_argument("--defuzzifier", choices=("centroid", "centre-of-sums"), default="centroid")
    ev.add_argument("--range", action="append", default=[], metavar="NAME=LO:HI",
                    help="observed range of a dynamic input variable (default: the inputs' own min and max)")
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
        engine = Engine(load_rulebase(args.file), args.defuzzifier)
        ranges = dict(_parse_range(r) for r in args.range)
        inputs = _read_csv(args.csv) if args.csv else _parse_sets(args.set)
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


def _parse_range(text: str) -> tuple[str, tuple[float, float]]:
    name, sep, rest = text.partition("=")
    lo, sep2, hi = rest.partition(":")
    if not (sep and sep2 and name):
        raise _UsageError(f"--range {text!r}: expected NAME=LO:HI")
    return name, (_number(lo, f"--range {name}"), _number(hi, f"--range {name}"))


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
        with open(path, newline="") as fh:
            reader = csv.reader(fh)
            header = [h.strip() for h in next(reader, [])]
            if not header:
                raise _UsageError(f"{path}: empty CSV (need a header of input names)")
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
    return cols
