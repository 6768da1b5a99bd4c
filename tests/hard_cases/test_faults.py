"""Faults the farm must survive without losing a unit, as far as they can be driven without a farm:
an agent dying at each step of the contract net (master/auction/ is a pure state machine, driven
here directly), and a disk that fills while a tile is written (core.image.tiles.write_tile on a tiny tmpfs).
The farm-level faults (SIGKILL, master and XMPP restarts) are in tests/test_farm.py."""

from __future__ import annotations

import contextlib
import dataclasses
import os
import random
import subprocess
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from auction_support import informed, message, register, submit, tick, uploadable

from core.errors import TileError
from core.image.tiles import Tile, read_tile, write_tile
from core.model import messages as m
from core.model.geometry import Rect
from core.model.units import WorkUnit
from master import auction as au

HASH = "ab" * 32
STEPS = ["proposed", "awarded", "rendering", "uploaded"]


def _auction() -> au.Auction:
    a = au.Auction(rng=random.Random(3))
    info = m.JobInfo(job_id="job-1", scene_url="http://127.0.0.1:8765/scene", scene_hash=HASH, width=16,
                     height=16, spp=4, depth=4, level="S", ranges={"C": (0.0, 1.0)})
    submit(a, info, [WorkUnit(index=0, rect=Rect(0, 0, 16, 16), C=1.0, S=256, Nd=0.0, cost=1.0)])
    for name in ("doomed", "spare"):
        register(a, name, 0.0)
    a._agents["doomed"].credits = 5  # it wins the contest, so its death is what the test exercises
    return a


def _sends(cmds: list[au.Instruction], kind: type) -> list[au.SendToAgent]:
    return [c for c in cmds if isinstance(c, au.SendToAgent) and isinstance(c.message, kind)]


def _kinds(cmds: list[au.Instruction]) -> list[type[au.Record]]:
    return [type(c) for c in cmds if isinstance(c, au.Record)]


def _bid(a: au.Auction, now: float, who: set[str], calls: list[au.Instruction] | None = None) -> None:
    """The agents in `who` bid on the calls for proposals in `calls` (default: a tick's)."""
    for send in _sends(tick(a, now) if calls is None else calls, m.CallForProposal):
        if send.to in who:
            est = tuple(m.Estimate(index=u.index, seconds=1.0) for u in send.message.units)
            message(a, send.to, m.Propose(conversation=send.message.conversation, job_id="job-1",
                                            estimates=est), now)


def _inform(award: m.Award) -> m.Inform:
    return m.Inform(conversation=award.conversation, job_id="job-1", index=award.unit.index, token=award.token,
                    tile_hash=HASH, depth=4, spp=4, band=2, seconds=1.0, nonfinite=0)


@pytest.mark.parametrize("step", STEPS)
def test_agent_dying_at_each_protocol_step_loses_nothing(step):
    a = _auction()
    _bid(a, 0.0, {"doomed", "spare"})
    award = _sends(tick(a, 0.0), m.Award)[0]
    assert award.to == "doomed"
    busy = (m.HeldUnit(job_id="job-1", index=0),)
    if step in ("rendering", "uploaded"):
        message(a, "doomed", m.Heartbeat(conversation="h", busy=busy), 1.0)
    if step == "uploaded":
        assert uploadable(a, "job-1", 0, award.message.token)  # the tile is on the master, no INFORM
    if step == "proposed":
        award = None  # it died before it could read the award: the award is lost with it
    # "doomed" says no more; "spare" keeps beating until the heartbeat timeout has passed.
    late = a.config.heartbeat_timeout_s + 2.0
    message(a, "spare", m.Heartbeat(conversation="h", busy=()), late)
    out = tick(a, late)
    assert au.AgentLost in _kinds(out) and a._agents["doomed"].lost
    # Back in the auction (offered to the spare agent at once), not failed, not lost.
    assert a.counts("job-1") == Counter(announced=1) and [s.to for s in _sends(out, m.CallForProposal)] == ["spare"]
    first_token = (award.message.token if award else None)
    if first_token:
        assert not uploadable(a, "job-1", 0, first_token)  # the dead agent's upload is void now
    _bid(a, late, {"spare"}, out)
    again = _sends(tick(a, late), m.Award)
    assert [s.to for s in again] == ["spare"] and again[0].message.token != first_token
    done = informed(a, "spare", _inform(again[0].message), late + 1)
    assert _kinds(done)[-1] is au.JobDone and a.counts("job-1") == Counter(done=1)
    if award:  # a result from the dead agent arriving now changes nothing
        ghost = informed(a, "doomed", _inform(award.message), late + 2)
        assert _kinds(ghost) == [au.MessageIgnored] and a.counts("job-1") == Counter(done=1)


def test_same_result_delivered_twice_by_the_same_agent_counts_once():
    a = _auction()
    _bid(a, 0.0, {"doomed", "spare"})
    award = _sends(tick(a, 0.0), m.Award)[0]
    inform = _inform(award.message)
    first = informed(a, "doomed", inform, 1.0)
    second = informed(a, "doomed", dataclasses.replace(inform, seconds=9.0), 1.1)
    assert _kinds(first).count(au.UnitDone) == 1 and au.UnitDone not in _kinds(second)
    assert a._agents["doomed"].credits == 6  # one credit for one result, not two
    assert a.counts("job-1") == Counter(done=1)


# ---- a disk that fills while a tile is written -------------------------------------------------------


@pytest.fixture
def tiny_disk(tmp_path: Path):
    """A 64 KiB tmpfs at tmp_path/disk (needs root and mount(8)); skipped with the reason otherwise."""
    mount = tmp_path / "disk"
    mount.mkdir()
    if os.geteuid() != 0:
        pytest.skip("mounting a small tmpfs needs root")
    cmd = ["mount", "-t", "tmpfs", "-o", "size=64k,nr_inodes=64", "tmpfs", str(mount)]
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=20)
    except (OSError, subprocess.TimeoutExpired) as exc:
        pytest.skip(f"cannot mount a tmpfs: {exc}")
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs: {done.stderr.strip() or done.returncode}")
    try:
        yield mount
    finally:
        with contextlib.suppress(OSError, subprocess.TimeoutExpired):
            subprocess.run(["umount", str(mount)], capture_output=True, timeout=20)


def test_disk_filling_while_writing_a_tile_leaves_nothing_partial(tiny_disk: Path):
    rng = np.random.default_rng(0)
    small = Tile(rng.random((8, 8, 3), dtype=np.float32), Rect(0, 0, 8, 8), Rect(0, 0, 8, 8))
    write_tile(tiny_disk / "small.exr", small)
    # Noise does not compress: 128x128x3 float32 is 192 KiB, three times the disk.
    big = Tile(rng.random((128, 128, 3), dtype=np.float32), Rect(0, 0, 128, 128), Rect(0, 0, 128, 128))
    target = tiny_disk / "big.exr"
    with pytest.raises(TileError) as info:
        write_tile(target, big)
    assert str(target) in str(info.value) and "cannot write tile" in str(info.value)
    assert sorted(p.name for p in tiny_disk.iterdir()) == ["small.exr"]  # no temp file, no half tile
    np.testing.assert_array_equal(read_tile(tiny_disk / "small.exr").pixels, small.pixels)  # intact
    write_tile(tiny_disk / "again.exr", small)  # the space came back: the disk is usable again
