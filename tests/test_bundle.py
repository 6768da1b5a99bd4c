"""Scene bundles: real scenes round-trip and load in Mitsuba; hostile archives and references are refused."""

from __future__ import annotations

import hashlib
import io
import json
import os
import subprocess
import tarfile
from pathlib import Path

import numpy as np
import pytest

from core.scene.bundle import (
    MANIFEST_NAME,
    VERSION,
    BundleError,
    BundleLimits,
    bundle_hash,
    extract_bundle,
    make_bundle,
    read_manifest,
    submitted_scene,
    submitted_scene_sha256,
)

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "scenes" / "mitsuba-data"
needs_shared = pytest.mark.skipif(not SHARED.is_dir(), reason="../shared scenes absent")


# ---- helpers: hand-made archives -------------------------------------------------------------


def _manifest(files: dict[str, bytes], scene: str = "scene.xml") -> bytes:
    entries = [{"path": n, "size": len(d), "sha256": hashlib.sha256(d).hexdigest()} for n, d in files.items()]
    return json.dumps({"format": "quekaro-bundle", "version": VERSION, "scene": scene, "defines": {},
                       "files": entries}).encode()


def _tar(members: list[tuple[tarfile.TarInfo, bytes | None]]) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w", format=tarfile.PAX_FORMAT) as tar:
        for info, data in members:
            tar.addfile(info, io.BytesIO(data) if data is not None else None)
    return buf.getvalue()


def _reg(name: str, data: bytes) -> tuple[tarfile.TarInfo, bytes]:
    info = tarfile.TarInfo(name)
    info.size = len(data)
    return info, data


def _special(name: str, kind: bytes, linkname: str = "") -> tuple[tarfile.TarInfo, None]:
    info = tarfile.TarInfo(name)
    info.type, info.linkname = kind, linkname
    return info, None


SCENE = b"<scene version='3.0.0'/>"


def _bundle(extra: list[tuple[tarfile.TarInfo, bytes | None]],
            listed: dict[str, bytes] | None = None) -> bytes:
    listed = {"scene.xml": SCENE, **(listed or {})}
    return _tar([_reg(MANIFEST_NAME, _manifest(listed)), _reg("scene.xml", SCENE), *extra])


def _refused(data: bytes | Path, tmp_path: Path, match: str, limits: BundleLimits | None = None) -> None:
    dest = tmp_path / "out" / "bundle"
    with pytest.raises(BundleError, match=match):
        extract_bundle(data, dest, limits)
    assert not dest.exists()
    # Nothing left behind: no half-unpacked folder beside dest, nothing written outside.
    assert not list((tmp_path / "out").iterdir())
    assert not (tmp_path / "evil").exists()


# ---- real scenes -----------------------------------------------------------------------------


def _render(scene: Path, defines: dict[str, str]) -> np.ndarray:
    import mitsuba as mi

    from core import mitsuba_env

    # threads=1 deadlocks while loading matpreview (mitsuba 3.9: load_file never returns); 2 works.
    mitsuba_env.init("llvm_ad_rgb", threads=2)
    loaded = mi.load_file(str(scene), **defines)
    return np.array(mi.render(loaded, seed=7))


@needs_shared
@pytest.mark.parametrize(("scene", "defines", "expected"), [
    ("cbox/cbox-rgb.xml", {"res": "16", "spp": "2"},
     {"cbox-rgb.xml", "fragments/base.xml", "fragments/shapes.xml", "meshes/cbox_floor.obj"}),
    ("matpreview/matpreview.xml", {"width": "24", "height": "16", "spp": "2", "max_depth": "4"},
     {"matpreview.xml", "matpreview.serialized", "envmap.exr"}),
])
def test_real_scene_round_trip_renders_identically(tmp_path, scene, defines, expected):
    src = SHARED / scene
    info = make_bundle(src, defines, tmp_path / "b.tar")
    assert expected <= set(info.files)
    assert info.sha256 == bundle_hash(info.path.read_bytes())
    out = extract_bundle(info.path, tmp_path / "x")
    assert out == tmp_path / "x" / src.name
    assert read_manifest(out.parent)["defines"] == defines
    for rel in info.files:  # XML files are rewritten (their references); every other file is as it was
        if not rel.endswith(".xml"):
            assert (out.parent / rel).read_bytes() == (src.parent / rel).read_bytes()
    # The unpacked copy renders as the original (same seed, variant, threads); two renders of the same
    # file differ by ~2e-7 from the order of filter splats across threads, hence the tiny tolerance.
    np.testing.assert_allclose(_render(out, defines), _render(src, defines), rtol=1e-5, atol=1e-5)


