"""The master's HTTP data plane (aiohttp): agents fetch scene bundles and upload rendered tiles here.

  GET /jobs/{job}/bundle              the job's scene bundle, its sha256 in `X-Content-SHA256`
  PUT /jobs/{job}/units/{unit}/tile   a rendered tile, with its award's token and the body's sha256
  GET /healthz                        up and serving (no token)
`create_app` builds it from the master's callbacks (it depends on no store); `get_bundle` and `put_tile`
say the rules. Every refusal is JSON `{"error": reason, "status": code}` and leaves no file behind.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import hmac
import inspect
import logging
import os
import re
import socket
import ssl
import tempfile
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import OpenEXR
from aiohttp import web

from core.errors import TileError
from core.image.tiles import MAX_CHANNELS, durable_replace, read_tile
from core.model.geometry import Rect
from master.http_guard import (
    JOB_PART,
    UNIT_PART,
    Refusal,
    bearer_token,
    disk_full,
    json_error,
    read_body_chunks,
    sender_of,
)
from master.http_guard import serve as guarded_serve

log = logging.getLogger(__name__)

TOKEN_HEADER = "X-Quekaro-Token"
HASH_HEADER = "X-Content-SHA256"
AGENT_HEADER = "X-Quekaro-Agent"
DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8765
_SHA_RE = re.compile(r"^[0-9a-f]{64}$")
_CHUNK = 1 << 20
# An EXR's header, offsets and compression overhead on top of the raw float32 RGB pixels.
_EXR_SLACK = 1 << 20
DISK_FULL = "disk full on the master: nothing was stored; send it again once space is freed"

Expected = Callable[[str, int, str], Any]  # (job, unit, token) -> (unit Rect, image (width, height)) or None
BundleProvider = Callable[[str], Any]
OnTile = Callable[[str, int, Path, str, str, "str | None"], Any]


@dataclass
class DataPlane:
    """The app's configuration and its small state (per-unit locks, hashes of accepted tiles)."""

    expected: Expected
    bundle: BundleProvider
    on_tile: OnTile
    tile_dir: Path
    max_tile_bytes: int = 256 << 20
    max_band: int = 256
    authorize_bundle: Callable[[str, str], Any] | None = None
    locks: dict[tuple[str, int], asyncio.Lock] = field(default_factory=dict)
    accepted: dict[tuple[str, int], tuple[str, str]] = field(default_factory=dict)  # (sha256, token)

    def tile_path(self, job: str, unit: int) -> Path:
        return self.tile_dir / job / "tiles" / f"unit-{unit}.exr"


KEY: web.AppKey[DataPlane] = web.AppKey("quekaro_data_plane", DataPlane)


def create_app(expected: Expected, bundle: BundleProvider, on_tile: OnTile, tile_dir: str | Path, *,
               max_tile_bytes: int = 256 << 20, max_band: int = 256,
               authorize_bundle: Callable[[str, str], Any] | None = None) -> web.Application:
    """The data-plane application; the callbacks may be plain functions or coroutines.

    `expected(job, unit, token) -> (rect, image) | None`: the unit's rectangle (band excluded) and the
    image's (width, height), if `token` is its current award's (the auction compares tokens).
    `bundle(job) -> (path, sha256) | None`. `on_tile(job, unit, path, sha256, token, agent)` records a
    stored tile. `authorize_bundle(job, token) -> bool`, if given, guards the bundles (`get_bundle`)."""
    plane = DataPlane(expected, bundle, on_tile, Path(tile_dir), max_tile_bytes, max_band, authorize_bundle)
    # client_max_size guards request.read()/post(); the tile route streams and enforces its own limit.
    app = web.Application(client_max_size=1 << 20, middlewares=[_json_errors])
    app[KEY] = plane
    app.router.add_get("/jobs/{job}/bundle", get_bundle)
    app.router.add_put("/jobs/{job}/units/{unit}/tile", put_tile)
    app.router.add_get("/healthz", healthz)
    return app


async def healthz(request: web.Request) -> web.Response:
    """Up and serving (a container's healthcheck asks this): no token needed, nothing told."""
    return web.json_response({"ok": True})


