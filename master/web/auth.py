"""Who may see the web page: a session opened by POSTing the farm's admin token to the login form.

- The token travels once, in a form body (never in a URL, so never in a log, a history or a Referer); the
  answer sets a random session id in a cookie that is HttpOnly (no script reads it), SameSite=Strict (no
  other site's page sends it) and Secure when the master serves HTTPS.
- Every action (cancel, re-submit, log out) is a POST that must carry the session's CSRF token in the
  `X-CSRF-Token` header (or a `csrf` form field); the page reads it from a meta tag of the HTML it was
  served. A forged cross-site POST has neither the cookie (SameSite) nor the token.
- Only the admin token opens a session: an agent's award token (`X-Quekaro-Token`, or as a bearer token)
  is never looked at here, so it gets the login form and no page.
- Sessions live in the master's memory (a restarted master asks again), end after `IDLE_S` without a
  request, and at most `MAX_SESSIONS` are kept (the oldest ends first).
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
    """The open sessions of the page, in memory."""

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
    """The session cookie: HttpOnly, SameSite=Strict, on /ui only, Secure over HTTPS."""
    response.set_cookie(COOKIE, session.id, path=COOKIE_PATH, httponly=True, samesite="Strict",
                        secure=request.secure)


def clear_cookie(response: web.StreamResponse) -> None:
    response.del_cookie(COOKIE, path=COOKIE_PATH)


def session_of(request: web.Request, sessions: Sessions) -> Session | None:
    """The request's session, from its cookie alone (no header or query token opens the page)."""
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
    """The session of a POST that carries its CSRF token (header or form field), or 401/403."""
    session = require(request, sessions)
    given = request.headers.get(CSRF_HEADER, "")
    if not given and request.content_type == "application/x-www-form-urlencoded":
        given = str((await request.post()).get("csrf", ""))
    if not given or not hmac.compare_digest(given.encode(), session.csrf.encode()):
        raise web.HTTPForbidden(reason=f"missing or wrong CSRF token (header {CSRF_HEADER})")
    return session