@needs_shared
def test_bundles_are_deterministic(tmp_path):
    src = SHARED / "cbox" / "cbox-rgb.xml"
    a = make_bundle(src, {"res": "8"}, tmp_path / "a.tar")
    b = make_bundle(src, {"res": "8"}, tmp_path / "b.tar")
    c = make_bundle(src, {"res": "9"}, tmp_path / "c.tar")
    assert a.sha256 == b.sha256 != c.sha256


# ---- making: references --------------------------------------------------------------------


def _scene_with(tmp_path: Path, body: str) -> Path:
    folder = tmp_path / "scene"
    folder.mkdir(exist_ok=True)
    path = folder / "scene.xml"
    path.write_text(f"<scene version='3.0.0'>{body}</scene>")
    return path


def _shape(name: str) -> str:
    return f"<shape type='obj'><string name='filename' value='{name}'/></shape>"


def test_defaults_and_defines_choose_the_file(tmp_path):
    scene = _scene_with(tmp_path, "<default name='mesh' value='a'/>" + _shape("meshes/$mesh.obj"))
    (scene.parent / "meshes").mkdir()
    for n in "ab":
        (scene.parent / "meshes" / f"{n}.obj").write_text(n)
    assert set(make_bundle(scene, None, tmp_path / "1.tar").files) == {"scene.xml", "meshes/a.obj"}
    assert set(make_bundle(scene, {"mesh": "b"}, tmp_path / "2.tar").files) == {"scene.xml", "meshes/b.obj"}


@pytest.mark.parametrize(("body", "match"), [
    (_shape("missing.obj"), r":1: file 'missing.obj' not found; searched: .*scene"),
    (_shape("$nope.obj"), r"undefined parameter"),
    ("<include filename='nope.xml'/>", r"include file 'nope.xml' not found"),
    ("<path value='nowhere'/>", r"<path>: folder 'nowhere' not found"),
])
def test_bad_references_are_refused(tmp_path, body, match):
    scene = _scene_with(tmp_path, body)
    with pytest.raises(BundleError, match=match) as err:
        make_bundle(scene, None, tmp_path / "b.tar")
    assert str(scene) in str(err.value)  # names the file at fault
    assert not (tmp_path / "b.tar").exists()


def test_files_outside_the_scene_folder_are_packed_and_references_rewritten(tmp_path):
    """Absolute names, `..` and `<path>` folders outside the scene's folder: the submitter owns those
    files, so the bundle holds them, and the unpacked scene names them inside the bundle only."""
    (tmp_path / "common" / "include").mkdir(parents=True)
    (tmp_path / "common" / "include" / "x.xml").write_text(
        "<scene version='3.0.0'>" + _shape("meshes/m.obj") + "</scene>")
    (tmp_path / "common" / "meshes").mkdir()
    (tmp_path / "common" / "meshes" / "m.obj").write_text("m")
    (tmp_path / "abs.obj").write_text("abs")
    scene = _scene_with(tmp_path, "<path value='../common'/><include filename='include/x.xml'/>"
                        + _shape(str(tmp_path / "abs.obj")) + _shape("../abs.obj"))
    info = make_bundle(scene, None, tmp_path / "b.tar")
    out = extract_bundle(info.path, tmp_path / "x")
    from core.scene.bundle import check_unpacked
    from core.scene.resolver import read_scene

    check_unpacked(out, {})
    found = read_scene(out, {}, cwd=None)
    folder = out.parent.resolve()
    targets = {r.target.resolve() for r in found.references}
    assert all(t.is_relative_to(folder) for t in targets)
    assert sorted(t.read_text() for t in targets if t.suffix == ".obj") == ["abs", "m"]
    assert "<path" not in out.read_text()


