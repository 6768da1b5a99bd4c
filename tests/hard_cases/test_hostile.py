"""Hostile input not covered elsewhere: a catalogue of refused message bodies (messages/refused.json)
and rule files that hide what the loader must refuse (rules/hostile/*.xml). Each is refused with a clear
reason naming the field or file, and nothing of the host leaks into the result or the message."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from core.errors import MessageError
from core.model import messages as m
from fuzzy import RuleFileError, load_rulebase
from hard_cases.conftest import MESSAGES, RULES

REFUSED = json.loads((MESSAGES / "refused.json").read_text())
HOSTILE_RULES = sorted((RULES / "hostile").glob("*.xml"))
HOSTNAME = Path("/etc/hostname").read_text().strip() if Path("/etc/hostname").is_file() else ""


@pytest.mark.parametrize("case", REFUSED, ids=[c["name"] for c in REFUSED])
def test_message_catalogue_is_refused_naming_the_field(case):
    with pytest.raises(MessageError) as info:
        m.parse(case["performative"], case["body"])
    assert info.value.field == case["field"]
    assert len(str(info.value)) < 300  # the reason is short, whatever the body holds
    with pytest.raises(MessageError):  # the same bytes, as they arrive from the wire
        m.parse(case["performative"], case["body"].encode())


def test_catalogue_bodies_are_valid_but_for_their_fault():
    """Each case differs from an accepted body in its one fault: the catalogue tests what it says."""
    accepted = next(c for c in REFUSED if c["name"] == f"version {m.PROTOCOL_VERSION + 1}")
    fixed = json.loads(accepted["body"]) | {"v": m.PROTOCOL_VERSION}
    assert isinstance(m.parse("propose", json.dumps(fixed)), m.Propose)


@pytest.mark.parametrize("path", HOSTILE_RULES, ids=[p.stem for p in HOSTILE_RULES])
def test_hostile_rule_files_are_refused_and_leak_nothing(path):
    with pytest.raises(RuleFileError) as info:
        load_rulebase(path)
    text = str(info.value)
    assert path.name in text and info.value.line is not None
    if len(HOSTNAME) >= 4:
        assert HOSTNAME not in text  # no external file was read into the error
    assert len(text) < 400  # no expanded entity text in the reason


@pytest.mark.parametrize("name", ["billion_laughs_utf16", "external_entity_utf16", "internal_entity_utf16"])
def test_utf16_doctype_is_refused_before_parsing_as_documented(name):
    with pytest.raises(RuleFileError, match="DOCTYPE and ENTITY declarations are not allowed"):
        load_rulebase(RULES / "hostile" / f"{name}.xml")
