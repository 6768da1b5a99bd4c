"""Trust on one machine: the local farm's XMPP server lets only the accounts the farm makes register,
and the master takes bids only from the agents it was told of (its allowlist)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from core.transport.xmpp_server import EmbeddedXmppServer
from master.service import MasterConfig, MasterService

REPO = Path(__file__).resolve().parent.parent
PEER = REPO / "tests" / "xmpp_peer.py"


def _register(port: int, user: str) -> list[dict]:
    done = subprocess.run([sys.executable, str(PEER), "--jid", f"{user}@localhost", "--password", "pw-123",
                           "--port", str(port), "--server", "127.0.0.1", "--register", "--connect-timeout",
                           "20", "--linger", "0", "send", "--to", "nobody@localhost", "--count", "0"],
                          capture_output=True, text=True, timeout=90, cwd=REPO)
    return [json.loads(line) for line in done.stdout.splitlines() if line.startswith("{")]


@pytest.mark.slow
def test_only_the_farms_accounts_may_register(tmp_path):
    with EmbeddedXmppServer(tmp_path / "xmpp") as server:
        server.allow(["agent-1"])
        assert [e["event"] for e in _register(server.port, "agent-1")][:1] == ["online"]
        stranger = _register(server.port, "agent-evil")
        assert stranger and stranger[0]["event"] == "error" and "refused" in stranger[0]["reason"]


def test_the_master_takes_bids_only_from_its_allowlist(tmp_path):
    allow = tmp_path / "agents.allow"
    allow.write_text("agent-1-abc@localhost\n")
    service = MasterService(MasterConfig(home=tmp_path / "home", agent_allowlist=allow))
    try:
        assert service._accepts("agent-1-abc@localhost")
        assert not service._accepts("agent-2-fff@localhost")  # matches the pattern, not on the list
        assert not service._accepts("master@localhost")
        allow.write_text("agent-1-abc@localhost\nagent-2-fff@localhost\n")  # a restarted agent joins
        assert service._accepts("agent-2-fff@localhost")
        allow.unlink()
        assert not service._accepts("agent-1-abc@localhost")  # an unreadable list lets nobody in
    finally:
        service.store.close()
        service._planner.stop()


def test_a_full_disk_pauses_every_job_and_stops_the_auctions_clock(tmp_path):
    """Below `min_free_bytes` free, the master pauses: no tick (no award, deadline or loss) and the
    auction's clock stands still, so nothing has run out when space returns."""
    import time

    service = MasterService(MasterConfig(home=tmp_path / "home", min_free_bytes=1 << 62))  # always "full"
    try:
        service.check_disk()
        assert service.paused == "disk full on the master" and service._tick(0.0) == []
        frozen = service.auction_now()
        time.sleep(0.3)
        assert service.auction_now() == pytest.approx(frozen, abs=0.02)
        service.config.min_free_bytes = 0  # space is back
        service.check_disk()
        assert service.paused is None
        time.sleep(0.2)
        assert service.auction_now() - frozen == pytest.approx(0.2, abs=0.1)  # the pause is not counted
    finally:
        service.store.close()
        service._planner.stop()
