"""Who may see the web page: a session opened by POSTing the farm's admin token to the login form.

The token travels once, in a form body (never in a URL, so never in a log, a history or a Referer), and
opens a session cookie (`set_cookie`). Every action is a POST with the session's CSRF token
(`require_action`). Only the admin token opens a session: an agent's award token is never looked at here.
Sessions (`Sessions`) live in the master's memory: a restarted master asks again.
"""

from __future__ import annotations

import hmac
import secrets
import time
from dataclasses import dataclass, field

from aiohttp import web

COOKIE = "quekaro_session"
CSRF_HEADER = "X-CSRF-Token"
COOKIE_PATH = "/ui"
IDLE_S = 12 * 3600.0
MAX_SESSIONS = 64


@dataclass
class Session:
    """A logged-in browser: its cookie's id, its CSRF token, when it was last used."""

    id: str
    csrf: str
    seen: float


@dataclass
class Sessions:
    """The open sessions of the page, in memory: each ends after `idle_s` without a request, and at most
    `limit` are kept (the oldest ends first)."""

    idle_s: float = IDLE_S
    limit: int = MAX_SESSIONS
    by_id: dict[str, Session] = field(default_factory=dict)

    def open(self) -> Session:
        """A new session; the least recently used goes when there are too many."""
        self._expire(time.monotonic())
        while len(self.by_id) >= self.limit:
            oldest = min(self.by_id.values(), key=lambda s: s.seen)
            del self.by_id[oldest.id]
        session = Session(secrets.token_urlsafe(32), secrets.token_urlsafe(32), time.monotonic())
        self.by_id[session.id] = session
        return session

    def find(self, session_id: str | None) -> Session | None:
        """The live session with this id (its idle clock restarts), or None."""
        now = time.monotonic()
        self._expire(now)
        session = self.by_id.get(session_id or "")  # ids are 256 random bits: nothing to learn from timing
        if session is not None:
            session.seen = now
        return session

    def alive(self, session: Session) -> bool:
        """Whether the session is still open (a stream ends when its session does); an open page's stream
        keeps its session from expiring."""
        if self.by_id.get(session.id) is not session or time.monotonic() - session.seen >= self.idle_s:
            return False
        session.seen = time.monotonic()
        return True

    def close(self, session: Session) -> None:
        self.by_id.pop(session.id, None)

    def _expire(self, now: float) -> None:
        for sid in [s.id for s in self.by_id.values() if now - s.seen >= self.idle_s]:
            del self.by_id[sid]


def token_matches(given: str, admin_token: str) -> bool:
    """The admin token, compared in constant time (an empty one never matches)."""
    return bool(given) and hmac.compare_digest(given.encode(), admin_token.encode())


def set_cookie(response: web.StreamResponse, request: web.Request, session: Session) -> None:
    """The session cookie: HttpOnly (no script reads it), SameSite=Strict (no other site's page sends it),
    on /ui only, Secure over HTTPS."""
    response.set_cookie(COOKIE, session.id, path=COOKIE_PATH, httponly=True, samesite="Strict",
                        secure=request.secure)


def clear_cookie(response: web.StreamResponse) -> None:
    response.del_cookie(COOKIE, path=COOKIE_PATH)


def session_of(request: web.Request, sessions: Sessions) -> Session | None:
    """The request's session, from its cookie alone (no header or query token opens the page: an award
    token, `X-Quekaro-Token` or bearer, gets the login form and no page)."""
    return sessions.find(request.cookies.get(COOKIE))


def unauthorized() -> web.HTTPUnauthorized:
    # The reason, not a body: the data plane's middleware answers every HTTP error as JSON {"error": reason}.
    return web.HTTPUnauthorized(reason="log in first: no valid session cookie")


def require(request: web.Request, sessions: Sessions) -> Session:
    """The request's session, or 401 (for the page's data and streams)."""
    session = session_of(request, sessions)
    if session is None:
        raise unauthorized()
    return session


async def require_action(request: web.Request, sessions: Sessions) -> Session:
    """The session of a POST that carries its CSRF token (header `X-CSRF-Token` or form field `csrf`), or
    401/403. The page reads the token from a meta tag of its HTML; a forged cross-site POST has neither
    the cookie (SameSite) nor the token."""
    session = require(request, sessions)
    given = request.headers.get(CSRF_HEADER, "")
    if not given and request.content_type == "application/x-www-form-urlencoded":
        given = str((await request.post()).get("csrf", ""))
    if not given or not hmac.compare_digest(given.encode(), session.csrf.encode()):
        raise web.HTTPForbidden(reason=f"missing or wrong CSRF token (header {CSRF_HEADER})")
    return session
