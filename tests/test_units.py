"""core.model.units: a WorkUnit survives to_dict/from_dict, and malformed units are refused naming the field."""

from __future__ import annotations

import json

import pytest
from hypothesis import given
from hypothesis import strategies as st

from core.model.geometry import Rect
from core.model.units import UnitError, WorkUnit

finite = st.floats(min_value=0, max_value=1e9, allow_nan=False)


@st.composite
def units(draw: st.DrawFn) -> WorkUnit:
    rect = Rect(draw(st.integers(0, 5000)), draw(st.integers(0, 5000)),
                draw(st.integers(1, 512)), draw(st.integers(1, 512)))
    return WorkUnit(index=draw(st.integers(0, 10_000)), rect=rect, C=draw(finite), S=rect.area, Nd=draw(finite),
                cost=draw(finite), neighbours=tuple(draw(st.lists(st.integers(0, 10_000), max_size=8))))


@given(units())
def test_round_trip_through_json(unit: WorkUnit) -> None:
    assert WorkUnit.from_dict(json.loads(json.dumps(unit.to_dict()))) == unit


def test_size_must_be_the_area() -> None:
    with pytest.raises(UnitError, match="S=5"):
        WorkUnit(index=0, rect=Rect(0, 0, 2, 2), C=0, S=5, Nd=0, cost=0)


@pytest.mark.parametrize("name", ["C", "Nd", "cost"])
@pytest.mark.parametrize("value", [float("nan"), float("inf"), -1.0])
def test_bad_feature_names_the_field(name: str, value: float) -> None:
    fields = {"C": 0.0, "Nd": 0.0, "cost": 0.0, name: value}
    with pytest.raises(UnitError, match=repr(name)):
        WorkUnit(index=0, rect=Rect(0, 0, 1, 1), S=1, **fields)


def test_missing_or_malformed_fields_are_named() -> None:
    good = WorkUnit(index=3, rect=Rect(1, 2, 3, 4), C=1, S=12, Nd=0.5, cost=2).to_dict()
    with pytest.raises(UnitError, match="'Nd'"):
        WorkUnit.from_dict({k: v for k, v in good.items() if k != "Nd"})
    with pytest.raises(UnitError, match="malformed"):
        WorkUnit.from_dict({**good, "rect": [1, 2, 3]})
    with pytest.raises(UnitError, match="JSON object"):
        WorkUnit.from_dict([1, 2])  # type: ignore[arg-type]