def test_a_rewritten_scene_keeps_the_submitted_files_hash_that_seeds_its_pre_pass(tmp_path):
    """The master seeds a job's pre-pass from the scene file as submitted (as `quekaro render` of it does),
    not from the bundle's copy, which names the files it packed; a bundle without it seeds from its copy,
    and a manifest whose hash is no sha256 is refused."""
    (tmp_path / "common").mkdir()
    (tmp_path / "common" / "m.obj").write_text("m")
    scene = _scene_with(tmp_path, _shape("../common/m.obj"))
    out = extract_bundle(make_bundle(scene, None, tmp_path / "b.tar").path, tmp_path / "x")
    assert out.read_bytes() != scene.read_bytes()  # rewritten
    assert submitted_scene_sha256(out) == hashlib.sha256(scene.read_bytes()).hexdigest()
    kept = _tar([_reg(MANIFEST_NAME, _manifest({"scene.xml": SCENE})), _reg("scene.xml", SCENE)])
    old = extract_bundle(kept, tmp_path / "old")
    assert submitted_scene_sha256(old) == hashlib.sha256(SCENE).hexdigest()
    assert submitted_scene(out) == {"path": str(scene), "search_paths": []}  # the report names it so
    assert submitted_scene(old) == {"path": "scene.xml", "search_paths": []}  # its name in the bundle
    searched = extract_bundle(make_bundle(scene, None, tmp_path / "c.tar", search_paths=(tmp_path / "common",)).path,
                              tmp_path / "y")
    assert submitted_scene(searched)["search_paths"] == [str(tmp_path / "common")]
    for submitted in ({"path": 3, "search_paths": []}, {"path": "a.xml"}, {"path": "a" * 5000, "search_paths": []},
                      {"path": "a.xml", "search_paths": ["b"] * 65}, "a.xml"):
        manifest = json.loads(_manifest({"scene.xml": SCENE})) | {"submitted": submitted}
        bad = _tar([_reg(MANIFEST_NAME, json.dumps(manifest).encode()), _reg("scene.xml", SCENE)])
        with pytest.raises(BundleError, match=r"bundle manifest: submitted .* is not the submitter's scene path"):
            extract_bundle(bad, tmp_path / "bad")
    for stated in ("ab" * 31, "AB" * 32, 7, "../" * 30):
        manifest = json.loads(_manifest({"scene.xml": SCENE})) | {"scene_sha256": stated}
        bad = _tar([_reg(MANIFEST_NAME, json.dumps(manifest).encode()), _reg("scene.xml", SCENE)])
        with pytest.raises(BundleError, match=r"scene_sha256 .* is not a sha256"):
            extract_bundle(bad, tmp_path / "bad")
        assert not (tmp_path / "bad").exists()


OUTSIDE = ["<shape type='obj'><string name='filename' value='{}'/></shape>", "<include filename='{}'/>",
           "<path value='{}'/>", "<bsdf type='diffuse'><spectrum name='reflectance' filename='{}'/></bsdf>"]


@pytest.mark.parametrize("reference", ["/etc/hostname", "../../outside.obj", "../../missing.obj", "/no/such/file",
                                       "scene/../../outside.obj"])
@pytest.mark.parametrize("element", OUTSIDE, ids=["file", "include", "path", "spectrum"])
def test_an_unpacked_scene_that_reads_outside_its_bundle_is_refused_telling_nothing_of_what_is_there(
        tmp_path, reference, element):
    """The same refusal whether the file outside exists, is a folder or is missing, and before it is parsed:
    a submitter learns nothing of the master's files (an include used to parse them first)."""
    from core.scene.bundle import check_unpacked

    (tmp_path / "outside.obj").write_text("not XML")
    folder = tmp_path / "job" / "scene"
    folder.mkdir(parents=True)
    scene = folder / "scene.xml"
    scene.write_text(f"<scene version='3.0.0'>{element.format(reference)}</scene>")
    with pytest.raises(BundleError) as refused:
        check_unpacked(scene, {})
    assert str(refused.value) == f"bundle scene: {scene}:1: reference {reference!r} leads outside the bundle"


