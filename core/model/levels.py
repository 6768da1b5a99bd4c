"""The optimisation levels, named once for the whole project: the Op input's labels in order (the rules
run), and `off` (no rules: every unit renders at the user's depth and spp)."""

from __future__ import annotations

from fuzzy.rulebase import OP_LABELS

OFF = "off"
RULE_LEVELS = OP_LABELS
LEVELS = (OFF, *RULE_LEVELS)


def canonical(name: str) -> str:
    """The level `name` spells in any case (`s`, `OFF`), as LEVELS writes it; an unknown name as given."""
    return {level.lower(): level for level in LEVELS}.get(name.lower(), name)
