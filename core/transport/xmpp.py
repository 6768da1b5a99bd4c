"""The XMPP transport both farm agents stand on: a SPADE agent that moves validated strings, nothing more.

`FarmAgent` connects with its own JID and password, comes back by itself after a drop, `send`s messages
with their metadata, and hands a message (an `Envelope`) to the code above only once its sender, size
and metadata pass; a refusal is logged and counted (`Refusal`), never raised. What a body means is
decided above: a `validate` callback, typically `core.model.messages.parse`, may refuse it. SPADE's
pitfalls it avoids are at the code that avoids them (docs/design.md section 4).
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import logging
import ssl
import time
from collections.abc import Awaitable, Callable, Collection, Iterable
from dataclasses import dataclass
from typing import Any

from slixmpp import JID
from slixmpp.exceptions import IqError, IqTimeout
from spade.agent import Agent, AuthenticationFailure, DisconnectedException
from spade.message import Message

from core.errors import MessageError, QuekaroError
from core.transport.rates import SenderRates
from core.transport.tmp_cleanup import remove_upload_dir_at_exit

log = logging.getLogger(__name__)
remove_upload_dir_at_exit()  # `spade` imports pyjabber

METADATA_KEYS = ("performative", "ontology", "protocol", "conversation-id")
DEFAULT_ONTOLOGY = "quekaro"
# Prosody's default c2s stanza limit is 256 KiB and a larger stanza disconnects the sender without an
# error in SPADE: keep bodies far below it (scenes and tiles travel over HTTP, not XMPP).
DEFAULT_MAX_BODY = 64 * 1024
INBOX_SIZE = 1000
SESSION_TIMEOUT_S = 8.0
# A ping to the server every KEEPALIVE_S; no answer within KEEPALIVE_TIMEOUT_S: the link is dead, reconnect.
# Within the master's heartbeat timeout (15 s, master.auction.state.Config), so a silent agent is reconnecting by the
# time the master gives its units back. (SPADE's own keepalive, every 55 s, is replaced.)
KEEPALIVE_S = 5.0
KEEPALIVE_TIMEOUT_S = 10.0


@dataclass(frozen=True)
class Envelope:
    """One accepted message: who sent it, its metadata and its (still opaque) body."""

    sender: str  # bare JID, as stamped by the server
    to: str
    performative: str
    ontology: str
    protocol: str
    conversation_id: str
    body: str
    received_at: float  # time.monotonic() on arrival
    resource: str = ""  # the sender's resource: which of the clients logged in as `sender` sent it


@dataclass(frozen=True)
class Refusal:
    """A message that never reached the handler, and why."""

    sender: str
    kind: str  # sender | rate | size | body | metadata | invalid | inbox
    reason: str
    performative: str | None
    conversation_id: str | None
    size: int


class _Refused(Exception):
    def __init__(self, kind: str, reason: str) -> None:
        super().__init__(reason)
        self.kind, self.reason = kind, reason


class XmppError(QuekaroError):
    """A connection that could not be made (wrong password, server unreachable, registration closed)."""


Handler = Callable[[Envelope], Awaitable[None]]
Validator = Callable[[str, str], object]  # (performative, body) -> anything; raises to refuse
SenderCheck = Callable[[str], bool]  # bare JID -> accepted?


class FarmAgent(Agent):
    """A SPADE agent with a guarded inbox, a one-call `send`, and reconnection by itself.

    Typical use (the master or a render agent subclasses it or wraps it):

        agent = FarmAgent("agent-1@localhost", pw, port=5222, peers={"master@localhost"},
                          validate=core.model.messages.parse)
        agent.set_handler(on_message)            # async def on_message(env: Envelope) -> None
        await agent.start()   # waits for the session; raises XmppError
        await agent.send("master@localhost", "propose", body, conversation_id="job1/u3",
                         protocol="fipa-contract-net")
        ...
        await agent.stop()

    Messages that pass the gate go to the handler (one at a time, in arrival order) and to any SPADE
    behaviour whose template matches them; refused ones reach neither. SPADE's web interface, which can
    stop an agent with one unauthenticated GET, is never started.
    """

    def __init__(
        self,
        jid: str,
        password: str,
        *,
        port: int = 5222,
        server: str | None = None,
        ontology: str = DEFAULT_ONTOLOGY,
        peers: Iterable[str] = (),
        accept_sender: SenderCheck | None = None,
        validate: Validator | None = None,
        performatives: Collection[str] | None = None,
        max_body: int = DEFAULT_MAX_BODY,
        verify_security: bool = False,
        ca_file: str | None = None,
        reconnect: bool = True,
        reconnect_max_delay: float = 1.0,
        keepalive_s: float = KEEPALIVE_S,
        keepalive_timeout_s: float = KEEPALIVE_TIMEOUT_S,
        rates: SenderRates | None = None,
    ) -> None:
        super().__init__(jid, password, port=port, verify_security=verify_security)
        self.server = server or self.jid.host
        self.ontology = ontology
        self.peers: set[str] = {JID(p).bare for p in peers}
        self.accept_sender = accept_sender
        self.validate = validate
        self.performatives = frozenset(performatives) if performatives else None
        self.max_body = max_body
        self.ca_file = ca_file
        self.reconnect = reconnect
        self.reconnect_max_delay = reconnect_max_delay
        self.keepalive_s, self.keepalive_timeout_s = keepalive_s, keepalive_timeout_s
        self.rates = rates  # each sender's allowance (core.transport.rates), drawn before its message is read
        self.refusals: collections.Counter[str] = collections.Counter()
        self.recent_refusals: collections.deque[Refusal] = collections.deque(maxlen=100)
        self.on_refusal: Callable[[Refusal], None] | None = None
        self.reconnects = 0
        self.last_outage_s: float | None = None
        self.tls = False
        self._handler: Handler | None = None
        self._inbox: asyncio.Queue[Envelope] | None = None
        self._inbox_task: asyncio.Task | None = None
        self._online = asyncio.Event()
        self._stopping = False
        self._down_since: float | None = None
        self._reconnect_task: asyncio.Task | None = None
        self._keepalive_task: asyncio.Task | None = None
        self._sessions = 0  # sessions started so far: a ping's answer counts for the session it was sent in

    # ---- public API -------------------------------------------------------------------------------

    @property
    def bare_jid(self) -> str:
        return str(self.jid.bare)

    @property
    def online(self) -> bool:
        """True while an XMPP session is up (messages can be sent)."""
        return self._online.is_set()

    def set_handler(self, handler: Handler | None) -> None:
        """The coroutine function every accepted message is given to, one at a time, in order."""
        self._handler = handler

    def allow_peer(self, jid: str) -> None:
        """Accept messages from this JID (bare or full) from now on."""
        self.peers.add(JID(jid).bare)

    def forget_peer(self, jid: str) -> None:
        self.peers.discard(JID(jid).bare)

    async def start(self, timeout: float = 30.0) -> None:
        """Connect, open the session and start the inbox; retries until `timeout` while the server is down.

        The account must exist (the farm makes every account ahead; registration is closed). Raises
        XmppError on a wrong password or a server that never answers.
        """
        self._stopping = False
        deadline = time.monotonic() + timeout
        while True:
            try:
                await super().start(auto_register=False)
                return
            except XmppError:  # a certificate not trusted: trying again for `timeout` changes nothing
                await self._drop_client()
                raise
            except AuthenticationFailure as exc:
                await self._drop_client()
                raise XmppError(f"XMPP login refused for {self.bare_jid} on {self.server}:{self.xmpp_port}"
                                " (account missing or wrong password)") from exc
            except (TimeoutError, DisconnectedException, OSError) as exc:
                await self._drop_client()
                if time.monotonic() > deadline:
                    raise XmppError(f"no XMPP session for {self.bare_jid} at {self.server}:{self.xmpp_port} "
                                    f"within {timeout:.0f} s: {exc}") from exc
                await asyncio.sleep(0.5)

    async def wait_online(self, timeout: float | None = None) -> bool:
        """Wait until a session is up; False if `timeout` passes first."""
        try:
            await asyncio.wait_for(self._online.wait(), timeout)
            return True
        except TimeoutError:
            return False

    async def send(self, to: str, performative: str, body: str, *, conversation_id: str,
                   protocol: str, ontology: str | None = None, thread: str | None = None) -> bool:
        """Send one message over the XMPP socket (never in-process, as SPADE delivers between two agents
        of one process). False when offline (not queued).

        Raises MessageError when the message itself is unsendable (empty body or metadata, too large).
        """
        meta = {"performative": performative, "ontology": ontology or self.ontology,
                "protocol": protocol, "conversation-id": conversation_id}
        for key, value in meta.items():
            if not isinstance(value, str) or not value:
                raise MessageError(f"metadata {key} must be a non-empty string", field=key)
        if not isinstance(body, str) or not body.strip():
            raise MessageError("message body is empty (XMPP drops empty bodies silently)", field="body")
        if len(body.encode()) > self.max_body:
            raise MessageError(f"body of {len(body.encode())} bytes exceeds the limit of {self.max_body}",
                               field="body")
        if not self.online or self.client is None:
            log.info("%s offline: %s to %s not sent", self.bare_jid, performative, to)
            return False
        # The full JID (with this session's resource), as Prosody stamps it and the embedded server does not:
        # the master tells apart two clients that log in with one JID by it (master.sessions).
        msg = Message(to=to, sender=str(self.client.boundjid), body=body, thread=thread or conversation_id,
                      metadata=meta)
        msg.prepare(self.client).send()
        return True

    # ---- SPADE hooks --------------------------------------------------------------------------------

    async def setup(self) -> None:
        if self._inbox_task is None or self._inbox_task.done():
            self._inbox = asyncio.Queue(maxsize=INBOX_SIZE)
            self._inbox_task = asyncio.create_task(self._drain_inbox(), name=f"inbox {self.bare_jid}")
        if self._keepalive_task is None or self._keepalive_task.done():
            self._keepalive_task = asyncio.create_task(self._keepalive(), name=f"keepalive {self.bare_jid}")

    async def stop(self) -> None:
        self._stopping = True
        for task in (self._reconnect_task, self._inbox_task, self._keepalive_task):
            if task and not task.done():
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await task
        self._online.clear()
        if self.client is not None and not self.is_alive():
            await self._drop_client()
        await super().stop()

    async def _async_connect(self) -> None:
        """Replaces SPADE's: same events, plus TLS settings, the server address and the reconnect hook."""
        client = self.client
        if self.ca_file:
            client.ssl_context = ssl.create_default_context(cafile=self.ca_file)
        # SPADE's keepalive (xep_0199, every 55 s, 30 s timeout, then slixmpp's own reconnect with its backoff)
        # is replaced by `_keepalive`, which hands a dead link to the reconnect loop.
        client.cancel_schedule("Ping keepalive")
        # A client from a failed start attempt may still fire events: only the current one counts.
        def current(handler: Callable[[object], None]) -> Callable[[object], None]:
            return lambda event: handler(event) if client is self.client else None

        client.add_event_handler("session_start", current(self._on_session_start))
        client.add_event_handler("tls_success", current(self._on_tls))
        client.add_event_handler("disconnected", current(self._on_disconnected))
        client.add_event_handler("message", current(self._message_received))
        outcome: asyncio.Future[str] = asyncio.get_running_loop().create_future()

        def settle(result: str) -> Callable[[object], None]:
            return lambda _event: outcome.done() or outcome.set_result(result)

        client.add_event_handler("session_start", settle("ok"), disposable=True)
        client.add_event_handler("failed_all_auth", settle("auth"), disposable=True)
        client.add_event_handler("disconnected", settle("down"), disposable=True)
        client.add_event_handler("connection_failed", settle("down"), disposable=True)

        failed_tls: list[str] = []  # why STARTTLS failed; slixmpp fires this after its connection_lost

        def tls_failed(exc: object) -> None:  # handled here, slixmpp leaves the disconnect to us
            failed_tls.append(self._tls_failure(exc))
            outcome.done() or outcome.set_result("down")
            client.disconnect()

        client.add_event_handler("ssl_invalid_chain", tls_failed, disposable=True)
        client.connect(host=self.server, port=self.xmpp_port)
        try:
            result = await asyncio.wait_for(outcome, timeout=SESSION_TIMEOUT_S)
        finally:  # a reconnect's failure is slixmpp's own again (its reconnect loop retries)
            client.del_event_handler("ssl_invalid_chain", tls_failed)
        if failed_tls:
            raise XmppError(failed_tls[0])
        if result == "auth":
            raise AuthenticationFailure(f"authentication failed for {self.bare_jid}")
        if result == "down":
            raise DisconnectedException(f"no session with {self.server}:{self.xmpp_port}")
        log.info("%s connected to %s:%d (tls=%s)", self.bare_jid, self.server, self.xmpp_port, self.tls)

    def _tls_failure(self, exc: object) -> str:
        """Why STARTTLS with the XMPP server failed, naming what the user can fix."""
        where = f"XMPP server {self.server}:{self.xmpp_port}"
        if not isinstance(exc, ssl.SSLCertVerificationError):
            return f"{where}: TLS handshake failed ({exc})"
        if exc.verify_code == 62:  # X509_V_ERR_HOSTNAME_MISMATCH
            return f"{where}: its certificate does not name the domain {self.jid.host} ({exc.verify_message})"
        trusted = f"the CA file {self.ca_file}" if self.ca_file else "the system's CAs"
        return f"{where}: its certificate is not trusted by {trusted} ({exc.verify_message})"

    # ---- connection state ---------------------------------------------------------------------------

    def _on_tls(self, _event: object) -> None:
        self.tls = True

    def _on_session_start(self, _event: object) -> None:
        self._sessions += 1
        if self._down_since is not None:
            self.last_outage_s = time.monotonic() - self._down_since
            self.reconnects += 1
            log.warning("%s back online after %.2f s", self.bare_jid, self.last_outage_s)
            self._down_since = None
        self._online.set()

    def _on_disconnected(self, reason: object) -> None:
        """Start the reconnect loop at once (SPADE alone reconnects only at its 55 s keepalive)."""
        was_online = self._online.is_set()
        self._online.clear()
        if self._stopping or not self.reconnect or not self.is_alive():
            return
        if was_online:
            self._down_since = time.monotonic()
            log.warning("%s lost its XMPP session (%s): reconnecting", self.bare_jid, reason or "no reason")
        if self._reconnect_task is None or self._reconnect_task.done():
            self._reconnect_task = asyncio.create_task(self._reconnect_loop(),
                                                       name=f"reconnect {self.bare_jid}")

    async def _reconnect_loop(self) -> None:
        """Try again quickly (0.25 s, doubling to `reconnect_max_delay`) until a session is up.

        slixmpp's own retry backs off 1, 3, 7, 15 ... s; a farm wants its agents back within a second
        or two of the server, so the TCP port is polled and slixmpp is asked to connect when it answers.
        """
        delay = 0.25
        while not self._stopping and not self._online.is_set():
            if await _port_open(self.server, self.xmpp_port) and not self.client.is_connecting():
                self.client.connect(host=self.server, port=self.xmpp_port)
                if await self.wait_online(timeout=SESSION_TIMEOUT_S):
                    return
                self.client.cancel_connection_attempt()
                self.client.abort()
            await asyncio.sleep(delay)
            delay = min(delay * 2, self.reconnect_max_delay)

    async def _keepalive(self) -> None:
        """Ping the server every `keepalive_s` while online; a ping unanswered for `keepalive_timeout_s` in the
        same session means a dead link: the connection is dropped, and `_on_disconnected` reconnects.

        A dead link (a pulled cable: no FIN, no RST) leaves TCP open while the kernel retransmits with
        backoff: without this, a host back after 30 s was heard again only ~25 s later (measured,
        tests/test_multihost.py); with it, within a second or two of the link."""
        while not self._stopping:
            await asyncio.sleep(self.keepalive_s)
            client, session = self.client, self._sessions
            if not self.online or client is None:
                continue
            try:
                await client["xep_0199"].ping(client.boundjid.host, timeout=self.keepalive_timeout_s)
            except IqTimeout:
                if client is self.client and session == self._sessions and self.online and not self._stopping:
                    log.warning("%s: no answer from %s:%d to a ping within %.0f s: dropping the connection",
                                self.bare_jid, self.server, self.xmpp_port, self.keepalive_timeout_s)
                    client.abort()
            except IqError:
                pass  # an answer, even an error, comes over a live link
            except Exception as exc:  # a ping that cannot be sent (disconnecting meanwhile): the next one tells
                log.debug("%s: keepalive ping failed: %s", self.bare_jid, exc)

    async def _drop_client(self) -> None:
        if self.client is None:
            return
        with contextlib.suppress(Exception):
            self.client.cancel_connection_attempt()
            self.client.abort()

    # ---- the gate -----------------------------------------------------------------------------------

    def _message_received(self, msg: Any) -> list[asyncio.Task]:
        """A message stanza from the XMPP stream: a sender past its allowance (`rates`), known or not, is
        refused here, before SPADE converts the stanza, so that a refused message costs no conversion."""
        if self.rates is not None:
            sender = str(msg["from"].bare)
            if not self.rates.allow(sender, time.monotonic()):
                self._rate_refused(self.rates, sender, msg)
                return []
        return super()._message_received(msg)

    def _rate_refused(self, rates: SenderRates, sender: str, stanza: Any) -> None:
        reason = f"over {rates.rate:g} messages a second (burst {rates.burst:g})"
        self._record_refusal(Refusal(sender=sender, kind="rate", reason=reason, performative=None,
                                     conversation_id=None, size=len(str(stanza["body"]).encode())))
        count = rates.report(sender, time.monotonic())
        if count:
            log.warning("%s refused %d message(s) from %s since it last said so: %s", self.bare_jid, count,
                        sender, reason)

    def dispatch(self, msg: Message) -> list[asyncio.Task]:
        """Every incoming message passes here (SPADE calls it for XMPP and in-process delivery alike)."""
        try:
            envelope = self._check(msg)
        except _Refused as exc:
            self._refuse(msg, exc.kind, exc.reason)
            return []
        except MessageError as exc:
            self._refuse(msg, "invalid", str(exc))
            return []
        except Exception as exc:  # a validator's bug must not kill the agent
            self._refuse(msg, "invalid", f"validator raised {type(exc).__name__}: {exc}")
            return []
        if self._handler is not None and self._inbox is not None:
            try:
                self._inbox.put_nowait(envelope)
            except asyncio.QueueFull:
                self._refuse(msg, "inbox", f"inbox full ({INBOX_SIZE} messages waiting)")
                return []
        if any(b.match(msg) for b in self.behaviours):
            return super().dispatch(msg)
        return []

    def _check(self, msg: Message) -> Envelope:
        sender = str(msg.sender.bare) if msg.sender else ""
        if not self._sender_known(sender):
            raise _Refused("sender", f"unknown sender {sender or '(none)'}")
        body = msg.body or ""
        size = len(body.encode())
        if size == 0:
            raise _Refused("body", "empty body")
        if size > self.max_body:
            raise _Refused("size", f"body of {size} bytes exceeds the limit of {self.max_body}")
        meta = {key: msg.get_metadata(key) for key in METADATA_KEYS}
        for key, value in meta.items():
            if not value:
                raise _Refused("metadata", f"metadata {key!r} missing")
        if meta["ontology"] != self.ontology:
            raise _Refused("metadata", f"unknown ontology {meta['ontology']!r}")
        if self.performatives is not None and meta["performative"] not in self.performatives:
            raise _Refused("metadata", f"unexpected performative {meta['performative']!r}")
        if self.validate is not None:
            self.validate(meta["performative"], body)
        return Envelope(sender=sender, to=str(msg.to.bare) if msg.to else "",
                        performative=meta["performative"], ontology=meta["ontology"],
                        protocol=meta["protocol"], conversation_id=meta["conversation-id"],
                        body=body, received_at=time.monotonic(),
                        resource=str(msg.sender.resource or "") if msg.sender else "")

    def _sender_known(self, sender: str) -> bool:
        if not sender:
            return False
        if sender in self.peers:
            return True
        return bool(self.accept_sender and self.accept_sender(sender))

    def _refuse(self, msg: Message, kind: str, reason: str) -> None:
        refusal = Refusal(sender=str(msg.sender.bare) if msg.sender else "", kind=kind, reason=reason,
                          performative=msg.get_metadata("performative"),
                          conversation_id=msg.get_metadata("conversation-id"),
                          size=len((msg.body or "").encode()))
        self._record_refusal(refusal)

    def _record_refusal(self, refusal: Refusal) -> None:
        self.refusals[refusal.kind] += 1
        self.recent_refusals.append(refusal)
        if refusal.kind != "rate":  # a flood is logged now and then by `_rate_refused`, not per message
            log.warning("%s refused a message from %s: %s", self.bare_jid, refusal.sender or "(none)",
                        refusal.reason)
        if self.on_refusal is not None:
            try:
                self.on_refusal(refusal)
            except Exception:
                log.exception("on_refusal callback failed")

    async def _drain_inbox(self) -> None:
        assert self._inbox is not None
        while True:
            envelope = await self._inbox.get()
            handler = self._handler
            if handler is None:
                continue
            try:
                await handler(envelope)
            except asyncio.CancelledError:
                raise
            except Exception:
                log.exception("%s: handler failed on %s from %s (conversation %s)", self.bare_jid,
                              envelope.performative, envelope.sender, envelope.conversation_id)


async def _port_open(host: str, port: int, timeout: float = 1.0) -> bool:
    try:
        _reader, writer = await asyncio.wait_for(asyncio.open_connection(host, port), timeout)
    except (TimeoutError, OSError):
        return False
    writer.close()
    with contextlib.suppress(Exception):
        await writer.wait_closed()
    return True
