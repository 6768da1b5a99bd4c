"""Dataclass fields that carry their validation constraints, for the types that cross the wire.

`constrained(lo=, hi=, max_len=, pattern=, choices=, max_items=, min_items=, key_pattern=, default=)`
is a `dataclasses.field` whose metadata `core.model.messages` checks every received value against."""

from __future__ import annotations

import dataclasses
from typing import Any


def constrained(**constraints: Any) -> Any:
    """A dataclass field with its validation constraints (and an optional default or default_factory)."""
    default = constraints.pop("default", dataclasses.MISSING)
    factory = constraints.pop("default_factory", dataclasses.MISSING)
    return dataclasses.field(default=default, default_factory=factory, metadata=constraints)
