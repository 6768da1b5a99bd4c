"""Agent accounts that more than one client uses at once, told apart by the resource of their JID.

Two agents started with the same JID both receive what the master sends to it: each renders every unit
awarded to that JID, and the second upload of each tile is refused. The master cannot tell which is
meant, so it says so (its log, `quekaro agents`) instead of guessing. A restarted agent is not a second
client: its new resource starts after the old one fell silent, where two live clients' messages overlap
in time. Pure: (sender, resource, time) in, what to say out.
"""

from __future__ import annotations

from dataclasses import dataclass, field

WINDOW_S = 60.0  # a resource silent this long no longer counts (a few missed heartbeats)
MAX_RESOURCES = 8  # kept per JID, the most recent: a client that makes up resources costs no more


@dataclass
class _Span:
    first: float
    last: float


@dataclass
class SharedAccounts:
    """Per bare JID, the recent span of each of its resources' messages."""

    window_s: float = WINDOW_S
    _spans: dict[str, dict[str, _Span]] = field(default_factory=dict)
    _said: set[str] = field(default_factory=set)

    def seen(self, jid: str, resource: str, now: float) -> str | None:
        """Record a message; return a warning the first time (in a while) two clients share `jid`."""
        spans = self._spans.setdefault(jid, {})
        span = spans.setdefault(resource, _Span(now, now))
        span.last = now
        if len(spans) > MAX_RESOURCES:
            del spans[min(spans, key=lambda r: spans[r].last)]
        sharing = self.sharing(jid, now)
        if len(sharing) < 2:
            self._said.discard(jid)
            return None
        if jid in self._said:
            return None
        self._said.add(jid)
        return note(jid, sharing)

    def sharing(self, jid: str, now: float) -> list[str]:
        """The resources of `jid` whose recent messages overlap another's in time (none if only one)."""
        spans = self._spans.get(jid, {})
        for resource in [r for r, s in spans.items() if now - s.last > self.window_s]:
            del spans[resource]
        if not spans:
            self._spans.pop(jid, None)
            return []
        live = sorted(spans)
        return [r for r in live if any(o != r and _overlap(spans[r], spans[o]) for o in live)]


def note(jid: str, resources: list[str]) -> str:
    """What the master says of a JID that these clients (resources) share."""
    return (f"{len(resources)} clients log in as {jid} (resources {', '.join(resources)}): each receives what "
            f"the master sends to it and renders every unit awarded to it; give each agent its own JID")


def _overlap(a: _Span, b: _Span) -> bool:
    return a.first <= b.last and b.first <= a.last
