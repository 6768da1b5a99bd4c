"""Tiles: a rendered unit (pixels, where they go, what happened) and its file form, a float32 EXR.

A tile holds every channel of the film (R, G, B first; then alpha, AOVs, moments: whatever the scene's
film and integrator write), in the film's order. File layout: one scanline part, every channel as
FLOAT, ZIP compressed. The EXR `dataWindow` is the rendered rectangle (band included), so the file
carries its own position; `quekaro_core` holds the unit rectangle as "x y w h", `quekaro_channels` the
channel order and `quekaro_meta` the meta dict as JSON. Files are written durably: a temporary file
beside the target, fsync, then an atomic rename.
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
import OpenEXR

from core.errors import TileError
from core.image.compose import TileSource
from core.model.geometry import Rect
from core.model.job import RGB

META_ATTR = "quekaro_meta"
CORE_ATTR = "quekaro_core"
CHANNELS_ATTR = "quekaro_channels"
MAX_CHANNELS = 64


@dataclass
class Tile:
    """Pixels (float32, H x W x channels) of `rect` (the rendered rectangle, band included); `core` is the
    unit; `channels` names the last axis (the film's channel names, R, G, B first)."""

    pixels: np.ndarray
    rect: Rect
    core: Rect
    meta: dict[str, Any] = field(default_factory=dict)
    channels: tuple[str, ...] = RGB

    def __post_init__(self) -> None:
        self.pixels = np.ascontiguousarray(self.pixels, dtype=np.float32)
        self.channels = tuple(self.channels)
        check_channels(self.channels)
        expected = (self.rect.h, self.rect.w, len(self.channels))
        if self.pixels.shape != expected:
            raise TileError(f"tile pixels shaped {self.pixels.shape}, rect {self.rect} needs {expected}")
        if self.core.intersect(self.rect) != self.core:
            raise TileError(f"tile core {self.core} lies outside its rendered rect {self.rect}")

    def core_pixels(self) -> np.ndarray:
        """The pixels of the unit itself, band cut away."""
        y0, x0 = self.core.y - self.rect.y, self.core.x - self.rect.x
        return self.pixels[y0:y0 + self.core.h, x0:x0 + self.core.w]


def check_channels(channels: tuple[str, ...], name: str = "tile") -> None:
    """Channel names must start with R, G, B, be unique, printable and at most MAX_CHANNELS."""
    if tuple(channels[:3]) != RGB:
        raise TileError(f"{name}: channels {list(channels[:8])} do not start with R, G, B")
    if len(set(channels)) != len(channels) or len(channels) > MAX_CHANNELS:
        raise TileError(f"{name}: {len(channels)} channels, duplicated or over {MAX_CHANNELS}")
    if any(not c or len(c) > 64 or not c.isprintable() or "," in c for c in channels):
        raise TileError(f"{name}: a channel name is empty, over 64 characters, not printable or has a comma")


def _header(tile: Tile) -> dict[str, Any]:
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
        CHANNELS_ATTR: ",".join(tile.channels),
    }


def write_tile(path: str | Path, tile: Tile, durable: bool = True) -> Path:
    """Write the tile as an EXR at `path` (temp file, then rename: never half-written); return the path.

    `durable` also fsyncs the file and its folder, so that the tile survives a crash of the machine; an
    agent's tile, deleted once uploaded and rendered again if lost, does not need it."""
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
        planes = {c: np.ascontiguousarray(tile.pixels[..., i]) for i, c in enumerate(tile.channels)}
        with OpenEXR.File(header, planes) as exr:
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


def tile_source(path: str | Path, **meta: Any) -> TileSource:
    """The tile at `path` known by its header alone (its pixels are read when composition needs them);
    `meta` entries override the header's (the store knows which unit a tile is)."""
    path = Path(path)
    try:
        with OpenEXR.File(str(path), header_only=True) as exr:
            header = exr.header()
            rect = _rect_from_header(header, str(path))
            order = _channel_order(header, str(path))
            core, stored = _core_and_meta(header, str(path))
    except TileError:
        raise
    except Exception as exc:  # OpenEXR reports corrupt data as RuntimeError or ValueError
        raise TileError(f"{path}: unreadable EXR header ({exc})") from exc

    def load() -> Tile:
        tile = read_tile(path)
        tile.meta.update(meta)
        return tile

    return TileSource(rect, core, order, load, {**stored, **meta})


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
    if data[:4] != b"\x76\x2f\x31\x01":
        raise TileError(f"{name}: not an EXR file")
    try:
        # The header and channels are only valid while the file is open: validate inside.
        with OpenEXR.File(io.BytesIO(data), separate_channels=True) as exr:
            header = exr.header()
            channels = {k: np.array(v.pixels) for k, v in exr.channels().items()}
            rect = _rect_from_header(header, name)
            order = _channel_order(header, name)
            pixels = _stack_channels(channels, order, rect, name)
            core, meta = _core_and_meta(header, name)
    except TileError:
        raise
    except Exception as exc:  # OpenEXR reports corrupt data as RuntimeError or ValueError
        raise TileError(f"{name}: unreadable EXR ({exc})") from exc
    try:
        return Tile(pixels, rect, core, meta, order)
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


def _channel_order(header: dict[str, Any], name: str) -> tuple[str, ...]:
    raw = header.get(CHANNELS_ATTR)
    order = tuple(str(raw).split(",")) if raw is not None else RGB
    check_channels(order, name)
    return order


def _stack_channels(channels: dict[str, np.ndarray], order: tuple[str, ...], rect: Rect,
                    name: str) -> np.ndarray:
    if sorted(channels) != sorted(order):
        raise TileError(f"{name}: channels {sorted(channels)[:8]} differ from the header's list {list(order)[:8]}")
    for key, plane in channels.items():
        if plane.dtype != np.float32:
            raise TileError(f"{name}: channel {key} is {plane.dtype}, a tile needs float32")
        if plane.shape != (rect.h, rect.w):
            raise TileError(f"{name}: channel {key} is {plane.shape}, dataWindow says {(rect.h, rect.w)}")
    return np.stack([channels[c] for c in order], axis=-1)


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
