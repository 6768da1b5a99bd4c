"""Scene files: what a scene is (`SceneSpec`: a file plus `-D` parameters), loading it into Mitsuba,
and reading facts from its XML without loading it (image size, film filter, files it references).

The XML reader follows Mitsuba's own rules (core.scene.resolver): `<default name value>` sets a parameter
unless `-D` already did, `$name` is substituted in attribute values, `<include filename>` is expanded in
place (at most 15 levels), and file names are looked up as Mitsuba's file resolver does (the scene's
folder, `<path>` entries, the working directory, then the `-a` search paths of the SceneSpec).
"""

from __future__ import annotations

import copy
import dataclasses
import importlib.util
import re
import tempfile
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lxml import etree

from core import mitsuba_env
from core.errors import QuekaroError, SceneError, did_you_mean, without_locations
from core.image import film as film_mod
from core.model.job import FILM_COLOURS, RGB, ImageFile, SceneSpec
from core.scene import resolver
from core.scene.bundle import scene_members
from core.scene.resolver import SRC_ATTR, parse_xml

# Mitsuba and Dr.Jit are imported where used: `import mitsuba` costs ~0.35 s and 85 MB, must follow the
# variant choice (core.mitsuba_env), and processes that never render must not pay for it.

__all__ = ["SRC_ATTR", "parse_xml"]

_NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")

# Mitsuba's defaults when the XML does not say: hdrfilm 768x576, gaussian filter (stddev 0.5, radius 4 sd).
DEFAULT_SIZE = (768, 576)
DEFAULT_FILTER = "gaussian"
_FILTER_RADIUS = {"box": 0.5, "tent": 1.0, "mitchell": 2.0, "catmullrom": 2.0}


@dataclass(frozen=True)
class FilmInfo:
    """The film of a scene's sensor: the image it renders (its crop window: `width` x `height` at
    `offset` in the film, the whole film unless the scene crops it) and its reconstruction filter."""

    width: int
    height: int
    filter_type: str
    filter_radius: float
    offset: tuple[int, int] = (0, 0)
    colour: tuple[str, ...] = RGB  # the colour channels its pixel format writes (core.model.job.FILM_COLOURS)
    image_file: ImageFile = field(default_factory=ImageFile)  # the file its image is written to


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
    """Load the scene into Mitsuba (variant set first if given, else the current one or the default); with
    the spec's `rfilter`, its films reconstruct with that filter instead of their own (`filtered_copy`)."""
    import mitsuba as mi

    if variant is not None or mi.variant() is None:
        mitsuba_env.init(variant or mitsuba_env.DEFAULT_VARIANT, threads)
    elif threads is not None:
        mitsuba_env.init(mi.variant(), threads)
    resolver.check_scene_file(spec.path)
    if spec.rfilter is None:
        return _load_file(spec.path, spec)
    with tempfile.TemporaryDirectory(prefix="quekaro-filter-") as folder:  # Mitsuba reads every file at load
        return _load_file(filtered_copy(spec, Path(folder)), spec)


def _load_file(path: Path, spec: SceneSpec) -> Any:
    """`mi.load_file` of `path` with the spec's parameters and search folders."""
    import drjit as dr
    import mitsuba as mi

    # Loading deadlocks when Dr.Jit's pool has one thread (seen with matpreview's envmap, serial or
    # parallel loader alike): load with two threads, then give the caller back its thread count.
    threads_before = dr.thread_count()
    if threads_before < 2:
        dr.set_thread_count(2)
    resolver = mi.file_resolver()
    before = [str(resolver[i]) for i in range(len(resolver))]
    for folder in spec.search_paths:  # as Mitsuba's `-a`: searched after everything else
        resolver.append(str(folder))
    try:
        return mi.load_file(str(path), **spec.defines)
    except RuntimeError as exc:
        raise SceneError(f"{spec.path}: {mitsuba_message(exc)}") from exc
    finally:
        resolver.clear()
        for folder in before:
            resolver.append(folder)
        if threads_before < 2:
            dr.set_thread_count(threads_before)


_UNKNOWN_PLUGIN = re.compile(r'Plugin "([^"]+)" not found')


