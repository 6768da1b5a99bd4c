"""core.model.geometry.Rect.window: a unit's rendered window keeps one size for one unit size and band,
stays inside the image, and holds the unit with at least its band wherever the image has room."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from core.model.geometry import Rect


@st.composite
def units(draw: st.DrawFn) -> tuple[Rect, int, int, int]:
    width, height = draw(st.integers(1, 200)), draw(st.integers(1, 200))
    x, y = draw(st.integers(0, width - 1)), draw(st.integers(0, height - 1))
    w, h = draw(st.integers(1, width - x)), draw(st.integers(1, height - y))
    return Rect(x, y, w, h), draw(st.integers(0, 60)), width, height


@given(units())
def test_a_window_holds_its_unit_and_band_inside_the_image(case) -> None:
    unit, band, width, height = case
    win = unit.window(band, width, height)
    assert min(win.x, win.y) >= 0 and win.x1 <= width and win.y1 <= height
    assert (win.w, win.h) == (min(unit.w + 2 * band, width), min(unit.h + 2 * band, height))
    # every side has the band, or all the image has there
    assert unit.x - win.x >= min(band, unit.x) and win.x1 - unit.x1 >= min(band, width - unit.x1)
    assert unit.y - win.y >= min(band, unit.y) and win.y1 - unit.y1 >= min(band, height - unit.y1)


@given(units())
def test_a_window_is_only_shifted_against_an_image_edge(case) -> None:
    unit, band, width, height = case
    win = unit.window(band, width, height)
    left, right = unit.x - win.x, win.x1 - unit.x1
    top, bottom = unit.y - win.y, win.y1 - unit.y1
    # a side with less than the band touches the image's edge, and the band it lacks is on the other side
    assert left >= band or win.x == 0
    assert right >= band or win.x1 == width
    assert top >= band or win.y == 0
    assert bottom >= band or win.y1 == height
    if unit.w + 2 * band <= width:
        assert left + right == 2 * band
    if unit.h + 2 * band <= height:
        assert top + bottom == 2 * band


def test_units_of_one_size_render_one_window_size_wherever_they_lie() -> None:
    sizes = {Rect(x, y, 64, 64).window(3, 256, 192).as_list()[2:] == [70, 70]
             for x in range(0, 256, 64) for y in range(0, 192, 64)}
    assert sizes == {True}
