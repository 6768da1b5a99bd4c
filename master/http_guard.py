"""Time limits on the master's HTTP connections, which aiohttp does not have: a client must finish its
request headers within HEADER_TIMEOUT_S of connecting, and a body must keep coming at MIN_BODY_RATE
(after a BODY_GRACE_S start). Without them, connections that trickle headers or bodies stay open for
as long as the client likes (20 such connections were seen open past 140 s).

Each connection serves one request (keep-alive off), so the header limit covers every request. aiohttp's
own handler does the HTTP; `GuardedProtocol` only watches the bytes go by and closes the connection when
a limit runs out. `read_body_chunks` applies the body limit where a route streams its body. The parts of
a request that every route checks alike are here too: job ids and unit indices in paths, bearer tokens.
"""

from __future__ import annotations

import asyncio
import errno
import re
import socket
import ssl
import time
from collections.abc import AsyncIterator, Callable
from typing import Any

from aiohttp import web

from core.transport.peers import describe_peer

HEADER_TIMEOUT_S = 10.0
BODY_GRACE_S = 30.0
MIN_BODY_RATE = 64 * 1024  # bytes per second, on average, after the grace period
LINGER_S = 2.0
_END_OF_HEADERS = b"\r\n\r\n"
JOB_PART = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,127}")  # a job id in a path
UNIT_PART = re.compile(r"[0-9]{1,9}")  # ASCII digits only: str.isdigit also takes '²' (int() fails) and '١'


def bearer_token(request: web.Request) -> str:
    """The token of `Authorization: Bearer ...` (the scheme in any case, RFC 9110), else ''."""
    scheme, _, token = request.headers.get("Authorization", "").partition(" ")
    return token.strip() if scheme.lower() == "bearer" else ""


class GuardedProtocol(asyncio.Protocol):
    """Wraps aiohttp's request handler: closes a connection whose headers are not complete in time."""

    def __init__(self, inner: asyncio.Protocol, loop: asyncio.AbstractEventLoop, header_timeout: float) -> None:
        self.inner = inner
        self._loop = loop
        self._timeout = header_timeout
        self._tail = b""
        self._timer: asyncio.TimerHandle | None = None
        self._transport: asyncio.Transport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self._transport = transport  # type: ignore[assignment]
        self._timer = self._loop.call_later(self._timeout, self._too_slow)
        self.inner.connection_made(transport)

    def data_received(self, data: bytes) -> None:
        if self._timer is not None:
            seen = self._tail + data
            if _END_OF_HEADERS in seen:
                self._timer.cancel()
                self._timer = None
            self._tail = seen[-3:]
        self.inner.data_received(data)

    def _too_slow(self) -> None:
        if self._transport is not None:
            self._transport.close()

    def connection_lost(self, exc: Exception | None) -> None:
        if self._timer is not None:
            self._timer.cancel()
        self.inner.connection_lost(exc)

    def eof_received(self) -> bool | None:
        return self.inner.eof_received()

    def pause_writing(self) -> None:
        self.inner.pause_writing()

    def resume_writing(self) -> None:
        self.inner.resume_writing()


def bind_free_port(host: str) -> socket.socket:
    """A socket bound now to a free port of `host` (its first address), for `serve(sock=...)`: its port is
    known before the app is served, and nothing can take it in between."""
    family, kind, proto, _, address = socket.getaddrinfo(host, 0, type=socket.SOCK_STREAM)[0]
    sock = socket.socket(family, kind, proto)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(address)
    except OSError:
        sock.close()
        raise
    return sock


async def serve(app: web.Application, host: str, port: int, header_timeout: float | None = None,
                ssl_context: ssl.SSLContext | None = None, sock: socket.socket | None = None
                ) -> tuple[web.AppRunner, int]:
    """Serve `app` on host:port (0: a free port), or on the bound `sock` when given, behind the header
    guard, one request a connection, over TLS with `ssl_context` (its handshake within the header time
    limit); returns the runner (its cleanup() stops everything) and the port."""
    header_timeout = HEADER_TIMEOUT_S if header_timeout is None else header_timeout
    listening: list[asyncio.AbstractServer] = []

    async def close(_app: web.Application) -> None:
        for server in listening:
            server.close()

    app.on_response_prepare.append(_one_request_per_connection)
    app.on_cleanup.append(close)
    # A refused request's unread body is read for LINGER_S at most, so that a client still sending can
    # read the refusal, and a stalled body does not hold the connection (aiohttp's default is 10 s).
    runner = web.AppRunner(app, access_log=None, lingering_time=LINGER_S)
    await runner.setup()
    loop = asyncio.get_running_loop()
    handler: Callable[[], Any] = runner.server  # aiohttp's protocol factory
    where = {"sock": sock} if sock is not None else {"host": host, "port": port, "reuse_address": True}
    server = await loop.create_server(lambda: GuardedProtocol(handler(), loop, header_timeout), **where,
                                      ssl=ssl_context, ssl_handshake_timeout=header_timeout if ssl_context else None)
    listening.append(server)
    return runner, server.sockets[0].getsockname()[1]


async def _one_request_per_connection(_request: web.Request, response: web.StreamResponse) -> None:
    response.force_close()  # keep-alive off: the header limit then covers every request


async def read_body_chunks(request: web.Request, chunk: int = 1 << 20) -> AsyncIterator[bytes]:
    """The request body a chunk at a time; 408 once it falls behind MIN_BODY_RATE after BODY_GRACE_S."""
    start, received, grace_s, rate = time.monotonic(), 0, BODY_GRACE_S, MIN_BODY_RATE
    while True:
        allowed = start + grace_s + received / rate - time.monotonic()
        try:
            data = await asyncio.wait_for(request.content.read(chunk), timeout=max(allowed, 0.001))
        except TimeoutError:
            raise web.HTTPRequestTimeout(text="the request body came too slowly") from None
        if not data:
            return
        received += len(data)
        yield data


class Refusal(Exception):
    """A request refused with an HTTP status and a reason for the client (the apps' error middleware
    answers it as `json_error`)."""

    def __init__(self, status: int, reason: str) -> None:
        super().__init__(reason)
        self.status, self.reason = status, reason


def sender_of(request: web.Request) -> str:
    """Who sent `request`, for the log of a refusal: its address, and on loopback the local user."""
    transport = request.transport
    if transport is None:
        return "(gone)"
    return describe_peer(transport.get_extra_info("peername"), transport.get_extra_info("sockname"))


def json_error(status: int, reason: str) -> web.Response:
    """Every error the master's APIs answer: {"error": reason, "status": status}."""
    return web.json_response({"error": reason, "status": status}, status=status)


def disk_full(exc: BaseException | None) -> bool:
    """ENOSPC, raised as is or as the cause of an error that names the file (core.image.imageio)."""
    for _ in range(8):  # a cause chain is short; a cycle must not hang the handler
        if exc is None:
            return False
        if isinstance(exc, OSError) and exc.errno == errno.ENOSPC:
            return True
        exc = exc.__cause__ or exc.__context__
    return False