def mitsuba_message(exc: Exception) -> str:
    """Mitsuba's error as a user reads it: no C++ source locations, and for an unknown plugin type the
    closest one Mitsuba has."""
    text = without_locations(str(exc))
    unknown = _UNKNOWN_PLUGIN.search(text)
    if unknown:
        text += did_you_mean(unknown.group(1), plugin_names())
    return text


def plugin_names() -> list[str]:
    """The plugin types Mitsuba ships (its plugins folder's libraries), without importing it."""
    spec = importlib.util.find_spec("mitsuba")  # once imported, its alias module's: the same folder
    if spec is None or not spec.origin:
        return []
    return sorted({lib.name.split(".")[0] for lib in (Path(spec.origin).parent / "plugins").glob("*.so")})


def check_parameters(spec: SceneSpec) -> None:
    """Refuse a -D parameter the scene never uses (Mitsuba would, at load: "unused parameters"), listing
    those it does, before anything is packed or rendered."""
    resolver.check_parameters(read(spec), spec.defines)


def filtered_copy(spec: SceneSpec, folder: Path) -> Path:
    """The scene laid out in `folder` as its bundle would hold it (core.scene.bundle.scene_members: every
    file it reads, the XML naming them), each film's reconstruction filter replaced by a plain
    `spec.rfilter`, wherever the film is (an included file's too); the main file's path. SceneError where
    no file of the scene holds a film."""
    films = 0
    for name, content in scene_members(spec.path, spec.defines, spec.search_paths).items():
        target = folder / name
        target.parent.mkdir(parents=True, exist_ok=True)
        if not name.endswith(".xml"):
            target.symlink_to(Path(content).resolve())
            continue
        root = etree.fromstring(content) if isinstance(content, bytes) else parse_xml(content)
        films += _replace_filters(root, spec.rfilter)
        target.write_bytes(etree.tostring(root, xml_declaration=True, encoding="utf-8"))
    if not films:
        raise SceneError(f"{spec.path}: no <film> in the scene's files (Mitsuba's default one cannot take another "
                         f"reconstruction filter): give the sensor a film to use {spec.rfilter}")
    return folder / spec.path.name


def _replace_filters(root: etree._Element, rfilter: str) -> int:
    """Replace each sensor's film's <rfilter> in `root` by a plain `rfilter`; how many films it changed."""
    films = [film for sensor in root.iter("sensor") for film in sensor.findall("film")]
    for film in films:
        for old in film.findall("rfilter"):
            film.remove(old)
        etree.SubElement(film, "rfilter", type=rfilter)
    return len(films)


# ---- reading the XML -------------------------------------------------------------------------


def read(spec: SceneSpec) -> resolver.SceneFiles:
    """The scene's XML files and every file reference, resolved as Mitsuba does (core.scene.resolver)."""
    return resolver.read_scene(spec.path, spec.defines, spec.search_paths, cwd=Path.cwd())


@dataclass
class ExpandedXml:
    """The scene XML with includes merged and parameters substituted."""

    root: etree._Element
    params: dict[str, str]
    includes: list[Path]


def expand(spec: SceneSpec) -> ExpandedXml:
    """Parse the scene file, expanding `<include>` and substituting `$name` as Mitsuba does."""
    files = read(spec)
    root = copy.deepcopy(files.trees[files.main])
    _splice(root, files)
    includes = [r.target for r in files.references if r.kind == "include"]
    return ExpandedXml(root, files.params, includes)


def _splice(root: etree._Element, files: resolver.SceneFiles) -> None:
    """Replace each `<include>` (in a copy) by the children of the file it resolved to, recursively."""
    targets = {(r.file, r.line, r.name): r.target for r in files.references if r.kind == "include"}
    for elem in [e for e in root.iter("include")]:
        key = (Path(elem.get(SRC_ATTR, "")), elem.sourceline or 0, elem.get("filename", ""))
        sub = copy.deepcopy(files.trees[targets[key]])
        _splice(sub, files)
        parent = elem.getparent()
        index = parent.index(elem)
        parent.remove(elem)
        for offset, child in enumerate(list(sub)):
            parent.insert(index + offset, child)


def referenced_files(spec: SceneSpec) -> list[Path]:
    """Every file the scene needs besides itself: includes, meshes, textures, envmaps, spectra.

    Absolute, without duplicates, in the order Mitsuba resolves them; a missing file is a SceneError
    naming the XML file, the line and every folder searched.
    """
    return read(spec).files()


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


