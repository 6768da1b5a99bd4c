"""The agent's side of the HTTP data plane: fetch a job's scene bundle, upload a rendered tile.

Both are aiohttp client coroutines. `fetch_bundle` streams the download to a temporary file (never
more than the bundle limit), checks its sha256 against the one the job announced (and the server's
`X-Content-SHA256`), then unpacks it with core.scene.bundle.extract_bundle, which refuses hostile archives.
`dest` is the folder the bundle unpacks into; callers name it by the hash, so a folder that exists is a
cache hit (extract_bundle creates it atomically, only once everything checked out).
`upload_tile` sends the file with its sha256 and the award's token, retrying with exponential backoff
on connection errors, timeouts and 502/503/504; any other refusal raises TransferError with the
server's reason and is not retried. A 500 (the master failed to record the tile) is retried too.
"""

from __future__ import annotations

import asyncio
import hashlib
import logging
import os
import ssl
import tempfile
from pathlib import Path
from typing import Any

import aiohttp

from core.errors import QuekaroError
from core.model.hashing import sha256_file
from core.scene.bundle import MANIFEST_NAME, BundleLimits, extract_bundle, read_manifest

log = logging.getLogger(__name__)

TOKEN_HEADER = "X-Quekaro-Token"
HASH_HEADER = "X-Content-SHA256"
AGENT_HEADER = "X-Quekaro-Agent"
_CHUNK = 1 << 20
_RETRY_STATUS = {500, 502, 503, 504}
DISK_FULL_STATUS = 507  # the master's disk is full: wait for space, never count it as the unit's failure
# A connection not made by then fails the transfer: a firewall that drops packets left a bundle fetch
# waiting past the unit's render deadline (30 s and up), the agent saying nothing of why.
CONNECT_TIMEOUT_S = 15.0


class TransferError(QuekaroError):
    """A fetch or upload that failed or was refused; `status` is the HTTP status (None: no answer)."""

    def __init__(self, url: str, reason: str, status: int | None = None) -> None:
        self.url, self.reason, self.status = url, reason, status
        super().__init__(f"{url}: {reason}" + (f" (HTTP {status})" if status else ""))


async def _reason(resp: aiohttp.ClientResponse) -> str:
    try:
        body = await resp.json(content_type=None)
        return str(body.get("error", body))[:500]
    except Exception:
        return (await resp.text(errors="replace"))[:500]


async def fetch_bundle(url: str, expected_sha256: str, dest: str | Path, limits: BundleLimits | None = None,
                       *, token: str | None = None, timeout_s: float = 300.0,
                       ssl_context: ssl.SSLContext | None = None) -> Path:
    """Download and unpack the bundle at `url` into the new folder `dest`; return the scene file's path."""
    limits = limits or BundleLimits()
    dest = Path(dest)
    if (dest / MANIFEST_NAME).is_file():
        return dest / read_manifest(dest)["scene"]
    dest.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=f".{dest.name}.", suffix=".tar", dir=dest.parent)
    tmp = Path(name)
    try:
        with os.fdopen(fd, "wb") as out:
            digest = await _download(url, out, limits.max_bundle_bytes, token, timeout_s, ssl_context)
        if digest != expected_sha256.lower():
            raise TransferError(url, f"bundle sha256 {digest} differs from the job's {expected_sha256}")
        return await asyncio.to_thread(extract_bundle, tmp, dest, limits)
    finally:
        tmp.unlink(missing_ok=True)


async def _download(url: str, out: Any, cap: int, token: str | None, timeout_s: float,
                    ssl_context: ssl.SSLContext | None) -> str:
    headers = {TOKEN_HEADER: token} if token else {}
    digest, size = hashlib.sha256(), 0
    try:
        timeout = aiohttp.ClientTimeout(total=timeout_s, sock_connect=CONNECT_TIMEOUT_S)
        async with aiohttp.ClientSession(timeout=timeout) as session, \
                session.get(url, headers=headers, ssl=ssl_context or True) as resp:
            if resp.status != 200:
                raise TransferError(url, await _reason(resp), resp.status)
            if resp.content_length is not None and resp.content_length > cap:
                raise TransferError(url, f"bundle of {resp.content_length} bytes exceeds the limit {cap}")
            async for chunk in resp.content.iter_chunked(_CHUNK):
                size += len(chunk)
                if size > cap:
                    raise TransferError(url, f"bundle exceeds the limit of {cap} bytes")
                digest.update(chunk)
                out.write(chunk)
            announced = resp.headers.get(HASH_HEADER, "").lower()
    except (TimeoutError, aiohttp.ClientError) as exc:
        raise TransferError(url, f"download failed ({type(exc).__name__}: {exc})") from exc
    if announced and announced != digest.hexdigest():
        raise TransferError(url, f"bundle sha256 {digest.hexdigest()} differs from the server's {announced}")
    return digest.hexdigest()


async def upload_tile(url: str, token: str, path: str | Path, sha256: str | None = None, *,
                      agent: str | None = None, retries: int = 4, backoff_s: float = 0.5,
                      timeout_s: float = 300.0, disk_full_wait_s: float = 600.0,
                      ssl_context: ssl.SSLContext | None = None) -> dict[str, Any]:
    """PUT the tile at `path` to `url`; return the server's JSON answer ("accepted" or "duplicate").

    A master whose disk is full (507) is asked again every few seconds for up to `disk_full_wait_s`
    without using up the retries: the tile waits on this agent until space returns."""
    path = Path(path)
    sha256 = sha256 or await asyncio.to_thread(sha256_file, path)
    headers = {TOKEN_HEADER: token, HASH_HEADER: sha256, "Content-Type": "image/x-exr"}
    if agent:
        headers[AGENT_HEADER] = agent
    timeout = aiohttp.ClientTimeout(total=timeout_s, sock_connect=CONNECT_TIMEOUT_S)
    full_until = asyncio.get_running_loop().time() + disk_full_wait_s
    attempt = -1
    while attempt < retries:
        attempt += 1
        delay = backoff_s * 2 ** attempt
        try:
            async with aiohttp.ClientSession(timeout=timeout) as session:
                with path.open("rb") as body:  # reopened per attempt: a retry resends from the start
                    async with session.put(url, data=body, headers=headers, ssl=ssl_context or True) as resp:
                        if resp.status in (200, 201):
                            return await resp.json(content_type=None)
                        reason = await _reason(resp)
                        if resp.status == DISK_FULL_STATUS and asyncio.get_running_loop().time() < full_until:
                            log.warning("upload to %s: %s; waiting for space", url, reason)
                            attempt -= 1  # not a retry of the tile's own: the master's disk
                            delay = min(5.0, backoff_s * 4)
                        elif resp.status not in _RETRY_STATUS or attempt == retries:
                            raise TransferError(url, reason, resp.status)
                        else:
                            log.warning("upload to %s: HTTP %d (%s), retrying in %.1f s", url, resp.status,
                                        reason, delay)
        except (TimeoutError, aiohttp.ClientConnectionError) as exc:
            if attempt == retries:
                raise TransferError(url, f"upload failed after {retries + 1} attempts "
                                         f"({type(exc).__name__}: {exc})") from exc
            log.warning("upload to %s failed (%s), retrying in %.1f s", url, exc, delay)
        await asyncio.sleep(delay)
    raise AssertionError("unreachable")
