"""Scene bundles: one archive holding a scene file and every file it references, and its safe unpacking.

A bundle is an uncompressed POSIX tar: `QUEKARO-MANIFEST.json` first (each member's size and sha256), then
the scene at the top and each file it reads (beside it, or at `files/<16 hex>/<its name>`), the XML
rewritten to name those members. Bundles are byte-for-byte deterministic, so their sha256 names them.
Entry points: `make_bundle`, `extract_bundle` (which assumes a hostile archive), `check_unpacked`,
`check_rules`.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import re
import shutil
import tarfile
import tempfile
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import IO, Any

from lxml import etree

from core.errors import SceneError
from core.model.hashing import sha256_file
from core.rules.unit_params import Planner
from core.scene.resolver import Reference, SceneFiles, check_scene_file, parse_xml, read_scene
from fuzzy.errors import RuleFileError

MANIFEST_NAME = "QUEKARO-MANIFEST.json"
FORMAT = "quekaro-bundle"
VERSION = 2
RULES_NAME = "QUEKARO-RULES.xml"
MAX_MANIFEST_BYTES = 4 << 20
_CHUNK = 1 << 20
_PARAM_RE = re.compile(r"\$([A-Za-z_][A-Za-z0-9_]*)")
_SHA256_RE = re.compile(r"[0-9a-f]{64}")
MAX_NAME_CHARS = 4096  # a submitted path in the manifest (PATH_MAX)
MAX_SEARCH_PATHS = 64


class BundleError(SceneError):
    """A bundle that cannot be made (bad reference) or must not be unpacked (hostile or corrupt)."""


@dataclass(frozen=True)
class BundleLimits:
    """Bounds on what one bundle may hold; the defaults fit real scenes with large textures."""

    max_bundle_bytes: int = 2 << 30
    max_file_bytes: int = 1 << 30
    max_files: int = 10_000


@dataclass(frozen=True)
class BundleInfo:
    """A bundle written to disk: where, its sha256, the scene's name inside it, and its members."""

    path: Path
    sha256: str
    size: int
    scene: str
    files: dict[str, int] = field(default_factory=dict)


# ---- making ----------------------------------------------------------------------------------


def _member_name(target: Path, root: Path) -> str:
    """Files in the scene's folder keep their place; others go to files/<hash of their path>/<name>."""
    if target.resolve().is_relative_to(root.resolve()):
        return target.resolve().relative_to(root.resolve()).as_posix()
    return f"files/{hashlib.sha256(str(target).encode()).hexdigest()[:16]}/{target.name}"


def scene_members(scene_path: Path, defines: dict[str, str] | None = None,
                  search_paths: tuple[Path, ...] = ()) -> dict[str, bytes | Path]:
    """Member name -> content (rewritten XML as bytes, other files by path) for the scene and every file
    it reads.

    Files are found as Mitsuba finds them (core.scene.resolver: `<path>`, includes, `-a`, absolute names,
    files outside the scene's folder too: the submitter owns them). A missing file is refused, naming the
    XML file, the line and every folder searched. The XML loses its `<path>`s and names the members, so the
    unpacked scene reads exactly the files the original read, and nothing outside the bundle."""
    scene = Path(os.path.abspath(scene_path))
    check_scene_file(scene_path, BundleError)
    try:
        found = read_scene(scene, {str(k): str(v) for k, v in (defines or {}).items()}, search_paths,
                           cwd=Path.cwd())
    except SceneError as exc:
        raise BundleError(str(exc)) from exc
    names = {found.main: scene.name}
    for ref in found.references:
        if ref.kind != "path":
            names.setdefault(ref.target, _member_name(ref.target, scene.parent))
    raw = {path: parse_xml(path, BundleError) for path in found.trees}  # as written, `$names` and all
    changed = {ref.file for ref in found.references if _rewrite(ref, raw[ref.file], names,
                                                                 _lookup_base(ref, found, names))}
    members: dict[str, bytes | Path] = {}
    for target, name in names.items():  # an XML file whose references stay as written is packed as is
        members[name] = etree.tostring(raw[target], xml_declaration=True, encoding="utf-8") \
            if target in changed else target
    return members