def _replaced_filter(rfilter: str) -> tuple[str, float] | None:
    """A replacing filter's type and radius at its defaults (None where only the loaded film can say)."""
    return (rfilter, _FILTER_RADIUS[rfilter]) if rfilter in _FILTER_RADIUS else None


def sensor_of(scene: Any, index: int, where: str = "scene") -> Any:
    """The loaded scene's sensor `index` (Mitsuba's `-s`), or a SceneError saying how many there are (a
    scene file may have none: Mitsuba then loads it but has nothing to render)."""
    sensors = scene.sensors()
    if not sensors:
        raise SceneError(f"{where}: the scene has no sensor (Mitsuba renders nothing without one)")
    if not 0 <= index < len(sensors):
        raise SceneError(f"{where}: sensor {index} asked for, the scene has {len(sensors)} (0..{len(sensors) - 1})")
    return sensors[index]


def film_info_from_scene(scene: Any, sensor: int = 0) -> FilmInfo:
    """Film facts of a loaded Mitsuba scene (sensor `sensor`); its `image_file` is Mitsuba's default, as a
    loaded film does not say which file it writes (`film_info` reads that from the XML)."""
    film = sensor_of(scene, sensor).film()
    width, height = (int(v) for v in film.crop_size())
    rfilter = film.rfilter()
    name = rfilter.class_name().lower().removesuffix("filter")
    offset = tuple(int(v) for v in film.crop_offset())
    film.prepare([])  # the bitmap's channels are the pixel format's; nothing is rendered
    bitmap = film.bitmap()
    names = film_mod.bitmap_names(bitmap)
    colour = film_mod.colour_of(names) or names
    return FilmInfo(width, height, name, float(rfilter.radius()), (offset[0], offset[1]), colour)


def sensor_elements(root: etree._Element) -> list[etree._Element] | None:
    """The scene's top-level sensors, in the order Mitsuba numbers them (`-s N`); None where a shape
    carries a sensor (an irradiance meter): Mitsuba numbers those among the others in an order that the
    XML does not show, so the loaded scene must say."""
    children = [e for e in root if isinstance(e.tag, str)]
    if any(e.tag == "shape" and e.find("sensor") is not None for e in children):
        return None
    return [e for e in children if e.tag == "sensor"]


def film_info(spec: SceneSpec, sensor: int = 0) -> FilmInfo:
    """Image size and filter of the scene's sensor `sensor`, read from the XML (loads it when unsure)."""
    root = expand(spec).root
    sensors = sensor_elements(root)
    if sensors is None:
        return _loaded_film_info(spec, sensor, _one_image_file(root, spec.path), f"of sensor {sensor}")
    if sensor < 0 or (sensors and sensor >= len(sensors)) or (not sensors and sensor > 0):
        raise SceneError(f"{spec.path}: sensor {sensor} asked for, the scene declares {len(sensors)} "
                         f"top-level sensor(s) (0..{max(len(sensors), 1) - 1})")
    element = sensors[sensor] if sensors else None
    film = element.find("film") if element is not None else None
    width = _int_property(film, "width", DEFAULT_SIZE[0]) if film is not None else DEFAULT_SIZE[0]
    height = _int_property(film, "height", DEFAULT_SIZE[1]) if film is not None else DEFAULT_SIZE[1]
    filt = _filter_from_xml(film) if spec.rfilter is None else _replaced_filter(spec.rfilter)
    image_file = _image_file_from_xml(film, spec.path)
    crop, colour = None, _colour_from_xml(film, image_file)
    if film is None:
        crop = (0, 0), (DEFAULT_SIZE[0], DEFAULT_SIZE[1])
    elif width is not None and height is not None:
        crop = _crop_from_xml(film, width, height)
    if width is None or height is None or filt is None or crop is None or colour is None:
        kind = film.get("type", "hdrfilm") if film is not None else "hdrfilm"
        return _loaded_film_info(spec, sensor, image_file, kind)
    if width < 1 or height < 1:
        raise SceneError(f"{spec.path}: film size {width}x{height} must be at least 1x1")
    (x, y), (w, h) = crop
    if w < 1 or h < 1 or x < 0 or y < 0 or x + w > width or y + h > height:
        raise SceneError(f"{spec.path}: film crop window {w}x{h} at ({x}, {y}) (crop_width, crop_height, "
                         f"crop_offset_x, crop_offset_y) does not fit in the film's {width}x{height}")
    return FilmInfo(w, h, filt[0], filt[1], (x, y), colour, image_file)


