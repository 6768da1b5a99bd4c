"""Prosody's registration: closed by default, open only to QUEKARO_REGISTRATION_ALLOWLIST (how
docker-compose lets `--scale agent=N` agents create their own accounts on its private network)."""

from __future__ import annotations

import asyncio

import pytest
from prosody_support import needs_prosody
from spade.agent import Agent, AuthenticationFailure

from core.transport.xmpp import FarmAgent, XmppError
from core.transport.xmpp_server import ProsodyServer

pytestmark = [
    pytest.mark.slow,
    needs_prosody,
]


async def _register(port: int, jid: str) -> None:
    agent = FarmAgent(jid, "secret-pw", port=port, server="127.0.0.1", reconnect=False)
    try:
        await Agent.start(agent, auto_register=True)  # SPADE's in-band registration: the farm never uses it
    finally:
        await agent.stop()


@pytest.mark.parametrize(("allowlist", "allowed"), [(None, False), ("10.0.0.0/8", False),
                                                    ("10.0.0.0/8, 127.0.0.0/8", True)])
def test_registration_follows_the_allowlist(tmp_path, monkeypatch, allowlist, allowed):
    if allowlist is None:
        monkeypatch.delenv("QUEKARO_REGISTRATION_ALLOWLIST", raising=False)
    else:
        monkeypatch.setenv("QUEKARO_REGISTRATION_ALLOWLIST", allowlist)
    with ProsodyServer(tmp_path / "prosody") as server:
        if allowed:
            asyncio.run(_register(server.port, "agent-x@localhost"))
        else:
            with pytest.raises((XmppError, AuthenticationFailure)):
                asyncio.run(_register(server.port, "agent-x@localhost"))
