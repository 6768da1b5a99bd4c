"""Finding every file a scene reads, exactly as Mitsuba 3.9's parser and file resolver find them.

`read_scene(main, defines, search_paths, cwd)` reads the scene file and its includes and returns
`SceneFiles`: each XML tree, parameters substituted, and every `Reference` resolved. Like Mitsuba it keeps
a list of search folders, and `lookup` takes the first that has the file; `_visit` says which list each
kind of reference is looked up in.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from lxml import etree

from core.errors import SceneError, did_you_mean

MAX_INCLUDE_DEPTH = 15
SRC_ATTR = "{urn:quekaro}src"  # private attribute: which file an element came from
RESOLVED_ATTR = "{urn:quekaro}resolved"  # private attribute: the file a spectrum's filename resolved to
_PARAM_RE = re.compile(r"\$([A-Za-z_][A-Za-z0-9_]*)")
# What an XML 1.0 document can hold (its Char production): a -D value is written into the scene's attributes.
_NOT_XML = re.compile("[^\t\n\r\x20-\ud7ff\ue000-\ufffd\U00010000-\U0010ffff]")


@dataclass
class Reference:
    """One file named in the XML: where, how (include, spectrum, file, path) and what it resolved to."""

    file: Path
    line: int
    kind: str
    name: str
    target: Path
    element: etree._Element


@dataclass
class SceneFiles:
    """The scene's XML files as read (parameters substituted, each file its own tree) and every reference."""

    main: Path
    trees: dict[Path, etree._Element] = field(default_factory=dict)
    references: list[Reference] = field(default_factory=list)
    params: dict[str, str] = field(default_factory=dict)
    includers: dict[Path, Path] = field(default_factory=dict)  # included file -> the file including it
    referenced: set[str] = field(default_factory=set)  # the `$name`s written in the files: the -D Mitsuba takes
    within: Path | None = None  # a folder no reference may leave (an unpacked bundle's)

    def files(self) -> list[Path]:
        """Every file the scene reads besides the main one (folders of `<path>` excluded), in order."""
        return list(dict.fromkeys(r.target for r in self.references if r.kind != "path"))


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


def lookup(name: str, folders: Sequence[Path]) -> Path | None:
    """Mitsuba's FileResolver.resolve: an absolute name as is, else the first folder holding it."""
    candidate = Path(name)
    if candidate.is_absolute():
        return candidate if candidate.exists() else None
    for folder in folders:
        if (folder / candidate).exists():
            return folder / candidate
    return None


def read_scene(main: Path, defines: dict[str, str], search_paths: Sequence[Path] = (),
               cwd: Path | None = None, within: Path | None = None) -> SceneFiles:
    """Read the scene file and everything it includes; resolve every reference (SceneError if one fails,
    naming the file, the line and every folder searched). With `within`, a reference that could lead
    outside that folder is refused before any file or folder it names is looked at: what lies outside
    (whether a file exists, whether it parses) is never told.

    The first list is the scene's folder, the working directory, then the `-a` paths. Plain `filename`s
    (meshes, textures, envmaps, volume grids, measured BSDFs) are looked up last, as Mitsuba does when it
    builds the plugins after reading all the XML: with the main file's final list, whichever file named it."""
    main = Path(main).absolute()
    check_scene_file(main)
    check_defines(defines)
    found = SceneFiles(main, params=dict(defines), within=None if within is None else Path(within).resolve())
    top = [main.parent, *([cwd] if cwd is not None else []), *(Path(p).absolute() for p in search_paths)]
    deferred: list[tuple[Path, etree._Element, str]] = []
    _read_file(main, top, found, deferred, [])
    for file, elem, name in deferred:
        found.references.append(_resolved(file, elem, "file", name, top, found.within))
    return found


def check_scene_file(path: Path, error: type[SceneError] = SceneError) -> None:
    """`error` unless `path` is a file: a folder, or nothing, named as such."""
    if Path(path).is_dir():
        raise error(f"{path}: a folder, not a scene file (give the XML file in it)")
    if not Path(path).is_file():
        raise error(f"{path}: scene file not found")


def check_parameters(found: SceneFiles, defines: Iterable[str]) -> None:
    """SceneError naming a -D parameter that no file of the scene uses as `$name` (Mitsuba refuses it at
    load, "unused parameters"), with the parameters the scene does use."""
    for name in sorted(set(defines) - found.referenced):
        known = sorted(found.referenced)
        listed = f"its parameters: {', '.join(known)}" if known else "it takes no parameters"
        raise SceneError(f"-D {name}: {found.main.name} has no parameter {name}"
                         f"{did_you_mean(name, known)}; {listed}")


def check_defines(defines: dict[str, str]) -> None:
    """SceneError naming the -D parameter whose value holds a character no XML file can (a NUL, a control)."""
    for name, value in defines.items():
        bad = _NOT_XML.search(str(value))
        if bad:
            raise SceneError(f"-D {name}: its value {str(value)[:40]!r} holds {bad.group()!r}, which no XML file can")


