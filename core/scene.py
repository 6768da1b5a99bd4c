"""Scene files: what a scene is (`SceneSpec`: a file plus `-D` parameters), loading it into Mitsuba,
and reading facts from its XML without loading it (image size, film filter, files it references).

The XML reader follows Mitsuba's own rules where they matter here: `<default name value>` sets a
parameter unless `-D` already did, `$name` is substituted in attribute values, `<include filename>`
is expanded in place (at most 15 levels), and a relative file name is looked up beside the file that
names it, then beside the main scene file.
"""

from __future__ import annotations

import copy
import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lxml import etree

from core.errors import SceneError

MAX_INCLUDE_DEPTH = 15
_NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_PARAM_RE = re.compile(r"\$([A-Za-z_][A-Za-z0-9_]*)")
# Private attribute marking which file an element came from once includes are merged.
SRC_ATTR = "{urn:quekaro}src"

# Mitsuba's defaults when the XML does not say: hdrfilm 768x576, gaussian filter (stddev 0.5, radius 4 sd).
DEFAULT_SIZE = (768, 576)
DEFAULT_FILTER = "gaussian"
_FILTER_RADIUS = {"box": 0.5, "tent": 1.0, "mitchell": 2.0, "catmullrom": 2.0}


@dataclass(frozen=True)
class SceneSpec:
    """A scene to render: its XML file and the `-D name=value` parameters it is loaded with."""

    path: Path
    defines: dict[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "path", Path(self.path))
        object.__setattr__(self, "defines", {str(k): str(v) for k, v in dict(self.defines).items()})

    def __hash__(self) -> int:
        return hash(self.key())

    def key(self) -> tuple[str, tuple[tuple[str, str], ...]]:
        """A hashable identity: the resolved path and the sorted parameters."""
        return str(self.path.resolve()), tuple(sorted(self.defines.items()))

    def with_defines(self, **extra: Any) -> SceneSpec:
        """The same scene with some parameters added or replaced."""
        return SceneSpec(self.path, {**self.defines, **{k: str(v) for k, v in extra.items()}})

    def to_dict(self) -> dict[str, Any]:
        return {"path": str(self.path), "defines": dict(self.defines)}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> SceneSpec:
        if not isinstance(data, dict) or "path" not in data:
            raise SceneError(f"scene spec must be an object with a 'path', got {data!r}")
        defines = data.get("defines") or {}
        if not isinstance(defines, dict):
            raise SceneError(f"scene spec field 'defines' must be an object, got {defines!r}")
        return cls(Path(data["path"]), defines)


@dataclass(frozen=True)
class FilmInfo:
    """The film of a scene's first sensor: image size and reconstruction filter."""

    width: int
    height: int
    filter_type: str
    filter_radius: float


def parse_defines(items: Iterable[str] | None) -> dict[str, str]:
    """`["spp=16", "res=64"]` -> `{"spp": "16", "res": "64"}`, as Mitsuba's `-D`; clear errors otherwise."""
    out: dict[str, str] = {}
    for item in items or ():
        name, sep, value = item.partition("=")
        name = name.strip()
        if not sep:
            raise SceneError(f"-D {item!r}: expected NAME=VALUE")
        if not _NAME_RE.match(name):
            raise SceneError(f"-D {item!r}: {name!r} is not a parameter name (letters, digits, _)")
        if name in out and out[name] != value:
            raise SceneError(f"-D {name} given twice with different values ({out[name]!r}, {value!r})")
        out[name] = value
    return out


