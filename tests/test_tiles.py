"""Tiles: EXR round trip with position and meta, durable write, and validation of bad files."""

import numpy as np
import OpenEXR
import pytest

from core.errors import TileError
from core.image.tiles import Tile, read_tile, read_tile_bytes, write_tile
from core.model.geometry import Rect


def _tile():
    rng = np.random.default_rng(1)
    return Tile(rng.random((4, 6, 3), dtype=np.float32) * 5, Rect(10, 20, 6, 4), Rect(12, 21, 3, 2),
                {"nonfinite": 2, "seed": 7, "job_id": "j"})


def test_round_trip_is_exact(tmp_path):
    tile = _tile()
    path = write_tile(tmp_path / "t.exr", tile)
    back = read_tile(path)
    assert back.rect == tile.rect and back.core == tile.core and back.meta == tile.meta
    assert np.array_equal(back.pixels, tile.pixels) and back.pixels.dtype == np.float32
    assert back.core_pixels().shape == (2, 3, 3)
    assert [p.name for p in tmp_path.iterdir()] == ["t.exr"]  # no temp file left behind


def test_tile_checks_its_own_shape():
    with pytest.raises(TileError, match="shaped"):
        Tile(np.zeros((3, 3, 3)), Rect(0, 0, 4, 3), Rect(0, 0, 1, 1))
    with pytest.raises(TileError, match="outside"):
        Tile(np.zeros((3, 4, 3)), Rect(0, 0, 4, 3), Rect(3, 0, 2, 1))


def test_bad_files_are_named(tmp_path):
    junk = tmp_path / "junk.exr"
    junk.write_bytes(b"not an exr at all")
    with pytest.raises(TileError, match=r"junk.exr: not an EXR"):
        read_tile(junk)
    good = write_tile(tmp_path / "g.exr", _tile()).read_bytes()
    with pytest.raises(TileError, match=r"cut.exr"):
        read_tile_bytes(good[: len(good) // 2], "cut.exr")
    with pytest.raises(TileError, match=r"missing.exr"):
        read_tile(tmp_path / "missing.exr")


def test_wrong_channels_and_missing_position(tmp_path):
    grey = tmp_path / "grey.exr"
    with OpenEXR.File({"dataWindow": ((0, 0), (3, 2))}, {"Y": np.zeros((3, 4), np.float32)}) as exr:
        exr.write(str(grey))
    with pytest.raises(TileError, match=r"grey.exr: channels"):
        read_tile(grey)
    half = tmp_path / "half.exr"
    header = {"dataWindow": ((0, 0), (3, 2)), "quekaro_core": "0 0 1 1"}
    with OpenEXR.File(header, {"RGB": np.zeros((3, 4, 3), np.float16)}) as exr:
        exr.write(str(half))
    with pytest.raises(TileError, match="float32"):
        read_tile(half)
    nocore = tmp_path / "nocore.exr"
    with OpenEXR.File({"dataWindow": ((0, 0), (3, 2))}, {"RGB": np.zeros((3, 4, 3), np.float32)}) as exr:
        exr.write(str(nocore))
    with pytest.raises(TileError, match="quekaro_core"):
        read_tile(nocore)


def test_unwritable_target_is_a_tile_error(tmp_path):
    with pytest.raises(TileError):
        write_tile(tmp_path / "no" / "dir" / "t.exr", _tile())
    with pytest.raises(TileError, match="JSON"):
        write_tile(tmp_path / "t.exr", Tile(np.zeros((1, 1, 3)), Rect(0, 0, 1, 1), Rect(0, 0, 1, 1),
                                            {"bad": float("nan")}))


def test_a_tile_written_without_fsync_reads_back_the_same(tmp_path):
    tile = _tile()
    path = write_tile(tmp_path / "quick.exr", tile, durable=False)
    back = read_tile(path)
    assert np.array_equal(back.pixels, tile.pixels) and back.rect == tile.rect
    assert not list(tmp_path.glob(".*.tmp"))  # the temporary file was renamed, not left behind
