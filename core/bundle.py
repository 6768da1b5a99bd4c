"""Scene bundles: one archive holding a scene file and every file it references, and its safe unpacking.

Format: an uncompressed POSIX tar whose first member is `QUEKARO-MANIFEST.json` (format, version, the
scene's relative name, its `-D` parameters, and the size and sha256 of every other member), followed by
the files under their names relative to the scene's folder. Nothing in the scene is rewritten, so the
unpacked scene loads exactly as the original.

Making a bundle refuses, naming the XML file and the reference at fault: absolute references (they
would read the agent's own files), references that escape the scene's folder (lexically with `..` or
through a symbolic link), missing files and files over the size limit. Bundles are byte-for-byte
deterministic (sorted names, zeroed times and owners), so their sha256 names them.

Unpacking assumes a hostile archive. It uses `tarfile` (not zip) because an uncompressed tar cannot be a
decompression bomb: everything unpacked is bounded by the archive's own size, which is checked first.
Each member goes through `tarfile.data_filter` (the standard library's vetted check against absolute
names, escapes, links and devices) and through stricter checks of ours: regular files and directories
only, no `..`, `.` or empty path parts, no duplicates, per-file, total and count limits, and exact
agreement with the manifest. Data is copied by us (not `extractall`) so that its hash and length are
checked while it is written; files are opened with O_EXCL|O_NOFOLLOW into a fresh folder that is
renamed into place only once everything checked out, so a refused bundle leaves nothing behind.
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
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import IO

from core.errors import SceneError
from core.hashing import sha256_file
from core.scene import parse_xml

MANIFEST_NAME = "QUEKARO-MANIFEST.json"
FORMAT = "quekaro-bundle"
VERSION = 1
MAX_INCLUDE_DEPTH = 15
MAX_MANIFEST_BYTES = 4 << 20
_CHUNK = 1 << 20
_PARAM_RE = re.compile(r"\$([A-Za-z_][A-Za-z0-9_]*)")


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


# ---- finding what a scene references ---------------------------------------------------------


def _references(path: Path, params: dict[str, str], depth: int) -> Iterator[tuple[Path, str, bool]]:
    """(referring file, file name as written after `$` substitution, is-include) in document order."""
    if depth > MAX_INCLUDE_DEPTH:
        raise BundleError(f"{path}: includes nested deeper than {MAX_INCLUDE_DEPTH} levels")
    for elem in parse_xml(path, BundleError).iter():
        if not isinstance(elem.tag, str):
            continue
        if elem.tag == "default":
            params.setdefault(elem.get("name", ""), elem.get("value", ""))
            continue
        name = None
        if elem.tag == "include" or (elem.tag == "spectrum" and elem.get("filename")):
            name = elem.get("filename")
        elif elem.get("name") == "filename":
            name = elem.get("value")
        if name:
            yield path, _PARAM_RE.sub(lambda m: params.get(m.group(1), m.group(0)), name), \
                elem.tag == "include"


def _locate(name: str, referrer: Path, root: Path) -> Path:
    """The lexical path of a reference: beside the referring file if there, else beside the scene file
    (Mitsuba's lookup order, as in core.scene); refused when absolute or outside `root`."""
    if "$" in name:
        raise BundleError(f"{referrer}: file name {name!r} uses an undefined parameter")
    if PurePosixPath(name).is_absolute() or Path(name).is_absolute() or "\\" in name:
        raise BundleError(f"{referrer}: reference {name!r} is an absolute path; bundles hold only "
                          f"files named relative to the scene's folder {root}")
    candidates = [Path(os.path.normpath(base / name)) for base in (referrer.parent, root)]
    target = next((c for c in candidates if c.exists()), candidates[-1])
    if not target.is_relative_to(root):
        raise BundleError(f"{referrer}: reference {name!r} escapes the scene's folder {root}")
    if not target.is_file():
        raise BundleError(f"{referrer}: referenced file {name!r} not found (looked for {target})")
    if not target.resolve().is_relative_to(root.resolve()):
        raise BundleError(f"{referrer}: reference {name!r} is a link to {target.resolve()}, "
                          f"outside the scene's folder {root}")
    return target


def scene_members(scene_path: Path, defines: dict[str, str] | None = None) -> dict[str, Path]:
    """Relative name -> file for the scene and everything it references (includes followed)."""
    scene = Path(os.path.abspath(scene_path))
    if not scene.is_file():
        raise BundleError(f"{scene_path}: scene file not found")
    root = scene.parent
    members = {scene.name: scene}
    params = {str(k): str(v) for k, v in (defines or {}).items()}
    stack = [(scene, 0)]
    while stack:
        current, depth = stack.pop()
        for referrer, name, is_include in _references(current, params, depth):
            target = _locate(name, referrer, root)
            rel = target.relative_to(root).as_posix()
            if rel == MANIFEST_NAME:
                raise BundleError(f"{referrer}: reference {name!r} collides with the bundle manifest")
            if is_include and rel not in members:
                stack.append((target, depth + 1))
            members.setdefault(rel, target)
    _cross_check(scene, defines, members)
    return members


def _cross_check(scene: Path, defines: dict[str, str] | None, members: dict[str, Path]) -> None:
    # core.scene reads the same XML for rendering; a file it needs that this walk missed would make a
    # bundle that fails on every agent, so say so here instead.
    from core.scene import SceneSpec, referenced_files

    ours = {p.resolve() for p in members.values()}
    try:
        needed = referenced_files(SceneSpec(scene, defines or {}))
    except BundleError:
        raise
    except SceneError as exc:
        raise BundleError(str(exc)) from exc
    missed = [p for p in needed if p.resolve() not in ours]
    if missed:
        raise BundleError(f"{scene}: references {', '.join(map(str, missed))} that the bundle would not hold")


# ---- making ----------------------------------------------------------------------------------


def _tarinfo(name: str, size: int) -> tarfile.TarInfo:
    info = tarfile.TarInfo(name)
    info.size, info.mode, info.mtime = size, 0o644, 0
    info.uid = info.gid = 0
    info.uname = info.gname = ""
    return info


def make_bundle(scene_path: str | Path, defines: dict[str, str] | None, out: str | Path,
                limits: BundleLimits | None = None) -> BundleInfo:
    """Write the bundle of `scene_path` (with its `-D` parameters) to `out`; return what was written."""
    limits = limits or BundleLimits()
    members = scene_members(Path(scene_path), defines)
    if len(members) > limits.max_files:
        raise BundleError(f"{scene_path}: references {len(members)} files, over the limit {limits.max_files}")
    entries = []
    for rel in sorted(members):
        size = members[rel].stat().st_size  # checked before reading, so a huge file costs nothing
        if size > limits.max_file_bytes:
            raise BundleError(f"{members[rel]}: {size} bytes, over the per-file limit "
                              f"{limits.max_file_bytes}")
        entries.append({"path": rel, "size": size, "sha256": sha256_file(members[rel])})
    manifest = {"format": FORMAT, "version": VERSION, "scene": Path(scene_path).name,
                "defines": {str(k): str(v) for k, v in (defines or {}).items()}, "files": entries}
    blob = json.dumps(manifest, sort_keys=True, indent=1).encode()
    out = Path(out)
    tmp = out.with_name(f".{out.name}.{os.getpid()}.part")
    try:
        with tarfile.open(tmp, "w", format=tarfile.PAX_FORMAT) as tar:
            tar.addfile(_tarinfo(MANIFEST_NAME, len(blob)), io.BytesIO(blob))
            for entry in entries:
                with members[entry["path"]].open("rb") as fh:
                    tar.addfile(_tarinfo(entry["path"], entry["size"]), fh)
        size = tmp.stat().st_size
        if size > limits.max_bundle_bytes:
            raise BundleError(f"{scene_path}: bundle is {size} bytes, over the limit "
                              f"{limits.max_bundle_bytes}")
        os.replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)
    return BundleInfo(out, bundle_hash(out), size, manifest["scene"], {e["path"]: e["size"] for e in entries})


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
    if not (member.isreg() or member.isdir()):
        kind = "link" if member.issym() or member.islnk() else "device or special file"
        raise BundleError(f"bundle member {member.name!r}: is a {kind}; bundles hold regular files only")
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
    # Kept beside the files so that the unpacked folder says what it is (read_manifest).
    (dest / MANIFEST_NAME).write_bytes(raw)
    return {"scene": scene, "files": files}


def _copy_member(src: IO[bytes], target: Path, size: int, sha256: str, name: str) -> None:
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

    Raises BundleError naming the member at fault; on any error `dest` is not created.
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