def load(spec: SceneSpec, variant: str | None = None, threads: int | None = None) -> Any:
    """Load the scene into Mitsuba (variant set first if given, else the current one or the default)."""
    import mitsuba as mi

    from core import mitsuba_env

    if variant is not None or mi.variant() is None:
        mitsuba_env.init(variant or mitsuba_env.DEFAULT_VARIANT, threads)
    elif threads is not None:
        mitsuba_env.init(mi.variant(), threads)
    path = spec.path
    if not path.is_file():
        raise SceneError(f"{path}: scene file not found")
    import drjit as dr

    # Loading deadlocks when Dr.Jit's pool has one thread (seen with matpreview's envmap, serial or
    # parallel loader alike): load with two threads, then give the caller back its thread count.
    threads_before = dr.thread_count()
    if threads_before < 2:
        dr.set_thread_count(2)
    try:
        return mi.load_file(str(path), **spec.defines)
    except RuntimeError as exc:
        raise SceneError(f"{path}: {exc}") from exc
    finally:
        if threads_before < 2:
            dr.set_thread_count(threads_before)


# ---- reading the XML -------------------------------------------------------------------------


def parse_xml(path: Path, error: type[SceneError] = SceneError) -> etree._Element:
    """One scene XML file, parsed safely: scene files may come from strangers (bundles), so no entity
    expansion, no DTD, no network, no huge trees. Failures raise `error` naming the file."""
    parser = etree.XMLParser(resolve_entities=False, no_network=True, load_dtd=False, huge_tree=False,
                             remove_comments=True)
    try:
        return etree.parse(str(path), parser).getroot()
    except OSError as exc:
        raise error(f"{path}: cannot read ({exc})") from exc
    except etree.XMLSyntaxError as exc:
        raise error(f"{path}: not well-formed XML ({exc})") from exc


def _substitute(text: str, params: dict[str, str]) -> str:
    return _PARAM_RE.sub(lambda m: params.get(m.group(1), m.group(0)), text)


def resolve_reference(name: str, referrer: Path, main: Path) -> Path:
    """A file named in the XML: beside the file naming it, else beside the main scene, else as given."""
    candidate = Path(name)
    if candidate.is_absolute():
        return candidate
    for base in (referrer.parent, main.parent):
        if (base / candidate).exists():
            return (base / candidate).resolve()
    return (main.parent / candidate).resolve()


@dataclass
class ExpandedXml:
    """The scene XML with includes merged and parameters substituted."""

    root: etree._Element
    params: dict[str, str]
    includes: list[Path]


def expand(spec: SceneSpec) -> ExpandedXml:
    """Parse the scene file, expanding `<include>` and substituting `$name` as Mitsuba does."""
    main = spec.path.resolve()
    if not main.is_file():
        raise SceneError(f"{spec.path}: scene file not found")
    params = dict(spec.defines)
    includes: list[Path] = []
    root = _expand_file(main, main, params, includes, [])
    return ExpandedXml(root, params, includes)


def _expand_file(path: Path, main: Path, params: dict[str, str], includes: list[Path],
                 stack: list[Path]) -> etree._Element:
    if len(stack) > MAX_INCLUDE_DEPTH:
        raise SceneError(f"{path}: includes nested deeper than {MAX_INCLUDE_DEPTH} levels")
    if path in stack:
        raise SceneError(f"{path}: includes itself (through {' -> '.join(map(str, stack))})")
    root = parse_xml(path)
    for elem in list(root.iter()):
        if not isinstance(elem.tag, str):
            continue
        for key, value in elem.attrib.items():
            elem.set(key, _substitute(value, params))
        elem.set(SRC_ATTR, str(path))
        if elem.tag == "default":
            params.setdefault(elem.get("name", ""), elem.get("value", ""))
        elif elem.tag == "include":
            _splice_include(elem, path, main, params, includes, [*stack, path])
    return root


def _splice_include(elem: etree._Element, path: Path, main: Path, params: dict[str, str],
                    includes: list[Path], stack: list[Path]) -> None:
    name = elem.get("filename")
    if not name:
        raise SceneError(f"{path}: <include> without a filename")
    target = resolve_reference(name, path, main)
    if not target.is_file():
        raise SceneError(f"{path}: included file {name!r} not found (looked for {target})")
    includes.append(target)
    sub = _expand_file(target, main, params, includes, stack)
    parent = elem.getparent()
    index = parent.index(elem)
    parent.remove(elem)
    for offset, child in enumerate(list(sub)):
        parent.insert(index + offset, copy.deepcopy(child))