async def serve(app: web.Application, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT,
                ssl_context: ssl.SSLContext | None = None, sock: socket.socket | None = None
                ) -> tuple[web.AppRunner, int]:
    """Start `app` on host:port (0 picks a free port), or on a bound `sock`, HTTPS with `ssl_context`,
    behind master.http_guard's time limits; return the runner (cleanup() stops) and the port."""
    return await guarded_serve(app, host, port, ssl_context=ssl_context, sock=sock)


@web.middleware
async def _json_errors(request: web.Request, handler: Callable[[web.Request], Awaitable[web.StreamResponse]]
                       ) -> web.StreamResponse:
    try:
        return await handler(request)
    except Refusal as exc:
        log.info("%s %s from %s refused (%d): %s", request.method, request.path, sender_of(request), exc.status,
                 exc.reason)
        return json_error(exc.status, exc.reason)
    except web.HTTPException as exc:
        if exc.status >= 400:  # aiohttp's own 404/405/413: same JSON shape as ours
            return json_error(exc.status, exc.reason)
        raise
    except Exception as exc:
        if not disk_full(exc):
            raise
        # The master's disk, not the sender's doing: 507, and the sender keeps its data to send again.
        log.error("%s %s: disk full on the master (%s)", request.method, request.path, exc)
        return json_error(507, DISK_FULL)


async def _call(fn: Callable[..., Any], *args: Any) -> Any:
    value = fn(*args)
    return await value if inspect.isawaitable(value) else value


def _job_and_unit(request: web.Request) -> tuple[str, int]:
    job, unit = request.match_info["job"], request.match_info.get("unit", "0")
    if not JOB_PART.fullmatch(job):
        raise Refusal(404, f"unknown job {job[:80]!r}")
    if not UNIT_PART.fullmatch(unit):
        raise Refusal(404, f"unknown unit {unit[:80]!r} of job {job!r}")
    return job, int(unit)


def _token(request: web.Request) -> str:
    return request.headers.get(TOKEN_HEADER, "") or bearer_token(request)


# ---- GET bundle ------------------------------------------------------------------------------


async def get_bundle(request: web.Request) -> web.StreamResponse:
    """GET /jobs/{job}/bundle: the job's scene bundle (core.scene.bundle), its sha256 in `X-Content-SHA256`.

    Open by default: agents need a bundle before they hold any token, and the default bind is 127.0.0.1.
    With `authorize_bundle` it needs `X-Quekaro-Token` (set it when binding beyond loopback); a refused
    token is 403."""
    plane = request.app[KEY]
    job, _ = _job_and_unit(request)
    if plane.authorize_bundle is not None and not await _call(plane.authorize_bundle, job, _token(request)):
        raise Refusal(403, f"missing or wrong {TOKEN_HEADER} for the bundle of job {job!r}")
    found = await _call(plane.bundle, job)
    if found is None or not Path(found[0]).is_file():
        raise Refusal(404, f"no bundle for job {job!r}")
    path, sha256 = Path(found[0]), str(found[1])
    return web.FileResponse(path, headers={HASH_HEADER: sha256, "Content-Type": "application/x-tar"})


# ---- PUT tile --------------------------------------------------------------------------------


def _not_yours(job: str, unit: int) -> Refusal:
    """The one answer to an upload without the current award's token, whatever the unit's state."""
    return Refusal(403, f"no current award of unit {unit} of job {job!r} matches the {TOKEN_HEADER} sent")


def _expected_rect(value: Any) -> tuple[Rect, tuple[int, int]]:
    """(unit rectangle, image (width, height)) from the `expected` callback's answer."""
    rect, (width, height) = value
    rect = rect if isinstance(rect, Rect) else Rect.from_list(rect)
    return rect, (int(width), int(height))


def _size_cap(plane: DataPlane, rect: Rect) -> int:
    # float32 per channel, as many channels as a tile may carry (alpha, AOVs, moments)
    pixels = (rect.w + 2 * plane.max_band) * (rect.h + 2 * plane.max_band)
    return min(plane.max_tile_bytes, pixels * 4 * MAX_CHANNELS + _EXR_SLACK)


