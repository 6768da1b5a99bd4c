"""The scene's own integrator, kept as the scene wrote it: which Mitsuba 3.9 integrators can be split
into tiles, which take a path depth, and the one change a unit may make (its `max_depth`).

`CATALOGUE` (and `kind`) says what each plugin allows, `splittable` whether a tree can be tiled, `depth_of`
its depth, and `with_depth` the tree re-read at a new `max_depth`. A unit never rebuilds an integrator
from its type alone: that dropped its other parameters (`hide_emitters`, `rr_depth`, nested integrators, AOVs).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

from lxml import etree

from core.errors import SceneError

DEFAULT_TYPE = "path"  # what Mitsuba renders with when the scene names no integrator


@dataclass(frozen=True)
class IntegratorKind:
    """What the farm needs to know of one Mitsuba integrator plugin."""

    name: str
    splittable: bool  # each sample writes only to its own pixel, so a crop equals that region
    depth: bool  # takes `max_depth`, which the rules may lower per unit
    nests: bool = False  # wraps child integrators (their channels and depth come from them)
    note: str = ""


# Every integrator Mitsuba 3.9 ships (C++ plugins and the Python `ad` ones), said once here.
CATALOGUE: dict[str, IntegratorKind] = {k.name: k for k in (
    IntegratorKind("path", True, True, note="unidirectional path tracer: camera sample -> its pixel"),
    IntegratorKind("volpath", True, True, note="path tracer with media: camera sample -> its pixel"),
    IntegratorKind("volpathmis", True, True, note="spectral-MIS volumetric path tracer: per pixel"),
    IntegratorKind("direct", True, False, note="direct illumination only: per pixel, no depth"),
    IntegratorKind("depth", True, False, note="distance to the first hit: per pixel"),
    IntegratorKind("aov", True, False, nests=True, note="arbitrary output variables: per pixel"),
    IntegratorKind("moment", True, False, nests=True, note="mean and second moment of its children"),
    IntegratorKind("stokes", True, False, nests=True, note="Stokes vector of its child (polarized variants)"),
    IntegratorKind("prb", True, True, note="path replay (differentiable) path tracer: per pixel"),
    IntegratorKind("prb_basic", True, True, note="basic path replay: per pixel"),
    IntegratorKind("prbvolpath", True, True, note="path replay with media: per pixel"),
    IntegratorKind("prb_projective", True, True, note="projective path replay: per pixel in a forward render"),
    IntegratorKind("direct_projective", True, False, note="projective direct illumination: per pixel"),
    IntegratorKind("volprim_rf_basic", True, True, note="volumetric primitives radiance field: per pixel"),
    IntegratorKind("ptracer", False, True,
                   note="particle tracer: light paths splat anywhere on the film, a crop loses them"),
)}


def kind(name: str) -> IntegratorKind:
    """The catalogue entry of a plugin name; an unknown (third-party) one is not split, to be safe."""
    return CATALOGUE.get(name) or IntegratorKind(
        name, False, False, note="not one of Mitsuba 3.9's integrators: rendered whole, to be safe")


def scene_element(root: etree._Element) -> etree._Element | None:
    """The scene's top-level `<integrator>` (None: Mitsuba's default, a `path` tracer)."""
    return root.find("integrator")


def walk(elem: etree._Element | None) -> Iterator[etree._Element]:
    """The integrator element and every integrator nested in it, outermost first."""
    if elem is None:
        return
    yield elem
    for child in elem:
        if isinstance(child.tag, str) and child.tag == "integrator":
            yield from walk(child)


def types(elem: etree._Element | None) -> list[str]:
    """Plugin types of the integrator tree, outermost first (`["path"]` when the scene names none)."""
    return [e.get("type", "") for e in walk(elem)] or [DEFAULT_TYPE]


def describe(elem: etree._Element | None) -> str:
    """`moment(path)`, `aov(path, path)`, `path`: the tree as one readable name."""
    if elem is None:
        return DEFAULT_TYPE
    children = [describe(c) for c in elem if isinstance(c.tag, str) and c.tag == "integrator"]
    name = elem.get("type", "?")
    return f"{name}({', '.join(children)})" if children else name


def parameter_names(elem: etree._Element | None) -> list[str]:
    """The named parameters of the integrator tree (`hide_emitters`, `rr_depth`, a nested integrator's
    own), each once, but `max_depth`: what an override by a bare type leaves behind (the depth goes on)."""
    names = (c.get("name") for e in walk(elem) for c in e
             if isinstance(c.tag, str) and c.tag != "integrator" and c.get("name") not in (None, "max_depth"))
    return list(dict.fromkeys(names))


def splittable(elem: etree._Element | None) -> tuple[bool, str]:
    """(can the integrator tree be rendered as tiles, why). A crop renders a window of the film with the
    same sample positions, so a tile equals that region of a full render only when each camera sample
    writes to its own pixel (and its filter footprint): every sampling integrator does. The particle
    tracer (`ptracer`) splats light paths wherever they land on the film, so it is rendered whole."""
    for name in types(elem):
        entry = kind(name)
        if not entry.splittable:
            return False, f"{name}: {entry.note}"
    return True, "every integrator in it writes each sample to its own pixel"


def depth_of(elem: etree._Element | None) -> int | None:
    """The scene's `max_depth` over its depth-bearing integrators (-1 unbounded); None when none takes one."""
    if elem is None:
        return -1  # Mitsuba's default path tracer, unbounded
    depths = [_depth_value(e) for e in walk(elem) if kind(e.get("type", "")).depth]
    if not depths:
        return None
    return -1 if -1 in depths else max(depths)