def _lookup_base(ref: Reference, found: SceneFiles, names: dict[Path, str]) -> PurePosixPath:
    """The bundle folder Mitsuba will look the rewritten name up in first (no `<path>`s are left): the
    including file's folder for an include; for a spectrum file, the folder of the file that included
    the one naming it; the scene's folder for every other file (they are looked up after parsing)."""
    owner = ref.file if ref.kind == "include" else found.includers.get(ref.file) if ref.kind == "spectrum" else None
    return PurePosixPath(names[owner]).parent if owner is not None else PurePosixPath(".")


def _rewrite(ref: Reference, raw_root: Any, names: dict[Path, str], base: PurePosixPath) -> bool:
    """Point the reference, in the file as written, at its member (found from `base`); whether it changed."""
    elem = raw_root.xpath(ref.element.getroottree().getpath(ref.element))[0]
    if ref.kind == "path":
        elem.getparent().remove(elem)  # every file it found is now named by its member
        return True
    attr = "filename" if ref.kind in ("include", "spectrum") else "value"
    new = PurePosixPath(os.path.relpath(names[ref.target], base.as_posix())).as_posix()
    if new == elem.get(attr):
        return False
    _keep_parameters(elem, raw_root, elem.get(attr, ""))
    elem.set(attr, new)
    return True


def _keep_parameters(elem: Any, root: Any, written: str) -> None:
    """Mitsuba refuses a -D parameter that nothing uses: when a rewritten name held `$x`, a `<default>`
    that uses it keeps it in use (put after the element's top-level ancestor, where `$x` is known)."""
    top = elem
    while top.getparent() is not None and top.getparent() is not root:
        top = top.getparent()
    for name in dict.fromkeys(_PARAM_RE.findall(written)):
        keeper = f"quekaro_keeps_{name}"
        if not root.xpath(f"default[@name='{keeper}']"):
            top.addnext(etree.Element("default", name=keeper, value=f"${name}"))


def _tarinfo(name: str, size: int) -> tarfile.TarInfo:
    """A member's header with zeroed times and owners, so that a bundle is deterministic."""
    info = tarfile.TarInfo(name)
    info.size, info.mode, info.mtime = size, 0o644, 0
    info.uid = info.gid = 0
    info.uname = info.gname = ""
    return info


def _entry(name: str, content: bytes | Path, limits: BundleLimits) -> dict[str, Any]:
    if isinstance(content, bytes):
        return {"path": name, "size": len(content), "sha256": hashlib.sha256(content).hexdigest()}
    size = content.stat().st_size  # checked before reading, so a huge file costs nothing
    if size > limits.max_file_bytes:
        raise BundleError(f"{content}: {size} bytes, over the per-file limit {limits.max_file_bytes}")
    return {"path": name, "size": size, "sha256": sha256_file(content)}


