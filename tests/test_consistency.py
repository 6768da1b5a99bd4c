"""One source of truth for a unit's state: done only when its tile is durable, an inform alone changes
nothing, and on start the master's store agrees with the tiles on disk."""

from __future__ import annotations

import random
from pathlib import Path

from auction_support import message, register, tick
from test_store import HASH, new_store, restore

from core.model import messages as m
from core.model.status import UnitStatus
from master import auction as au


def _awarded(auction: au.Auction, store, now: float) -> list[au.SendToAgent]:
    cmds = tick(auction, now)
    store.apply(cmds, now)
    for send in [c for c in cmds if isinstance(c, au.SendToAgent) and isinstance(c.message, m.CallForProposal)]:
        est = tuple(m.Estimate(index=u.index, seconds=u.cost) for u in send.message.units)
        message(auction, send.to, m.Propose(conversation=send.message.conversation, job_id="job-1",
                                              estimates=est), now)
    cmds = tick(auction, now)
    store.apply(cmds, now)
    return [c for c in cmds if isinstance(c, au.SendToAgent) and isinstance(c.message, m.Award)]


def _inform(award: au.SendToAgent) -> m.Inform:
    msg = award.message
    return m.Inform(conversation=msg.conversation, job_id=msg.job.job_id, index=msg.unit.index, token=msg.token,
                    tile_hash=HASH, depth=4, spp=8, band=2, seconds=0.1, nonfinite=0)


def test_an_inform_without_a_tile_changes_nothing(tmp_path: Path):
    with new_store(tmp_path / "farm.db", n=2) as store:
        auction, events = restore(store, 0.0, rng=random.Random(1))
        store.apply(events, 0.0)
        register(auction, "agent-1@localhost", 0.0, speed=1.0)
        award = _awarded(auction, store, 1.0)[0]
        out = message(auction, award.to, _inform(award), 2.0)
        assert [type(c) for c in out if isinstance(c, au.Record)] == [au.MessageIgnored]
        store.apply(out, 2.0)  # the store and the auction still agree: nothing is done
        unit = auction._jobs["job-1"].units[award.message.unit.index]
        assert unit.status == UnitStatus.AWARDED
        assert {u.status for u in store.units("job-1")} <= {"pending", "awarded"}


def test_a_done_unit_whose_tile_is_gone_goes_back_to_auction(tmp_path: Path):
    tile = tmp_path / "0.exr"
    tile.write_bytes(b"tile")
    with new_store(tmp_path / "farm.db", n=2) as store:
        store.record_award("job-1", 0, "A", "aa" * 16, 1.0, 1.0)  # a unit is done only from awarded
        store.record_result("job-1", 0, str(tile), HASH, {"spp": 8}, 1.0)
        assert store.mark_done("job-1", 0, 1.0)
        assert store.repair(["job-1"], 2.0) == []  # tile present: nothing to repair
        tile.unlink()
        assert store.repair(["job-1"], 3.0) == [("job-1", 0)]
        assert store.units("job-1")[0].status == "pending" and store.results("job-1") == []
        auction, _ = restore(store, 4.0, rng=random.Random(1))
        assert auction._jobs["job-1"].units[0].status == UnitStatus.PENDING
