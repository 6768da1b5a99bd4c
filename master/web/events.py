"""Live updates of the page by server-sent events (`GET /ui/events[?job=ID]`).

One stream per open page (`stream`). Once a second (`TICK_S`; the page itself never polls) its `Watcher`
sends only what changed, each as a named event whose data is one JSON object: `jobs` (the jobs table),
`job` (the job `?job=` names, with its units) and `agents` (the agents table, with `server_now`).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from aiohttp import web

from master.store import StoreError
from master.web.views import WebService, agents_view, job_view, jobs_view
from planning.pipeline import AOV_PASS_FILE

TICK_S = 1.0
KEEPALIVE_S = 15.0
AGE_SLACK_S = 5.0  # seconds a "last heard" shown may be off; agents beat every 2 s by default
AGEING = ("last_seen_s", "heard_at")  # the fields that change by the clock alone


def sse(event: str, data: dict[str, Any]) -> bytes:
    """One server-sent event: its name and its data as one line of JSON."""
    return f"event: {event}\ndata: {json.dumps(data, separators=(',', ':'))}\n\n".encode()


@dataclass
class Watcher:
    """What one stream last sent, to send again only what changed."""

    service: WebService
    job_id: str | None
    key: tuple[Any, ...] | None = None
    counts: dict[str, tuple[int, int]] = field(default_factory=dict)  # units done/failed per agent, at `key`
    sent: dict[str, str] = field(default_factory=dict)
    waiting: set[str] = field(default_factory=set)  # jobs done whose report is not written yet
    aov_waiting: set[str] = field(default_factory=set)  # denoised jobs whose AOV pass is not kept yet
    agents_at: float = 0.0  # time.monotonic() when the agents table was last sent
    ages: dict[str, float] = field(default_factory=dict)  # each agent's last_seen_s as last sent

    def _change_key(self) -> tuple[Any, ...]:
        """What says jobs changed: the job store's change counter (`total_changes` of the master's
        connection, through which every award, tile, status change and submission is written) and the
        reports still being assembled, and the denoised jobs' AOV passes still being rendered (which no row
        records). An idle farm costs a counter read a second, not queries."""
        ready = sum(self.service.result_path(j).with_suffix(".json").exists() for j in self.waiting)
        passes = sum((self.service.job_dir(j) / AOV_PASS_FILE).exists() for j in self.aov_waiting)
        return self.service.store.db.total_changes, ready, passes

    def changes(self) -> list[bytes]:
        """The events whose data differ from what this stream sent last."""
        out = []
        key = self._change_key()
        if key != self.key:
            self.key = key
            self.counts = self.service.store.agent_counts()  # a scan of every attempt: only when rows changed
            jobs = jobs_view(self.service)
            self.waiting = {j["job_id"] for j in jobs if j["status"] == "done" and not j["result_ready"]}
            self.aov_waiting = {j["job_id"] for j in jobs if j.get("aov_pass") is False}
            out += self._if_new("jobs", {"jobs": jobs})
            if self.job_id is not None:
                out += self._if_new("job", self._job())
        agents = agents_view(self.service, self.counts)  # every tick: heartbeats change no row
        if self._ages_drifted(agents):
            self.sent.pop("agents", None)
        steady = [{k: v for k, v in row.items() if k not in AGEING} for row in agents]
        sent = self._if_new("agents", {"agents": steady}, send={"agents": agents, "server_now": time.time()})
        if sent:
            self.agents_at, self.ages = time.monotonic(), {row["jid"]: row["last_seen_s"] for row in agents}
        return out + sent

    def _ages_drifted(self, agents: list[dict[str, Any]]) -> bool:
        """Whether an agent's last_seen_s is off by more than AGE_SLACK_S from what the page has aged
        it to since the last agents event. The page ages "last heard" itself, so an idle farm's
        heartbeats (every 2 s) make the stream talk every few seconds, not every second."""
        gone = time.monotonic() - self.agents_at
        return any(abs(self.ages.get(row["jid"], 0.0) + gone - row["last_seen_s"]) > AGE_SLACK_S for row in agents)

    def _job(self) -> dict[str, Any]:
        try:
            return job_view(self.service, str(self.job_id))
        except StoreError as exc:
            return {"job_id": self.job_id, "error": str(exc)}

    def _if_new(self, event: str, data: dict[str, Any], send: dict[str, Any] | None = None) -> list[bytes]:
        """The event, unless `data` equals what was compared last time; `send` is sent instead of `data`."""
        text = json.dumps(data, sort_keys=True)
        if self.sent.get(event) == text:
            return []
        self.sent[event] = text
        return [sse(event, data if send is None else send)]


async def stream(request: web.Request, watcher: Watcher, alive: Callable[[], bool],
                 closing: asyncio.Event) -> web.StreamResponse:
    """Send `watcher`'s changes every TICK_S until the client goes, `alive()` turns false (log out, expiry)
    or `closing` is set (the master stops). A comment every KEEPALIVE_S shows a dead connection to both sides."""
    response = web.StreamResponse(headers={"Content-Type": "text/event-stream", "Cache-Control": "no-store",
                                           "X-Accel-Buffering": "no"})
    await response.prepare(request)
    last_write = time.monotonic()
    try:
        await response.write(b"retry: 3000\n\n")
        while alive() and not closing.is_set():
            chunks = watcher.changes()
            if not chunks and time.monotonic() - last_write >= KEEPALIVE_S:
                chunks = [b": keepalive\n\n"]
            for chunk in chunks:
                await response.write(chunk)
                last_write = time.monotonic()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(closing.wait(), TICK_S)
    except ConnectionError:
        pass  # the browser went away: nothing to answer
    return response