def make_bundle(scene_path: str | Path, defines: dict[str, str] | None, out: str | Path,
                limits: BundleLimits | None = None, search_paths: tuple[Path, ...] = (),
                rules: Path | None = None) -> BundleInfo:
    """Write the bundle of `scene_path` (with its `-D` parameters, `-a` search paths and, if given, the
    job's rule file) to `out`; return what was written.

    The manifest holds: format, version, the scene's name, its `-D` parameters, the rule file if any, the
    size and sha256 of every other member (sorted by name), `scene_sha256` (the scene as the submitter
    wrote it, which seeds the job's pre-pass as `quekaro render` of that file would) and `submitted`
    (where the scene and `-a` folders were, which the job's report names). Files over the limits are
    refused."""
    limits = limits or BundleLimits()
    members = scene_members(Path(scene_path), defines, tuple(search_paths))
    if rules is not None:
        check_rules(Path(rules))
        members[RULES_NAME] = Path(rules).read_bytes()
    if len(members) > limits.max_files:
        raise BundleError(f"{scene_path}: reads {len(members)} files, over the limit {limits.max_files}")
    entries = [_entry(name, members[name], limits) for name in sorted(members)]
    manifest = {"format": FORMAT, "version": VERSION, "scene": Path(scene_path).name,
                "defines": {str(k): str(v) for k, v in (defines or {}).items()}, "files": entries,
                "rules": RULES_NAME if rules is not None else None, "scene_sha256": sha256_file(scene_path),
                "submitted": {"path": str(scene_path), "search_paths": [str(p) for p in search_paths]}}
    blob = json.dumps(manifest, sort_keys=True, indent=1).encode()
    out = Path(out)
    tmp = out.with_name(f".{out.name}.{os.getpid()}.part")
    try:
        with tarfile.open(tmp, "w", format=tarfile.PAX_FORMAT) as tar:
            tar.addfile(_tarinfo(MANIFEST_NAME, len(blob)), io.BytesIO(blob))
            for entry in entries:
                content = members[entry["path"]]
                with (io.BytesIO(content) if isinstance(content, bytes) else content.open("rb")) as fh:
                    tar.addfile(_tarinfo(entry["path"], entry["size"]), fh)
        size = tmp.stat().st_size
        if size > limits.max_bundle_bytes:
            raise BundleError(f"{scene_path}: bundle is {size} bytes, over the limit "
                              f"{limits.max_bundle_bytes}")
        os.replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)
    return BundleInfo(out, bundle_hash(out), size, manifest["scene"], {e["path"]: e["size"] for e in entries})


def check_rules(path: Path, defuzzifier: str | None = None, what: str = "--rules") -> None:
    """Refuse (naming the file, line, variable and label) a rule file a planner cannot use: at submit, on
    the submitter's side and again on the master's."""
    try:
        Planner(path, defuzzifier)
    except (RuleFileError, ValueError) as exc:
        raise BundleError(f"{what}: {exc}") from exc


def check_unpacked(scene: Path, defines: dict[str, str]) -> None:
    """Refuse an unpacked scene that would read any file outside its bundle folder (naming the reference),
    before anything outside is looked at."""
    try:
        read_scene(scene, defines, (), cwd=None, within=Path(scene).parent)
    except SceneError as exc:
        raise BundleError(f"bundle scene: {exc}") from exc


def bundle_hash(data: bytes | str | Path) -> str:
    """Hex sha256 of a bundle given as bytes or as a file."""
    if isinstance(data, bytes | bytearray | memoryview):
        return hashlib.sha256(data).hexdigest()
    return sha256_file(Path(data))


# ---- unpacking -------------------------------------------------------------------------------


def _check_name(name: str) -> PurePosixPath:
    path = PurePosixPath(name)
    parts = name.split("/")
    if (not name or path.is_absolute() or "\\" in name or "\x00" in name
            or any(p in ("", ".", "..") for p in parts)):
        raise BundleError(f"bundle member {name!r}: unsafe path "
                          "(absolute, '..', '.', empty part or backslash)")
    return path


def _check_member(member: tarfile.TarInfo, dest: Path) -> None:
    """Refuse a member unless it passes both `tarfile.data_filter` (the standard library's vetted check
    against absolute names, escapes, links and devices) and our stricter checks: regular files and
    directories only, no `..`, `.` or empty path parts."""
    if not (member.isreg() or member.isdir()):
        kind = "link" if member.issym() or member.islnk() else "device or special file"
        raise BundleError(f"bundle member {member.name!r}: is a {kind}; bundles hold regular files only")
    if member.issparse():  # its holes unpack to disk the upload never paid for (a 10 KiB tar, 300 MiB here)
        raise BundleError(f"bundle member {member.name!r}: is a sparse file; bundles hold plain tar members only")
    _check_name(member.name)
    try:
        tarfile.data_filter(member, str(dest))
    except tarfile.FilterError as exc:
        raise BundleError(f"bundle member {member.name!r}: refused by tarfile's data filter ({exc})") from exc


