"""Trust on one machine: the master takes bids only from the agents it was told of (its allowlist).
(The XMPP server's closed registration: tests/test_local_xmpp.py.)"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from core.scene.bundle import make_bundle
from farm.local import LocalFarm
from master.service import MasterConfig, MasterService

REPO = Path(__file__).resolve().parent.parent
PEER = REPO / "tests" / "xmpp_peer.py"


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

    from master import auction as au

    service = MasterService(MasterConfig(home=tmp_path / "home", min_free_bytes=1 << 62))  # always "full"
    service.auction = au.Auction(config=service.config.auction)  # what `start` restores, without its servers
    try:
        assert [type(i) for i in service.check_disk()] == [au.JobsPaused]
        assert service.paused == "disk full on the master" and service.auction.handle(au.Tick(), 0.0) == []
        assert service.check_disk() == []  # paused once
        frozen = service.auction.clock(time.time())
        time.sleep(0.3)
        assert service.auction.clock(time.time()) == pytest.approx(frozen, abs=0.02)
        service.config.min_free_bytes = 0  # space is back
        assert [type(i) for i in service.check_disk()] == [au.JobsResumed]
        assert service.paused is None
        time.sleep(0.2)
        assert service.auction.clock(time.time()) - frozen == pytest.approx(0.2, abs=0.1)  # the pause is not counted
    finally:
        service.store.close()
        service._planner.stop()


def test_events_the_store_cannot_write_are_kept_and_written_in_order_once_it_can(tmp_path):
    """SQLite's own 'database or disk is full' (its page count capped at what it holds): the auction has
    moved on, so its events are kept and written at a later call; they were lost, and a job the auction
    had ended stayed running in the store until the master restarted."""
    import asyncio

    from master import auction as au

    service = MasterService(MasterConfig(home=tmp_path / "home"))
    try:
        db = service.store.db
        db.execute(f"PRAGMA max_page_count = {db.execute('PRAGMA page_count').fetchone()[0]}")
        first = [au.AgentJoined(f"agent-{i}-abc@localhost", 1.0) for i in range(300)]
        asyncio.run(service._execute(first))
        assert service._unrecorded == first and service.store.credits() == {}
        asyncio.run(service._execute([]))  # a tick: still full
        assert service._unrecorded == first
        db.execute("PRAGMA max_page_count = 1000000")  # space again
        asyncio.run(service._execute([au.AgentJoined("agent-late-abc@localhost", 1.0)]))
        assert service._unrecorded == [] and len(service.store.credits()) == 301
    finally:
        service.store.close()
        service._planner.stop()


def test_a_failure_while_the_disk_is_full_is_not_held_against_its_agent(tmp_path):
    """A local farm's agents write their tiles on the master's disk: one that fails while it is full may
    fail for that, and three such failures blocklisted the farm's only agent and failed the job."""
    import asyncio

    from auction_support import message, register, tick

    from core.model import messages as m
    from core.model.geometry import Rect
    from core.model.job import Effects, JobPlan, JobSpec, RenderOptions, SceneSpec
    from core.model.units import WorkUnit
    from core.transport.xmpp import Envelope
    from master import auction as au

    service = MasterService(MasterConfig(home=tmp_path / "home"))
    service.auction = au.Auction(config=service.config.auction)  # what `start` restores, without its servers
    try:
        options = RenderOptions(level="off", spp=4)
        plan = JobPlan(SceneSpec(Path("scene.xml")), options, 16, 8, Effects("llvm_ad_rgb", "path", 8), 4, 8,
                       [WorkUnit(index=0, rect=Rect(0, 0, 16, 8), C=0.1, S=128, Nd=0.0, cost=1.0)],
                       bundle_sha256="ef" * 32)
        service._create_job("job0000001", "scene.xml", JobSpec({}, options), plan, time.time())
        agent, auction, now = "agent-0-abc@localhost", service.auction, time.time()
        service._record(register(auction, agent, now))
        [cfp] = [c.message for c in tick(auction, now) if isinstance(c, au.SendToAgent)]
        service._record(message(auction, agent, m.Propose(conversation=cfp.conversation, job_id=cfp.job.job_id,
                                                            estimates=(m.Estimate(index=0, seconds=1.0),)), now))
        decided = tick(auction, now + 5)
        service._record(decided)
        [award] = [c.message for c in decided if isinstance(c, au.SendToAgent) and isinstance(c.message, m.Award)]
        service.config.min_free_bytes = 1 << 62  # the disk is full
        service._record(service.check_disk())
        failure = m.Failure(conversation=award.conversation, job_id="job0000001", index=0, token=award.token,
                            reason="cannot write the tile: No space left on device")
        performative, body = m.encode(failure)
        envelope = Envelope(sender=agent, to=service.config.jid, performative=performative, ontology=m.ONTOLOGY,
                            protocol=m.PROTOCOL, conversation_id=award.conversation, body=body,
                            received_at=time.monotonic(), resource="r1")
        asyncio.run(service._on_envelope(envelope))
        assert auction._agents[agent].credits == 0 and auction._jobs["job0000001"].units[0].failures == 0
        [attempt] = service.store.attempts("job0000001", 0)
        assert attempt.outcome == "requeued" and "not counted" in attempt.reason
    finally:
        service.store.close()
        service._planner.stop()


