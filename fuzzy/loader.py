"""Read a rule base from XML: secure parsing, schema validation, then consistency checks.

`load_rulebase(path)`, or `parse_rulebase(data)`, returns a `RuleBase`; every refusal is a `RuleFileError`
naming the file, line, variable and label at fault. Both dialects of the schema (`schema_path`) are read,
each with its own meaning: the paper's (`<fset>`) and the original MASYRO files' (`<fuzzyset>`).
"""

from __future__ import annotations

import copy
import functools
import math
import os
import re
from pathlib import Path

from lxml import etree

from fuzzy.errors import RuleFileError
from fuzzy.rulebase import Antecedent, Consequent, Rule, RuleBase
from fuzzy.terms import Trapezoid
from fuzzy.variables import MAGNITUDE_MAX, InputVariable, OutputVariable

MAX_BYTES = 1 << 20  # 1 MiB: a rule base of thousands of rules fits; anything larger is refused
_SET_TAGS = ("fset", "fuzzyset")
_CONSEQUENT_TAGS = ("consequent", "consequence")
_LABEL_SPLIT = re.compile(r"[\s,{}]+")  # what a set's label may not hold
_LABEL_ITEMS = re.compile(r"\s*,\s*|\s+")  # a clause's labels: "VS,S", "VS S", "{VS, S}" (braces taken off)
_FORBIDDEN = re.compile(rb"<!\s*(DOCTYPE|ENTITY)", re.IGNORECASE)
_FORBIDDEN_TEXT = re.compile(r"<!\s*(DOCTYPE|ENTITY)", re.IGNORECASE)


def schema_path() -> Path:
    """The rule files' XML schema, fuzzy/quekaro-rules.xsd (shipped with this package)."""
    return Path(__file__).resolve().parent / "quekaro-rules.xsd"


@functools.lru_cache(maxsize=1)
def _schema() -> etree.XMLSchema:
    return etree.XMLSchema(etree.parse(str(schema_path()), _secure_parser()))


def _secure_parser() -> etree.XMLParser:
    """A parser that resolves no entities, loads no DTD and never touches the network."""
    return etree.XMLParser(
        resolve_entities=False, no_network=True, load_dtd=False, dtd_validation=False, huge_tree=False
    )


def load_rulebase(path: str | os.PathLike[str]) -> RuleBase:
    """Read, validate and check one rule file; raises `RuleFileError`."""
    name = str(path)
    data = _read_limited(name)
    return parse_rulebase(data, name)


def _declaration_line(data: bytes) -> int | None:
    """The line of a DOCTYPE/ENTITY declaration, looked for in the bytes and in the text they decode to
    (a UTF-16 or UTF-32 file hides the declaration from a byte search); None if there is none."""
    found = _FORBIDDEN.search(data)
    if found:
        return data.count(b"\n", 0, found.start()) + 1
    for codec in ("utf-16", "utf-32"):
        try:
            text = data.decode(codec)
        except UnicodeDecodeError:
            continue
        found = _FORBIDDEN_TEXT.search(text)
        if found:
            return text.count("\n", 0, found.start()) + 1
    return None


def parse_rulebase(data: bytes, file: str = "<rules>") -> RuleBase:
    """Same as `load_rulebase` for bytes already in memory; `file` names them in errors. Hostile files are
    refused before parsing: more than `MAX_BYTES`, or any DOCTYPE / ENTITY declaration (entity expansion
    such as "billion laughs", external entities)."""
    if len(data) > MAX_BYTES:
        raise RuleFileError(f"file is larger than {MAX_BYTES} bytes", file=file)
    line = _declaration_line(data)
    if line is not None:
        raise RuleFileError(
            "DOCTYPE and ENTITY declarations are not allowed in rule files", file=file, line=line
        )
    try:
        root = etree.fromstring(data, _secure_parser())
    except etree.XMLSyntaxError as exc:
        raise RuleFileError(f"not well-formed XML: {exc.msg}", file=file, line=exc.lineno) from None
    system = _find_system(root, file)
    _validate(system, file)
    return _build(system, file)


def _read_limited(file: str) -> bytes:
    try:
        with open(file, "rb") as fh:
            data = fh.read(MAX_BYTES + 1)
    except OSError as exc:
        raise RuleFileError(f"cannot read: {exc.strerror or exc}", file=file) from None
    if len(data) > MAX_BYTES:
        raise RuleFileError(f"file is larger than {MAX_BYTES} bytes", file=file)
    return data


def _find_system(root: etree._Element, file: str) -> etree._Element:
    """`<system>`, as the root or as a child of any outer element (MASYRO's files wrap it)."""
    if root.tag == "system":
        return root
    found = [el for el in root if el.tag == "system"]
    if len(found) != 1:
        what = "no <system> element" if not found else f"{len(found)} <system> elements"
        raise RuleFileError(
            f"expected <system> as the root or one child of it, found {what}", file=file, line=root.sourceline
        )
    return found[0]


