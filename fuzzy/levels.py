"""The optimisation levels, named once for the whole project: the Op input's labels in order (the rules
run), and `off` (no rules: every unit renders at the user's depth and spp)."""

from __future__ import annotations

OFF = "off"
RULE_LEVELS = ("VS", "S", "N", "B", "VB")
LEVELS = (OFF, *RULE_LEVELS)