def _read_file(path: Path, folders: list[Path], found: SceneFiles,
               deferred: list[tuple[Path, etree._Element, str]], stack: list[Path]) -> None:
    """Read one XML file: `$name` is substituted in every attribute, and a `<default>` sets a parameter
    from its place on, shared with includes, as Mitsuba does."""
    if len(stack) > MAX_INCLUDE_DEPTH:
        raise SceneError(f"{path}: includes nested deeper than {MAX_INCLUDE_DEPTH} levels")
    if path in stack:
        raise SceneError(f"{path}: includes itself (through {' -> '.join(map(str, stack))})")
    root = parse_xml(path)
    found.trees.setdefault(path, root)
    for elem in root.iter():
        if not isinstance(elem.tag, str):
            continue
        for key, value in elem.attrib.items():
            found.referenced.update(_PARAM_RE.findall(value))
            elem.set(key, _PARAM_RE.sub(lambda m: found.params.get(m.group(1), m.group(0)), value))
        elem.set(SRC_ATTR, str(path))
        _visit(elem, path, root, folders, found, deferred, stack)


def _visit(elem: etree._Element, path: Path, root: etree._Element, folders: list[Path], found: SceneFiles,
           deferred: list[tuple[Path, etree._Element, str]], stack: list[Path]) -> None:
    """One element, as Mitsuba reads it. `<path value>` (a child of the root only): beside the XML file,
    else through the folders; it then goes first in the list of the file being read. `<include filename>`:
    looked up with the including file's folder first, and read with that list (a copy: its own `<path>`s
    end with it). `<spectrum filename>`: looked up now, in the list of the file being read. Any other
    `filename` waits until all the XML is read (read_scene)."""
    if elem.tag == "default":
        found.params.setdefault(elem.get("name", ""), elem.get("value", ""))
    elif elem.tag == "path":
        if elem.getparent() is not root:
            raise SceneError(f"{path}:{elem.sourceline}: <path> can only be a child of the root")
        ref = _path_folder(elem, path, folders, found.within)
        found.references.append(ref)
        folders.insert(0, ref.target)
    elif elem.tag == "include":
        scope = [path.parent, *folders]
        ref = _resolved(path, elem, "include", elem.get("filename") or "", scope, found.within)
        found.references.append(ref)
        found.includers.setdefault(ref.target, path)
        _read_file(ref.target, scope, found, deferred, [*stack, path])
    elif elem.tag == "spectrum" and elem.get("filename"):
        ref = _resolved(path, elem, "spectrum", elem.get("filename", ""), folders, found.within)
        found.references.append(ref)
        elem.set(RESOLVED_ATTR, str(ref.target))  # readers of the expanded XML need not resolve it again
    elif elem.get("name") == "filename" and elem.get("value") is not None and elem.tag == "string":
        deferred.append((path, elem, elem.get("value", "")))


def _resolved(file: Path, elem: etree._Element, kind: str, name: str, folders: Sequence[Path],
              within: Path | None = None) -> Reference:
    where = f"{file}:{elem.sourceline}"
    if not name:
        raise SceneError(f"{where}: <{elem.tag}> names no file")
    if "$" in name:
        raise SceneError(f"{where}: file name {name!r} uses an undefined parameter")
    _refuse_outside(where, name, [Path(name)] if Path(name).is_absolute() else [f / name for f in folders], within)
    target = lookup(name, folders)
    if target is None or not target.is_file():
        searched = (", ".join(dict.fromkeys(str(f) for f in folders)) if not Path(name).is_absolute()
                    else "(absolute name)")
        what = "file" if kind == "file" else f"{kind} file"
        raise SceneError(f"{where}: {what} {name!r} not found; searched: {searched}")
    return Reference(file, elem.sourceline or 0, kind, name, Path(os.path.normpath(target.absolute())), elem)


def _refuse_outside(where: str, name: str, candidates: Sequence[Path], within: Path | None) -> None:
    """SceneError if a place `name` may resolve to lies outside `within` (resolved): each candidate is
    resolved as the file system would reach it, links followed and `..` taken where it leads, whether
    or not it exists."""
    for candidate in candidates if within is not None else ():
        if not candidate.absolute().resolve().is_relative_to(within):
            raise SceneError(f"{where}: reference {name!r} leads outside the bundle")


def _path_folder(elem: etree._Element, file: Path, folders: Sequence[Path], within: Path | None = None) -> Reference:
    value = elem.get("value", "")
    absolute = Path(value).is_absolute()
    _refuse_outside(f"{file}:{elem.sourceline}", value,
                    [Path(value)] if absolute else [file.parent / value, *(f / value for f in folders)], within)
    target = Path(value) if absolute else file.parent / value
    if not target.exists():
        target = lookup(value, folders) or target
    if not target.is_dir():
        raise SceneError(f"{file}:{elem.sourceline}: <path>: folder {value!r} not found; searched: "
                         f"{', '.join(str(f) for f in [file.parent, *folders])}")
    return Reference(file, elem.sourceline or 0, "path", value, Path(os.path.normpath(target.absolute())), elem)