def _read_manifest(tar: tarfile.TarFile, member: tarfile.TarInfo | None, dest: Path) -> dict:
    if member is None or member.name != MANIFEST_NAME or not member.isreg():
        raise BundleError(f"bundle does not start with {MANIFEST_NAME}")
    _check_member(member, dest)
    if member.size > MAX_MANIFEST_BYTES:
        raise BundleError(f"bundle manifest is {member.size} bytes, over {MAX_MANIFEST_BYTES}")
    try:
        raw = tar.extractfile(member).read()
        manifest = json.loads(raw)
        files = {e["path"]: (int(e["size"]), str(e["sha256"])) for e in manifest["files"]}
        scene = manifest["scene"]
        ok = manifest.get("format") == FORMAT and manifest.get("version") == VERSION
    except (ValueError, KeyError, TypeError) as exc:
        raise BundleError(f"bundle manifest is malformed ({exc})") from exc
    if not ok:
        raise BundleError(f"bundle manifest: unknown format/version {manifest.get('format')!r}/"
                          f"{manifest.get('version')!r} (expected {FORMAT!r}/{VERSION})")
    if not isinstance(scene, str) or scene not in files:
        raise BundleError(f"bundle manifest: scene {scene!r} is not among its files")
    if manifest.get("rules") not in (None, RULES_NAME) or (manifest.get("rules") and RULES_NAME not in files):
        raise BundleError(f"bundle manifest: rules {str(manifest.get('rules'))[:60]!r} is not {RULES_NAME!r} "
                          "among its files")
    stated = manifest.get("scene_sha256")
    if stated is not None and not (isinstance(stated, str) and _SHA256_RE.fullmatch(stated)):
        raise BundleError(f"bundle manifest: scene_sha256 {str(stated)[:80]!r} is not a sha256 (64 hex digits)")
    if not _submitted_ok(manifest.get("submitted", {"path": scene, "search_paths": []})):
        raise BundleError(f"bundle manifest: submitted {str(manifest.get('submitted'))[:80]!r} is not the "
                          f"submitter's scene path and -a folders (strings of at most {MAX_NAME_CHARS} characters, "
                          f"at most {MAX_SEARCH_PATHS} folders)")
    # Kept beside the files so that the unpacked folder says what it is (read_manifest).
    (dest / MANIFEST_NAME).write_bytes(raw)
    return {"scene": scene, "files": files}


def _copy_member(src: IO[bytes], target: Path, size: int, sha256: str, name: str) -> None:
    """Copy a member ourselves (not `extractall`), checking its length and hash as it is written, into a
    file opened with O_EXCL|O_NOFOLLOW."""
    target.parent.mkdir(parents=True, exist_ok=True)
    try:
        fd = os.open(target, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o644)
    except OSError as exc:
        raise BundleError(f"bundle member {name!r}: cannot be created ({exc.strerror})") from exc
    digest, written = hashlib.sha256(), 0
    with os.fdopen(fd, "wb") as out:
        while chunk := src.read(min(_CHUNK, size - written + 1)):
            written += len(chunk)
            if written > size:
                break
            digest.update(chunk)
            out.write(chunk)
    if written != size or digest.hexdigest() != sha256:
        raise BundleError(f"bundle member {name!r}: content does not match the manifest "
                          f"({written} bytes, expected {size} with sha256 {sha256[:12]}..)")