def _source(elem: etree._Element) -> Path:
    return Path(elem.get(SRC_ATTR, "."))


def _file_values(root: etree._Element) -> Iterator[tuple[etree._Element, str]]:
    for elem in root.iter():
        if not isinstance(elem.tag, str):
            continue
        if elem.get("name") == "filename" and elem.get("value"):
            yield elem, elem.get("value", "")
        elif elem.tag == "spectrum" and elem.get("filename"):
            yield elem, elem.get("filename", "")


def referenced_files(spec: SceneSpec) -> list[Path]:
    """Every file the scene needs besides itself: includes, meshes, textures, envmaps, spectra.

    Absolute, resolved, without duplicates, in document order; a missing file is a SceneError
    naming the XML file that references it.
    """
    xml = expand(spec)
    main = spec.path.resolve()
    found: list[Path] = list(xml.includes)
    for elem, name in _file_values(xml.root):
        if "$" in name:
            raise SceneError(f"{_source(elem)}: file name {name!r} uses an undefined parameter")
        target = resolve_reference(name, _source(elem), main)
        if not target.is_file():
            raise SceneError(f"{_source(elem)}: referenced file {name!r} not found (looked for {target})")
        found.append(target)
    return list(dict.fromkeys(found))


def _int_property(parent: etree._Element, name: str, default: int) -> int | None:
    for child in parent:
        if child.tag == "integer" and child.get("name") == name:
            try:
                return int(child.get("value", ""))
            except ValueError:
                return None  # an unresolved $parameter: let Mitsuba decide
    return default


def _float_property(parent: etree._Element, name: str) -> float | None:
    for child in parent:
        if child.tag == "float" and child.get("name") == name:
            try:
                return float(child.get("value", ""))
            except ValueError:
                return None
    return None


def _filter_from_xml(film: etree._Element | None) -> tuple[str, float] | None:
    rfilter = film.find("rfilter") if film is not None else None
    ftype = rfilter.get("type", DEFAULT_FILTER) if rfilter is not None else DEFAULT_FILTER
    if ftype == "gaussian":
        stddev = _float_property(rfilter, "stddev") if rfilter is not None else None
        return ftype, 4.0 * (stddev if stddev is not None else 0.5)
    if ftype in _FILTER_RADIUS:
        radius = _float_property(rfilter, "radius") if rfilter is not None and ftype == "tent" else None
        return ftype, radius if radius is not None else _FILTER_RADIUS[ftype]
    return None


def film_info_from_scene(scene: Any) -> FilmInfo:
    """Film facts of a loaded Mitsuba scene (first sensor)."""
    film = scene.sensors()[0].film()
    width, height = (int(v) for v in film.size())
    rfilter = film.rfilter()
    name = rfilter.class_name().lower().removesuffix("filter")
    return FilmInfo(width, height, name, float(rfilter.radius()))


def film_info(spec: SceneSpec) -> FilmInfo:
    """Image size and filter of the scene's first sensor, read from the XML (loads it when unsure)."""
    root = expand(spec).root
    sensor = root.find("sensor")
    film = sensor.find("film") if sensor is not None else None
    width = _int_property(film, "width", DEFAULT_SIZE[0]) if film is not None else DEFAULT_SIZE[0]
    height = _int_property(film, "height", DEFAULT_SIZE[1]) if film is not None else DEFAULT_SIZE[1]
    filt = _filter_from_xml(film)
    if width is None or height is None or filt is None:
        return film_info_from_scene(load(spec))
    if width < 1 or height < 1:
        raise SceneError(f"{spec.path}: film size {width}x{height} must be at least 1x1")
    return FilmInfo(width, height, filt[0], filt[1])


def image_size(spec: SceneSpec) -> tuple[int, int]:
    """(width, height) of the image the scene renders."""
    info = film_info(spec)
    return info.width, info.height