@pytest.mark.slow
def test_a_peer_whose_tiles_lie_is_refused_or_named_and_the_job_completes(tmp_path):
    """An allowed agent holding real awards uploads tiles placed right whose headers lie: another agent named
    as their renderer (accepted: the award's holder is named), a billion samples in negative time, NaN
    seconds, an extra channel. Each of the last three is refused (422) at upload: accepted, the first made
    the job's image impossible to compose (a 500 on every download) and the others entered the report,
    the credits and the auction's rates. The job completes on the honest agent."""
    home = tmp_path / "home"
    with LocalFarm(home, agents=1, threads=1) as farm:
        farm.wait_for_agents()
        env = dict(os.environ, QUEKARO_XMPP_PASSWORD=farm.add_account("agent-liar"), PYTHONPATH=str(REPO))
        liar = subprocess.Popen([sys.executable, str(REPO / "tests" / "liar_agent.py"), "--mode", "tiles",
                                 "--jid", "agent-liar@localhost", "--port", str(farm.server.port), "--master",
                                 "master@localhost", "--lies", "4"],
                                stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env, cwd=REPO)
        try:
            online = json.loads(liar.stdout.readline())
            assert online["event"] == "online", online
            time.sleep(3)  # its registration reaches the master before the job's first auction
            client = farm.client()
            defines = {"res": "64", "spp": "4"}
            with tempfile.TemporaryDirectory() as tmp:
                bundle = make_bundle(REPO / "scenes" / "cbox.xml", defines, Path(tmp) / "b.tar").path.read_bytes()
            job = client.submit(bundle, defines, {"level": "off", "units": 12})
            assert client.wait(job, timeout=300)["status"] == "done"
            out = client.result(job, tmp_path / "out.exr")
        finally:
            liar.kill()
        lies = {e["lie"]: e for e in map(json.loads, liar.stdout.read().splitlines()) if e["event"] == "lied"}
    assert {k: e["status"] for k, e in lies.items()} == {
        "forged-agent": 200, "absurd-spp": 422, "nan-seconds": 422, "extra-channel": 422}, lies
    report = json.loads(out.with_suffix(".json").read_text())
    by_unit = {u["index"]: u for u in report["units"]}
    assert by_unit[lies["forged-agent"]["unit"]]["agent"] == "agent-liar@localhost"  # not whom it named
    assert all(u["agent"] != "agent-0-honest@localhost" for u in report["units"])  # the name the liar gave
    assert all(u["spp"] == 4 and 0 <= u["seconds"] < 300 for u in report["units"]), report["units"]
    assert report["totals"]["samples"] == 4 * 64 * 64


def test_the_master_reads_a_stored_tiles_header_back_and_blames_itself_when_it_cannot(tmp_path):
    """master.service reads back only the header of a tile the data plane decoded in full; a stored tile it
    cannot read is the master's error (a 500 upload answer), not the agent's (a TileError, a 422)."""
    import numpy as np

    from core.errors import QuekaroError, TileError
    from core.image.tiles import Tile, write_tile
    from core.model.geometry import Rect
    from master.service import _stored_header

    meta = {"job_id": "j1", "unit_index": 3, "spp": 16, "depth": 5, "band": 2}
    tile = Tile(np.ones((6, 8, 4), np.float32), Rect(0, 0, 8, 6), Rect(2, 2, 4, 2), meta, ("R", "G", "B", "A"))
    header = _stored_header(write_tile(tmp_path / "good.exr", tile))
    assert (header.rect, header.core, header.channels) == (tile.rect, tile.core, tile.channels)
    assert header.meta == meta
    torn = tmp_path / "torn.exr"
    torn.write_bytes((tmp_path / "good.exr").read_bytes()[:40])  # a disk that lost the file's tail
    with pytest.raises(QuekaroError, match="stored tile") as raised:
        _stored_header(torn)
    assert not isinstance(raised.value, TileError)