def test_a_bundle_reached_through_a_linked_folder_reads_its_own_files(tmp_path):
    """A master's home behind a link (a linked ~/.quekaro; /tmp on macOS): the bundle's own files are inside."""
    from core.scene.bundle import check_unpacked

    (tmp_path / "real").mkdir()
    scene = _scene_with(tmp_path / "real", _shape("inside.obj") + "<include filename='sub/inc.xml'/>")
    (scene.parent / "inside.obj").write_text("o")
    (scene.parent / "sub").mkdir()
    (scene.parent / "sub" / "inc.xml").write_text(f"<scene version='3.0.0'>{_shape('sub/../inside.obj')}</scene>")
    (tmp_path / "link").symlink_to(tmp_path / "real")
    check_unpacked(tmp_path / "link" / "scene" / "scene.xml", {})


def test_a_link_inside_the_bundle_to_a_file_outside_is_refused(tmp_path):
    from core.scene.bundle import check_unpacked

    (tmp_path / "outside.obj").write_text("secret")
    scene = _scene_with(tmp_path, _shape("inside.obj"))
    (scene.parent / "inside.obj").symlink_to(tmp_path / "outside.obj")
    with pytest.raises(BundleError, match=r"'inside\.obj' leads outside the bundle"):
        check_unpacked(scene, {})


def test_huge_referenced_file_is_refused_without_reading(tmp_path):
    scene = _scene_with(tmp_path, _shape("big.obj"))
    with (scene.parent / "big.obj").open("wb") as fh:
        fh.truncate(5 << 30)  # sparse: 5 GiB on paper, nothing on disk
    with pytest.raises(BundleError, match=r"big.obj: 5368709120 bytes, over the per-file limit"):
        make_bundle(scene, None, tmp_path / "b.tar")


def test_include_cycle_is_bounded(tmp_path):
    scene = _scene_with(tmp_path, "<include filename='a.xml'/>")
    (scene.parent / "a.xml").write_text("<scene version='3.0.0'><include filename='b.xml'/></scene>")
    (scene.parent / "b.xml").write_text("<scene version='3.0.0'><include filename='a.xml'/></scene>")
    with pytest.raises(BundleError, match="includes itself"):
        make_bundle(scene, None, tmp_path / "b.tar")


# ---- unpacking: hostile archives -------------------------------------------------------------


@pytest.mark.parametrize(("member", "match"), [
    (_reg("../evil/x", b"pwned"), r"'../evil/x': unsafe path"),
    (_reg("meshes/../../evil/x", b"pwned"), r"unsafe path"),
    (_reg("/tmp/evil-abs", b"pwned"), r"'/tmp/evil-abs': unsafe path"),
    (_reg("./scene2.xml", b"x"), r"unsafe path"),
    (_special("link", tarfile.SYMTYPE, "../evil"), r"'link': is a link"),
    (_special("inside-link", tarfile.SYMTYPE, "scene.xml"), r"is a link"),
    (_special("hard", tarfile.LNKTYPE, "scene.xml"), r"'hard': is a link"),
    (_special("dev", tarfile.CHRTYPE), r"'dev': is a device or special file"),
    (_special("fifo", tarfile.FIFOTYPE), r"device or special file"),
])
def test_hostile_members_are_refused(tmp_path, member, match):
    (tmp_path / "out").mkdir()
    _refused(_bundle([member]), tmp_path, match)


def test_a_sparse_member_is_refused(tmp_path):
    """A GNU sparse member's holes unpack to disk that the upload never carried: 64 MiB of zeros travel in
    a tar of a few KiB (GNU tar writes it; Python's tarfile reads it as a regular file)."""
    src = tmp_path / "src"
    src.mkdir()
    (src / MANIFEST_NAME).write_bytes(_manifest({"scene.xml": SCENE, "big.bin": bytes(64 << 20)}))
    (src / "scene.xml").write_bytes(SCENE)
    with (src / "big.bin").open("wb") as fh:
        fh.truncate(64 << 20)
    archive = tmp_path / "sparse.tar"
    subprocess.run(["tar", "--format=gnu", "--sparse", "-cf", str(archive), "-C", str(src), MANIFEST_NAME,
                    "scene.xml", "big.bin"], check=True)
    assert archive.stat().st_size < 64 << 10
    (tmp_path / "out").mkdir()
    _refused(archive, tmp_path, r"'big.bin': is a sparse file")