async def put_tile(request: web.Request) -> web.Response:
    """PUT /jobs/{job}/units/{unit}/tile: headers `X-Quekaro-Token` (or `Authorization: Bearer ..`), the
    award's per-unit token; `X-Content-SHA256`, the body's hex sha256; optional `X-Quekaro-Agent` (informational).

    The body streams to a temporary file beside its destination while its size (413 over `max_tile_bytes`
    or what the unit's rectangle can need) and hash (422 on a mismatch) are checked. The EXR header comes
    before any pixel is decoded (a small file can declare a huge image): its dataWindow must be the unit's
    window at one band (422 otherwise); then read_tile checks the whole tile. Only then is it fsynced,
    renamed to `{tile_dir}/{job}/tiles/unit-{unit}.exr`, the folder fsynced, and `on_tile` awaited; if that
    raises, the file is removed and the answer is 500 (422 for a TileError), so the agent may retry.
    A repeat of an accepted tile (same sha256 and token) is 200 "duplicate" and changes nothing. Any upload
    without the current award's token gets one answer, 403 whatever the unit's state or the body, so that
    no one without the token learns a unit's state or whether a sha256 matches."""
    plane = request.app[KEY]
    job, unit = _job_and_unit(request)
    declared = request.headers.get(HASH_HEADER, "").strip().lower()
    if not _SHA_RE.match(declared):
        raise Refusal(400, f"header {HASH_HEADER} must be the body's sha256 as 64 hex digits")
    slot = await _call(plane.expected, job, unit, _token(request))
    if slot is None:
        return _late_upload(plane, job, unit, declared, _token(request))
    rect, _ = _expected_rect(slot)
    cap = _size_cap(plane, rect)
    if request.content_length is not None and request.content_length > cap:
        raise Refusal(413, f"tile of {request.content_length} bytes exceeds the limit of {cap} bytes "
                           f"for unit {unit} ({rect.w}x{rect.h} px)")
    final = plane.tile_path(job, unit)
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = await _receive(request, final, declared, cap)
    try:
        return await _accept(request, plane, job, unit, tmp, declared)
    finally:
        tmp.unlink(missing_ok=True)


def _late_upload(plane: DataPlane, job: str, unit: int, declared: str, token: str) -> web.Response:
    # No current award of the unit has this token: the repeat of its accepted tile by the award that delivered it is
    # harmless; anything else gets one answer, whatever it holds.
    accepted = plane.accepted.get((job, unit))
    if accepted is not None and accepted[0] == declared and hmac.compare_digest(accepted[1].encode(),
                                                                                token.encode()):
        return web.json_response({"status": "duplicate", "job": job, "unit": unit, "sha256": declared})
    raise _not_yours(job, unit)


async def _receive(request: web.Request, final: Path, declared: str, cap: int) -> Path:
    """Stream the body to a temp file beside `final`, checking its size as it comes, its hash at the end."""
    fd, name = tempfile.mkstemp(prefix=f".{final.name}.", suffix=".part", dir=final.parent)
    tmp, digest, size = Path(name), hashlib.sha256(), 0
    try:
        with os.fdopen(fd, "wb") as out:
            async for chunk in read_body_chunks(request, _CHUNK):
                size += len(chunk)
                if size > cap:
                    raise Refusal(413, f"tile exceeds the limit of {cap} bytes")
                digest.update(chunk)
                out.write(chunk)
        if size == 0:
            raise Refusal(400, "empty body: a tile upload needs the EXR file")
        if digest.hexdigest() != declared:
            raise Refusal(422, f"body sha256 {digest.hexdigest()} differs from {HASH_HEADER} {declared}")
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return tmp