def _unpack(tar: tarfile.TarFile, work: Path, limits: BundleLimits) -> str:
    manifest = _read_manifest(tar, tar.next(), work)
    files, seen, total, count = manifest["files"], set(), 0, 0
    while (member := tar.next()) is not None:
        count += 1
        if count > limits.max_files:
            raise BundleError(f"bundle holds more than {limits.max_files} members")
        _check_member(member, work)
        if member.isdir():
            continue
        if member.name in seen:
            raise BundleError(f"bundle member {member.name!r}: appears twice")
        if member.name not in files or files[member.name][0] != member.size:
            raise BundleError(f"bundle member {member.name!r}: not in the manifest with size {member.size}")
        if member.size > limits.max_file_bytes:
            raise BundleError(f"bundle member {member.name!r}: {member.size} bytes, over the per-file "
                              f"limit {limits.max_file_bytes}")
        total += member.size
        if total > limits.max_bundle_bytes:
            raise BundleError(f"bundle unpacks to more than {limits.max_bundle_bytes} bytes")
        seen.add(member.name)
        _copy_member(tar.extractfile(member), work / member.name, member.size, files[member.name][1],
                     member.name)
    missing = sorted(set(files) - seen)
    if missing:
        raise BundleError(f"bundle lacks files its manifest lists: {', '.join(missing[:5])}")
    return manifest["scene"]


def extract_bundle(data: bytes | str | Path, dest: str | Path, limits: BundleLimits | None = None) -> Path:
    """Unpack a bundle (bytes or a file) into the new folder `dest`; return the scene file's path.

    Raises BundleError naming the member at fault; on any error `dest` is not created. A tar, not a zip:
    an uncompressed tar cannot be a decompression bomb, since what it unpacks is bounded by its own size,
    checked first. Members are checked against the manifest (no duplicates; per-file, total and count
    limits) and written to a fresh folder that is renamed into place only once everything checked out.
    """
    limits = limits or BundleLimits()
    dest = Path(dest)
    if dest.exists():
        raise BundleError(f"{dest}: already exists; bundles unpack into a new folder")
    size = len(data) if isinstance(data, bytes | bytearray) else Path(data).stat().st_size
    if size > limits.max_bundle_bytes:
        raise BundleError(f"bundle is {size} bytes, over the limit {limits.max_bundle_bytes}")
    dest.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f".{dest.name}.", dir=dest.parent))
    try:
        source = io.BytesIO(data) if isinstance(data, bytes | bytearray) else open(data, "rb")  # noqa: SIM115
        with source, tarfile.open(fileobj=source, mode="r:") as tar:
            scene = _unpack(tar, work, limits)
        os.rename(work, dest)
    except tarfile.TarError as exc:
        raise BundleError(f"bundle is not a readable uncompressed tar ({exc})") from exc
    finally:
        if work.exists():
            shutil.rmtree(work)
    return dest / scene


def read_manifest(bundle_dir: str | Path) -> dict:
    """The manifest of an unpacked bundle (scene name, defines, files)."""
    return json.loads((Path(bundle_dir) / MANIFEST_NAME).read_text())


def _submitted_ok(submitted: Any) -> bool:
    if not isinstance(submitted, dict) or set(submitted) != {"path", "search_paths"}:
        return False
    names = [submitted["path"], *(submitted["search_paths"] if isinstance(submitted["search_paths"], list) else [0])]
    return len(names) <= MAX_SEARCH_PATHS + 1 and all(isinstance(n, str) and len(n) <= MAX_NAME_CHARS for n in names)


def submitted_scene(scene: Path) -> dict[str, Any]:
    """Where an unpacked bundle's scene was on the submitter's side: its path and `-a` folders as given
    (its manifest's `submitted`, checked when unpacked), else its name in the bundle and none."""
    return read_manifest(scene.parent).get("submitted") or {"path": scene.name, "search_paths": []}


def submitted_scene_sha256(scene: Path) -> str:
    """The sha256 of an unpacked bundle's scene file as the submitter wrote it (its manifest's
    `scene_sha256`, checked when unpacked), else of the unpacked file (a bundle made before it was kept)."""
    return read_manifest(scene.parent).get("scene_sha256") or sha256_file(scene)