def shallower(a: int, b: int) -> int:
    """The smaller of two max_depth values, -1 meaning unbounded."""
    return b if a == -1 else a if b == -1 else min(a, b)


def _depth_value(elem: etree._Element) -> int:
    for child in elem:
        if child.tag == "integer" and child.get("name") == "max_depth":
            raw = child.get("value", "-1")
            try:
                return int(raw)
            except ValueError as exc:
                raise SceneError(f"integrator {elem.get('type')!r}: max_depth {raw!r} is not an integer") from exc
    return -1


def with_depth(elem: etree._Element | None, depth: int) -> str:
    """The integrator tree as a standalone XML string at `depth` (the rest exactly as written, includes and
    `$parameters` already resolved; a unit that keeps its depth renders the scene's own object): the deepest
    depth-bearing integrators in it (those at `depth_of`) get max_depth = depth, and a shallower nested one
    keeps its own unless `depth` is less (an aov's direct child at 2 stays at 2 when its path sibling is
    cut to 6, or set from -1 to 20 by --depth). Private attributes of the XML reader are dropped."""
    tree = etree.Element("integrator", type=DEFAULT_TYPE) if elem is None else _clean_copy(elem)
    tree.set("version", "3.0.0")
    deepest = depth_of(tree)
    for e in walk(tree):
        if not kind(e.get("type", "")).depth:
            continue
        new = _depth_in_tree(_depth_value(e), deepest, int(depth))
        for child in [c for c in e if c.tag == "integer" and c.get("name") == "max_depth"]:
            e.remove(child)
        etree.SubElement(e, "integer", name="max_depth", value=str(new))
    if tree.find(".//ref") is not None:
        raise SceneError(f"integrator {describe(elem)}: refers to objects by id (<ref>); its depth cannot be "
                         "changed per unit, render at level off or give --depth")
    return etree.tostring(tree, encoding="unicode")


def radiance_xml(elem: etree._Element | None, depth: int) -> str:
    """The first integrator of the tree that renders radiance itself (not a wrapper such as moment or aov),
    at the depth the whole tree at `depth` gives it (`with_depth`), as standalone XML: what a pre-pass
    estimates cost and noise with."""
    leaf = next((e for e in walk(elem) if not kind(e.get("type", "")).nests), None)
    if leaf is None or elem is None or not kind(leaf.get("type", "")).depth:
        return with_depth(leaf, depth)
    return with_depth(leaf, _depth_in_tree(_depth_value(leaf), depth_of(elem), depth))


def _depth_in_tree(own: int, deepest: int | None, depth: int) -> int:
    """The max_depth an integrator of its own `own` takes when its tree, whose deepest is `deepest`, is
    given `depth`: the deepest take it, a shallower one keeps its own unless `depth` is less."""
    return depth if own == deepest else shallower(own, depth)


def _clean_copy(elem: etree._Element) -> etree._Element:
    copy = etree.fromstring(etree.tostring(elem))
    for e in copy.iter():
        if not isinstance(e.tag, str):
            continue
        for key in [k for k in e.attrib if k.startswith("{")]:
            del e.attrib[key]
    etree.cleanup_namespaces(copy)
    return copy