def _validate(system: etree._Element, file: str) -> None:
    schema = _schema()
    doc = etree.ElementTree(copy.deepcopy(system))  # deepcopy keeps source lines
    if schema.validate(doc):
        return
    err = schema.error_log[0]
    variable, label = _context_at_line(system, err.line)
    raise RuleFileError(f"schema: {err.message}", file=file, line=err.line, variable=variable, label=label)


def _context_at_line(system: etree._Element, line: int) -> tuple[str | None, str | None]:
    """The variable and label named by the element at `line`, to enrich a schema error."""
    for el in system.iter():
        if not isinstance(el.tag, str) or el.sourceline != line:
            continue
        if el.tag in _SET_TAGS:
            return el.getparent().get("name"), el.get("label")
        if el.tag == "linguisticvar":
            return el.get("name"), None
        if el.tag in ("antecedent", *_CONSEQUENT_TAGS):
            return el.get("name") or el.get("varname"), el.get("label") or el.get("linguisticlabel")
    return None, None


def _build(system: etree._Element, file: str) -> RuleBase:
    inputs: list[InputVariable] = []
    outputs: list[OutputVariable] = []
    seen: set[str] = set()
    masyro = next(system.iter("fuzzyset"), None) is not None
    for el in system.iter("linguisticvar"):
        var = _build_variable(el, file, masyro)
        if var.name in seen:
            raise RuleFileError("variable declared twice", file=file, line=el.sourceline, variable=var.name)
        seen.add(var.name)
        (inputs if isinstance(var, InputVariable) else outputs).append(var)
    if not inputs or not outputs:
        raise RuleFileError("a system needs at least one input and one output variable", file=file)
    ins = {v.name: v for v in inputs}
    outs = {v.name: v for v in outputs}
    rules = tuple(_build_rule(el, i, ins, outs, file) for i, el in enumerate(system.iter("rule"), 1))
    if not rules:
        raise RuleFileError("the system has no rules", file=file, line=system.sourceline)
    dialect = "masyro" if masyro else "paper"
    return RuleBase(system.get("name") or Path(file).stem, tuple(inputs), tuple(outputs), rules, file, dialect)


def _build_variable(el: etree._Element, file: str, masyro: bool = False) -> InputVariable | OutputVariable:
    """One variable. A MASYRO file (`<fuzzyset>`) is read as MASYRO's published code reads it
    (TheProjecter/masyro06, trunk/src/Util_fuzzy.py and src/RenderAgent.py): inputs are not clamped, and
    an output with no `default` has no value where no rule fires, so the planner keeps the user's value.
    Its sets are kept as written: rebuilding C, Nd and S per job is the planner's part, as it was the
    agent's in MASYRO (core.rules.unit_params)."""
    name = el.get("name")
    is_input = el.get("type") == "in"
    dynamic = el.get("dynamic") in ("true", "1")
    set_els = [s for s in el if s.tag in _SET_TAGS]
    if not set_els:
        raise RuleFileError("variable has no fuzzy sets", file=file, line=el.sourceline, variable=name)
    labels: list[str] = []
    for s in set_els:
        if _LABEL_SPLIT.search(s.get("label") or " "):
            raise RuleFileError("a label must be one word without commas or braces: a rule's label is split "
                                "there, so no rule could name this set", file=file, line=s.sourceline,
                                variable=name, label=s.get("label"))
        if s.get("label") in labels:
            raise RuleFileError(
                "duplicate label", file=file, line=s.sourceline, variable=name, label=s.get("label")
            )
        labels.append(s.get("label"))
    if dynamic:
        if not is_input:
            raise RuleFileError(
                "only input variables can be dynamic", file=file, line=el.sourceline, variable=name
            )
        for s in set_els:
            if any(s.get(k) is not None for k in "abcd"):
                raise RuleFileError(
                    "sets of a dynamic variable take only a label (they are built at run time)",
                    file=file, line=s.sourceline, variable=name, label=s.get("label"),
                )
        return InputVariable(name, tuple(labels), dynamic=True)
    sets = tuple(_build_set(s, name, file) for s in set_els)
    universe = _universe(el, sets, file)
    if is_input:
        return InputVariable(name, tuple(labels), dynamic=False, sets=sets, universe=universe, clamp=not masyro)
    if masyro and el.get("default") is None:
        return OutputVariable(name, sets, universe, None)
    return OutputVariable(name, sets, universe, _default(el, universe, file))


def _number(
    el: etree._Element, attr: str, file: str, variable: str | None, label: str | None
) -> float | None:
    raw = el.get(attr)
    if raw is None:
        return None
    try:
        value = float(raw)
    except ValueError:
        value = math.nan
        msg = f"{attr}={raw!r} is not a number"
    else:
        msg = f"{attr}={raw!r} is not a finite number of magnitude up to {MAGNITUDE_MAX:g}"
    if not abs(value) <= MAGNITUDE_MAX:
        raise RuleFileError(msg, file=file, line=el.sourceline, variable=variable, label=label)
    return value