async def _accept(request: web.Request, plane: DataPlane, job: str, unit: int, tmp: Path,
                  sha256: str) -> web.Response:
    lock = plane.locks.setdefault((job, unit), asyncio.Lock())
    async with lock:
        # Asked again under the lock: a concurrent upload may have completed the unit meanwhile.
        token = _token(request)
        slot = await _call(plane.expected, job, unit, token)
        if slot is None:  # done, or awarded to another token meanwhile
            return _late_upload(plane, job, unit, sha256, token)
        rect, image = _expected_rect(slot)
        if plane.accepted.get((job, unit)) == (sha256, token):  # a repeat the master has not acted on yet
            return web.json_response({"status": "duplicate", "job": job, "unit": unit, "sha256": sha256})
        await asyncio.to_thread(_validate, tmp, rect, image, plane.max_band, f"unit {unit} of job {job!r}", job, unit)
        final = plane.tile_path(job, unit)
        await asyncio.to_thread(durable_replace, tmp, final)
        agent = request.headers.get(AGENT_HEADER, "")[:256] or None
        try:
            await _call(plane.on_tile, job, unit, final, sha256, token, agent)
        except TileError as exc:  # what the tile claims is not what its award allows
            final.unlink(missing_ok=True)
            raise Refusal(422, f"unit {unit} of job {job!r}: {exc}") from exc
        except Exception as exc:
            final.unlink(missing_ok=True)
            log.exception("on_tile failed for unit %d of job %s", unit, job)
            reason = f"the master could not record the tile ({type(exc).__name__}: {exc})"
            raise Refusal(500, reason) from exc
        plane.accepted[(job, unit)] = (sha256, token)
    return web.json_response({"status": "accepted", "job": job, "unit": unit, "sha256": sha256,
                              "bytes": final.stat().st_size})


def _validate(path: Path, core: Rect, image: tuple[int, int], max_band: int, what: str, job: str,
              unit: int) -> None:
    """Header first (no pixel decoded for a wrong window), then the whole tile through core.image.tiles, and
    the unit and job its header names (assembly reads them)."""

    window = _data_window(path, what)
    band = _band_of(window, core, image, max_band, what)
    try:
        tile = read_tile(path)
    except TileError as exc:
        raise Refusal(422, f"{what}: {exc}") from exc
    if tile.core != core:
        raise Refusal(422, f"{what}: tile says its unit is {tile.core}, expected {core}")
    if tile.meta.get("unit_index") != unit or tile.meta.get("job_id") != job:
        raise Refusal(422, f"{what}: tile header names unit {tile.meta.get('unit_index')!r} of job "
                           f"{tile.meta.get('job_id')!r}")
    log.debug("%s: tile %s with band %d valid", what, window, band)


def _data_window(path: Path, what: str) -> Rect:
    with path.open("rb") as fh:
        if fh.read(4) != b"\x76\x2f\x31\x01":
            raise Refusal(422, f"{what}: the body is not an EXR file")
    try:
        with OpenEXR.File(str(path), header_only=True) as exr:
            if len(exr.parts) != 1:
                raise Refusal(422, f"{what}: EXR has {len(exr.parts)} parts, a tile has one")
            (x0, y0), (x1, y1) = (tuple(int(v) for v in c) for c in exr.header()["dataWindow"])
    except Refusal:
        raise
    except Exception as exc:  # OpenEXR reports corrupt headers as RuntimeError/ValueError/KeyError
        raise Refusal(422, f"{what}: unreadable EXR header ({exc})") from exc
    if x1 < x0 or y1 < y0:
        raise Refusal(422, f"{what}: empty EXR dataWindow")
    return Rect(x0, y0, x1 - x0 + 1, y1 - y0 + 1)


def _band_of(window: Rect, core: Rect, image: tuple[int, int], max_band: int, what: str) -> int:
    """The band of a unit's window: the one whose core.model.geometry.Rect.window it is. Its margins give
    the candidates (an axis's two margins add up to twice the band unless the axis is the whole image)."""
    left, top = core.x - window.x, core.y - window.y
    right, bottom = window.x1 - core.x1, window.y1 - core.y1
    for band in sorted({(left + right) // 2, (top + bottom) // 2, max(left, top, right, bottom)}):
        if 0 <= band <= max_band and core.window(band, *image) == window:
            return band
    raise Refusal(422, f"{what}: EXR dataWindow {window.as_list()} is not the window of unit {core.as_list()} "
                       f"for one band of at most {max_band} px in a {image[0]}x{image[1]} image")


async def close(runner: web.AppRunner) -> None:
    """Stop a server started with `serve`."""
    with contextlib.suppress(Exception):
        await runner.cleanup()
