"""Tiles: a rendered unit (pixels, where they go, what happened) and its file form, a float32 RGB EXR.

File layout: one scanline part, channels R, G, B as FLOAT, ZIP compressed. The EXR `dataWindow` is
the rendered rectangle (band included), so the file carries its own position; `quekaro_core` holds the
unit rectangle as "x y w h" and `quekaro_meta` the meta dict as JSON. Files are written durably:
a temporary file beside the target, fsync, then an atomic rename.
"""

from __future__ import annotations

import io
import json
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from core.errors import TileError
from core.geometry import Rect

META_ATTR = "quekaro_meta"
CORE_ATTR = "quekaro_core"


@dataclass
class Tile:
    """Pixels (float32, H x W x 3) of `rect` (the rendered rectangle, band included); `core` is the unit."""

    pixels: np.ndarray
    rect: Rect
    core: Rect
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.pixels = np.ascontiguousarray(self.pixels, dtype=np.float32)
        expected = (self.rect.h, self.rect.w, 3)
        if self.pixels.shape != expected:
            raise TileError(f"tile pixels shaped {self.pixels.shape}, rect {self.rect} needs {expected}")
        if self.core.intersect(self.rect) != self.core:
            raise TileError(f"tile core {self.core} lies outside its rendered rect {self.rect}")

    def core_pixels(self) -> np.ndarray:
        """The pixels of the unit itself, band cut away."""
        y0, x0 = self.core.y - self.rect.y, self.core.x - self.rect.x
        return self.pixels[y0:y0 + self.core.h, x0:x0 + self.core.w]


def _header(tile: Tile) -> dict[str, Any]:
    import OpenEXR

    r = tile.rect
    try:
        meta = json.dumps(tile.meta, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise TileError(f"tile meta is not plain JSON ({exc})") from exc
    return {
        "compression": OpenEXR.ZIP_COMPRESSION,
        "type": OpenEXR.scanlineimage,
        "dataWindow": ((r.x, r.y), (r.x1 - 1, r.y1 - 1)),
        "displayWindow": ((0, 0), (r.x1 - 1, r.y1 - 1)),
        META_ATTR: meta,
        CORE_ATTR: " ".join(str(v) for v in tile.core.as_list()),
    }


def write_tile(path: str | Path, tile: Tile, durable: bool = True) -> Path:
    """Write the tile as an EXR at `path` (temp file, then rename: never half-written); return the path.

    `durable` also fsyncs the file and its folder, so that the tile survives a crash of the machine; an
    agent's tile, deleted once uploaded and rendered again if lost, does not need it."""
    import OpenEXR

    path = Path(path)
    if tile.rect.area == 0:
        raise TileError(f"{path}: refusing to write an empty tile ({tile.rect})")
    header = _header(tile)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:
        raise TileError(f"{path}: cannot write tile ({exc})") from exc
    os.close(fd)
    try:
        with OpenEXR.File(header, {"RGB": tile.pixels}) as exr:
            exr.write(tmp)
        if durable:
            durable_replace(Path(tmp), path)
        else:
            os.replace(tmp, path)
    except (OSError, RuntimeError) as exc:
        Path(tmp).unlink(missing_ok=True)
        raise TileError(f"{path}: cannot write tile ({exc})") from exc
    return path


def durable_replace(tmp: Path, final: Path) -> None:
    """Make `tmp` the file `final`, durably: fsync its data, rename it, fsync the folder (so a tile
    counts as written only once a crash can no longer lose it)."""
    _fsync(tmp)
    os.replace(tmp, final)
    _fsync(final.parent)


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def read_tile(path: str | Path) -> Tile:
    """Read and validate a tile file; every defect is a TileError naming the file."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise TileError(f"{path}: cannot read tile ({exc})") from exc
    return read_tile_bytes(data, str(path))


def read_tile_bytes(data: bytes, name: str = "<tile>") -> Tile:
    """Parse and validate a tile from its EXR bytes (an upload); errors name `name`."""
    import OpenEXR

    if data[:4] != b"\x76\x2f\x31\x01":
        raise TileError(f"{name}: not an EXR file")
    try:
        # The header and channels are only valid while the file is open: validate inside.
        with OpenEXR.File(io.BytesIO(data), separate_channels=True) as exr:
            header = exr.header()
            channels = {k: np.array(v.pixels) for k, v in exr.channels().items()}
            rect = _rect_from_header(header, name)
            pixels = _rgb_from_channels(channels, rect, name)
            core, meta = _core_and_meta(header, name)
    except TileError:
        raise
    except Exception as exc:  # OpenEXR reports corrupt data as RuntimeError or ValueError
        raise TileError(f"{name}: unreadable EXR ({exc})") from exc
    try:
        return Tile(pixels, rect, core, meta)
    except TileError as exc:
        raise TileError(f"{name}: {exc}") from exc


def _rect_from_header(header: dict[str, Any], name: str) -> Rect:
    try:
        (x0, y0), (x1, y1) = (tuple(int(v) for v in corner) for corner in header["dataWindow"])
    except (KeyError, TypeError, ValueError) as exc:
        raise TileError(f"{name}: EXR header has no valid dataWindow") from exc
    if x1 < x0 or y1 < y0:
        raise TileError(f"{name}: empty dataWindow {(x0, y0)}-{(x1, y1)}")
    return Rect(x0, y0, x1 - x0 + 1, y1 - y0 + 1)


def _rgb_from_channels(channels: dict[str, np.ndarray], rect: Rect, name: str) -> np.ndarray:
    if sorted(channels) != ["B", "G", "R"]:
        raise TileError(f"{name}: channels {sorted(channels)}, a tile needs exactly R, G, B")
    for key, plane in channels.items():
        if plane.dtype != np.float32:
            raise TileError(f"{name}: channel {key} is {plane.dtype}, a tile needs float32")
        if plane.shape != (rect.h, rect.w):
            raise TileError(f"{name}: channel {key} is {plane.shape}, dataWindow says {(rect.h, rect.w)}")
    return np.stack([channels["R"], channels["G"], channels["B"]], axis=-1)


def _core_and_meta(header: dict[str, Any], name: str) -> tuple[Rect, dict[str, Any]]:
    try:
        core = Rect.from_list(str(header[CORE_ATTR]).split())
    except (KeyError, ValueError) as exc:
        raise TileError(f"{name}: missing or bad header attribute {CORE_ATTR!r}") from exc
    try:
        meta = json.loads(str(header.get(META_ATTR, "{}")))
    except json.JSONDecodeError as exc:
        raise TileError(f"{name}: header attribute {META_ATTR!r} is not JSON ({exc})") from exc
    if not isinstance(meta, dict):
        raise TileError(f"{name}: header attribute {META_ATTR!r} is not a JSON object")
    return core, meta