def test_member_not_in_manifest_or_tampered_or_missing(tmp_path):
    (tmp_path / "out").mkdir()
    _refused(_bundle([_reg("extra.obj", b"x")]), tmp_path, r"'extra.obj': not in the manifest")
    tampered = _tar([_reg(MANIFEST_NAME, _manifest({"scene.xml": SCENE})), _reg("scene.xml", SCENE[::-1])])
    _refused(tampered, tmp_path, r"'scene.xml': content does not match the manifest")
    _refused(_bundle([], listed={"mesh.obj": b"m"}), tmp_path, r"lacks files its manifest lists: mesh.obj")
    _refused(_bundle([_reg("scene.xml", SCENE)]), tmp_path, r"'scene.xml': appears twice")
    no_manifest = _tar([_reg("scene.xml", SCENE)])
    _refused(no_manifest, tmp_path, "does not start with")
    bad_scene = _tar([_reg(MANIFEST_NAME, _manifest({"scene.xml": SCENE}, scene="other.xml")),
                      _reg("scene.xml", SCENE)])
    _refused(bad_scene, tmp_path, r"scene 'other.xml' is not among its files")


def test_not_a_tar_compressed_or_garbage(tmp_path):
    import gzip

    (tmp_path / "out").mkdir()
    _refused(b"\x00garbage" * 300, tmp_path, "not a readable uncompressed tar|does not start with")
    _refused(gzip.compress(_bundle([])), tmp_path, "not a readable uncompressed tar")


def test_too_many_files(tmp_path):
    (tmp_path / "out").mkdir()
    files = {f"m/{i}.obj": b"v" for i in range(60)}
    data = _bundle([_reg(n, d) for n, d in files.items()], listed=files)
    _refused(data, tmp_path, "more than 50 members", BundleLimits(max_files=50))
    assert extract_bundle(data, tmp_path / "ok", BundleLimits(max_files=61)).name == "scene.xml"


def test_file_over_per_file_limit_streamed(tmp_path):
    (tmp_path / "out").mkdir()
    big = b"\0" * (2 << 20)
    data = _bundle([_reg("big.exr", big)], listed={"big.exr": big})
    _refused(data, tmp_path, r"'big.exr': 2097152 bytes, over the per-file limit",
             BundleLimits(max_file_bytes=1 << 20))
    _refused(data, tmp_path, r"bundle is \d+ bytes, over the limit", BundleLimits(max_bundle_bytes=1 << 20))


def test_huge_member_header_is_refused_before_reading(tmp_path):
    # A header claiming 100 GiB followed by a few bytes: refused on the header alone, memory stays small.
    (tmp_path / "out").mkdir()
    head = _bundle([]).rstrip(b"\0")
    head += b"\0" * (-len(head) % 512)
    info = tarfile.TarInfo("huge.bin")
    info.size = 100 << 30
    listed = _manifest({"scene.xml": SCENE, "huge.bin": b""}).replace(b'"size": 0', b'"size": 107374182400')
    data = _tar([_reg(MANIFEST_NAME, listed), _reg("scene.xml", SCENE)]).rstrip(b"\0")
    data += b"\0" * (-len(data) % 512) + info.tobuf(tarfile.PAX_FORMAT) + b"x" * 4096
    _refused(data, tmp_path, r"'huge.bin': 107374182400 bytes, over the per-file limit")


def test_dest_must_be_new_and_good_bundle_unpacks(tmp_path):
    data = _bundle([_reg("meshes/a.obj", b"v 0 0 0")], listed={"meshes/a.obj": b"v 0 0 0"})
    scene = extract_bundle(data, tmp_path / "x")
    assert scene.read_bytes() == SCENE
    assert (scene.parent / "meshes" / "a.obj").read_bytes() == b"v 0 0 0"
    umask = os.umask(0)
    os.umask(umask)
    assert oct(os.stat(scene).st_mode & 0o777) == oct(0o666 & ~umask)  # a new file's, whatever the tar says
    with pytest.raises(BundleError, match="already exists"):
        extract_bundle(data, tmp_path / "x")