def _loaded_film_info(spec: SceneSpec, sensor: int, image_file: ImageFile, film: str) -> FilmInfo:
    """`film_info` from the loaded scene, where the XML does not say plainly; a film whose colour
    quekaro cannot compose is refused, naming the film (`film`: its type, or whose it is) and channels."""
    loaded = load(spec)
    sensor_of(loaded, sensor, str(spec.path))
    info = dataclasses.replace(film_info_from_scene(loaded, sensor), image_file=image_file)
    if film_mod.colour_of(info.colour) != info.colour:
        raise SceneError(f"{spec.path}: film {film} writes channels {list(info.colour)[:8]}; quekaro composes "
                         "films whose colour is R, G, B; X, Y, Z or Y (hdrfilm's pixel formats), so render "
                         "this one with plain Mitsuba")
    return info


def _one_image_file(root: etree._Element, path: Path) -> ImageFile:
    """The file every film of the scene writes, where the XML cannot tell which film a sensor number
    has (`sensor_elements`); films asking for different files are refused, naming them."""
    files = {_image_file_from_xml(film, path) for film in root.iter("film")} or {ImageFile()}
    if len(files) > 1:
        asked = ", ".join(sorted(f"{f.format} {f.component}" for f in files))
        raise SceneError(f"{path}: a shape carries a sensor, so Mitsuba numbers the sensors in an order the XML "
                         f"does not show, and the films ask for different files ({asked}); give them one "
                         "file_format and component_format")
    return files.pop()


def _string_property(parent: etree._Element, name: str) -> str | None:
    values = [c.get("value", "") for c in parent if c.tag == "string" and c.get("name") == name]
    return values[0] if values else None


def _image_file_from_xml(film: etree._Element | None, path: Path) -> ImageFile:
    """The file hdrfilm writes its image to (`file_format`, `component_format`, any case, as Mitsuba reads
    them; its defaults where the XML is silent or the film is another kind)."""
    if film is None or film.get("type", "hdrfilm") != "hdrfilm":
        return ImageFile()
    fmt = (_string_property(film, "file_format") or "openexr").lower()
    component = (_string_property(film, "component_format") or "float16").lower()
    try:
        return ImageFile(fmt, component)
    except QuekaroError as exc:
        raise SceneError(f"{path}: film hdrfilm (file_format {fmt!r}, component_format {component!r}): "
                         f"{exc}") from exc


def _colour_from_xml(film: etree._Element | None, image_file: ImageFile) -> tuple[str, ...] | None:
    """The colour channels of the film's pixel format (Mitsuba's default rgb); None where the XML does
    not say plainly (a parameter, a film other than hdrfilm, a format this table lacks)."""
    if film is None:
        return RGB
    if film.get("type", "hdrfilm") != "hdrfilm":
        return None
    pixel_format = (_string_property(film, "pixel_format") or "rgb").lower()
    fmt = image_file.format
    if fmt == "rgbe" or (fmt == "pfm" and pixel_format not in ("rgb", "luminance")):
        pixel_format = "rgb"  # Mitsuba overrides a pixel format these files cannot hold
    return FILM_COLOURS.get(pixel_format)


def _crop_from_xml(film: etree._Element, width: int, height: int) -> tuple[tuple[int, int], tuple[int, int]] | None:
    """((offset x, y), (width, height)) of the film's crop window, Mitsuba's defaults where the XML is
    silent (no offset, the whole film's size); None when a value is an unresolved parameter."""
    values = [_int_property(film, name, default) for name, default in
              (("crop_offset_x", 0), ("crop_offset_y", 0), ("crop_width", width), ("crop_height", height))]
    if None in values:
        return None
    x, y, w, h = values
    return (x, y), (w, h)


def image_size(spec: SceneSpec, sensor: int = 0) -> tuple[int, int]:
    """(width, height) of the image the scene renders through sensor `sensor` (its film's crop window)."""
    info = film_info(spec, sensor)
    return info.width, info.height
