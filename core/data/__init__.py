"""Files the farm ships: the default rule base and the sample scenes (package data, so that an installed
farm finds them as a checkout does; the repository's `rules/` and `scenes/` link here)."""

from __future__ import annotations

import os
from pathlib import Path

DATA = Path(__file__).resolve().parent
SCENES = DATA / "scenes"
DEMO_SCENE = SCENES / "cbox.xml"  # `quekaro demo`, and the scene agents measure their speed on


def rules_dir() -> Path:
    """The folder of the default rule base: $QUEKARO_RULES_DIR, else the shipped one."""
    env = os.environ.get("QUEKARO_RULES_DIR")
    return Path(env) if env else DATA / "rules"


def default_rules_path() -> Path:
    """The default rule base, pathtracing.xml, in `rules_dir()`."""
    return rules_dir() / "pathtracing.xml"