def _build_set(el: etree._Element, variable: str, file: str) -> Trapezoid:
    label = el.get("label")
    values = []
    for k in "abcd":
        v = _number(el, k, file, variable, label)
        if v is None:
            raise RuleFileError(f"set has no {k!r} vertex", file=file, line=el.sourceline,
                                variable=variable, label=label)
        values.append(v)
    for i in range(3):
        (k1, v1), (k2, v2) = ("abcd"[i], values[i]), ("abcd"[i + 1], values[i + 1])
        if v1 > v2:
            raise RuleFileError(
                f"trapezoid vertices out of order: {k1}={v1:g} > {k2}={v2:g} (need a <= b <= c <= d)",
                file=file, line=el.sourceline, variable=variable, label=label,
            )
    return Trapezoid(label, *values)


def _universe(el: etree._Element, sets: tuple[Trapezoid, ...], file: str) -> tuple[float, float]:
    name = el.get("name")
    lo = _number(el, "min", file, name, None)
    hi = _number(el, "max", file, name, None)
    lo = min(s.a for s in sets) if lo is None else lo
    hi = max(s.d for s in sets) if hi is None else hi
    if hi < lo:
        raise RuleFileError(f"universe max {hi:g} < min {lo:g}", file=file, line=el.sourceline, variable=name)
    return lo, hi


def _default(el: etree._Element, universe: tuple[float, float], file: str) -> float:
    name = el.get("name")
    value = _number(el, "default", file, name, None)
    if value is None:
        raise RuleFileError(
            'output variable declares no default (the value it takes when no rule fires): add default="..."',
            file=file, line=el.sourceline, variable=name,
        )
    if not universe[0] <= value <= universe[1]:
        raise RuleFileError(
            f"default {value:g} is outside the universe [{universe[0]:g}, {universe[1]:g}]",
            file=file, line=el.sourceline, variable=name,
        )
    return value


def _clause(el: etree._Element, file: str) -> tuple[str, tuple[str, ...]]:
    """(variable, labels) of an antecedent or consequent: `name label` (the paper's) or `varname
    linguisticlabel` (MASYRO's)."""
    names = [v for v in (el.get("name"), el.get("varname")) if v is not None]
    raw_labels = [v for v in (el.get("label"), el.get("linguisticlabel")) if v is not None]
    if len(names) != 1 or len(raw_labels) != 1:
        raise RuleFileError(
            f"<{el.tag}> needs exactly one of name/varname and one of label/linguisticlabel",
            file=file, line=el.sourceline, variable=names[0] if names else None,
        )
    text = raw_labels[0].strip()
    inner = text[1:-1].strip() if text.startswith("{") and text.endswith("}") else text
    if not inner:
        raise RuleFileError("empty label", file=file, line=el.sourceline, variable=names[0])
    items = _LABEL_ITEMS.split(inner)
    if any(not t or "{" in t or "}" in t for t in items):
        raise RuleFileError(f"label {text!r} is not one label or a set of labels such as {{B, VB}} (a brace "
                            "unmatched, or an empty item)", file=file, line=el.sourceline, variable=names[0],
                            label=text)
    if len(set(items)) != len(items):
        raise RuleFileError(f"label {text!r} names a label twice", file=file, line=el.sourceline,
                            variable=names[0], label=text)
    return names[0], tuple(items)


def _build_rule(
    el: etree._Element,
    index: int,
    ins: dict[str, InputVariable],
    outs: dict[str, OutputVariable],
    file: str,
) -> Rule:
    antecedents: list[Antecedent] = []
    consequents: list[Consequent] = []
    for clause in el:
        if not isinstance(clause.tag, str):
            continue
        var, labels = _clause(clause, file)
        is_ante = clause.tag == "antecedent"
        table = ins if is_ante else outs
        kind = "input" if is_ante else "output"
        if var not in table:
            raise RuleFileError(f"rule names an unknown {kind} variable", file=file,
                                line=clause.sourceline, variable=var, label=",".join(labels))
        for label in labels:
            if label not in table[var].labels:
                raise RuleFileError(f"rule names an unknown label of {kind} variable {var!r}",
                                    file=file, line=clause.sourceline, variable=var, label=label)
        if is_ante:
            antecedents.append(Antecedent(var, labels))
        else:  # "{S, N}": each label concluded at the rule's strength, as by two rules of these antecedents
            consequents.extend(Consequent(var, label) for label in labels)
    name = el.get("name") or f"R{index}"
    if not antecedents or not consequents:
        raise RuleFileError(f"rule {name!r} needs at least one antecedent and one consequent",
                            file=file, line=el.sourceline)
    return Rule(name, tuple(antecedents), tuple(consequents), el.sourceline)
