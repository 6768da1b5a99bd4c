"""The job store on real SQLite files: jobs and units, the auction's typed events, status changes checked
against the transition table, crash and resume (the auction rebuilding itself from the store), readers."""

from __future__ import annotations

import dataclasses
import json
import multiprocessing
import random
import sqlite3
import time
from pathlib import Path

import pytest
from auction_support import cancel, informed, message, register, submit, tick

from core.errors import QuekaroError
from core.model import messages as m
from core.model.geometry import Rect
from core.model.job import Effects, ImageFile, JobPlan, JobSpec, RenderOptions, SceneSpec
from core.model.status import JobStatus, TransitionError, UnitStatus
from core.model.units import WorkUnit
from master import auction as au
from master.store import _SCHEMA, SCHEMA_VERSION, JobStore, RunningJob, StoreError, token_sha256

HASH = "ef" * 32


ONE_A_ROUND = au.Config(slots=2)  # one unit a round and a call: what the auction tests here trace

def specs(n: int) -> list[WorkUnit]:
    return [
        WorkUnit(index=i, rect=Rect(8 * i, 0, 8, 8), C=0.5, S=64, Nd=0.1, cost=1.0 + i) for i in range(n)
    ]


def plan_of(units: list[WorkUnit], spp: int = 16) -> JobPlan:
    effects = Effects("llvm_ad_rgb", "path", 8, ["a reason"])
    return JobPlan(SceneSpec(Path("scene.xml")), RenderOptions(level="S", spp=spp), 64, 8, effects, spp, 8, units,
                   bundle_sha256=HASH)


def info_of(record) -> m.JobInfo:
    return m.JobInfo(
        job_id=record.id, scene_url="http://127.0.0.1:8765/scene", scene_hash=HASH, width=64, height=8,
        spp=record.plan["spp"], depth=8, level="S", ranges={},
    )  # fmt: skip


def restore(store: JobStore, now: float, rng: random.Random | None = None) -> tuple[au.Auction, list[au.Instruction]]:
    """What the master does on start: awarded units back to pending, then the auction rebuilds itself."""
    store.resume(now)
    return au.Auction.restore(store.running_jobs(), lambda job_id: info_of(store.job(job_id)), store.credits(),
                              rng=rng)


def new_store(path: Path, n: int = 4, job_id: str = "job-1") -> JobStore:
    store = JobStore(path)
    store.create_job(job_id, "scene.xml", JobSpec({"k": "v"}, RenderOptions(level="S", spp=16)), plan_of(specs(n)),
                     now=100.0)
    return store


def play(auction: au.Auction, store: JobStore, now: float, finish: int | None = None) -> list[au.SendToAgent]:
    """One auction round where every agent bids; `finish` awards are completed the way the master does it:
    tile recorded (durably written by the data plane), then the inform applied."""
    cmds = tick(auction, now)
    store.apply(cmds, now)
    for send in [c for c in cmds if isinstance(c, au.SendToAgent) and isinstance(c.message, m.CallForProposal)]:
        est = tuple(m.Estimate(index=u.index, seconds=u.cost) for u in send.message.units)
        message(auction,
            send.to, m.Propose(conversation=send.message.conversation, job_id="job-1", estimates=est), now
        )
    cmds = tick(auction, now)
    store.apply(cmds, now)
    awarded = [c for c in cmds if isinstance(c, au.SendToAgent) and isinstance(c.message, m.Award)]
    for award in awarded[:finish]:
        msg = award.message
        store.record_result(
            msg.job.job_id, msg.unit.index, f"/tiles/{msg.unit.index}.exr", HASH, {"spp": 8}, now
        )
        inform = m.Inform(
            conversation=msg.conversation, job_id=msg.job.job_id, index=msg.unit.index, token=msg.token,
            tile_hash=HASH, depth=4, spp=8, band=2, seconds=msg.estimate_s, nonfinite=0,
        )  # fmt: skip
        store.apply(informed(auction, award.to, inform, now + 1), now + 1)
    return awarded


def test_schema_pragmas_and_records(tmp_path: Path) -> None:
    with new_store(tmp_path / "farm.db") as store:
        assert store.db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        assert store.db.execute("PRAGMA foreign_keys").fetchone()[0] == 1
        assert store.db.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION
        job = store.job("job-1")
        assert (job.scene, job.spec, job.status) == ("scene.xml", JobSpec({"k": "v"}, RenderOptions("S", 16)),
                                                     "running")
        plan = store.plan("job-1", Path("/jobs/job-1/scene.xml"))
        assert plan == dataclasses.replace(plan_of(specs(4)), spec=SceneSpec(Path("/jobs/job-1/scene.xml"),
                                                                               {"k": "v"}))
        units = store.units("job-1")
        assert [u.unit() for u in units] == specs(4) and {u.status for u in units} == {"pending"}
        with pytest.raises(StoreError, match="already exists"):
            store.create_job("job-1", "s", JobSpec(), plan_of(specs(1)), now=0)
        with pytest.raises(StoreError, match="no job 'nope'"):
            store.job("nope")
        with pytest.raises(sqlite3.IntegrityError):  # foreign keys hold
            store.db.execute("INSERT INTO units VALUES"
                             " ('nope', 0, 0, 0, 1, 1, 0, 0, 0, 1, 'pending', 0, NULL, NULL, NULL)")
    assert [j.id for j in JobStore(tmp_path / "farm.db").list_jobs()] == ["job-1"]


def test_a_plan_keeps_its_filter_and_an_old_one_gets_mitsubas_default() -> None:
    """The filter radius decides which band pixels composition cuts (JobPlan.reach): it survives the store,
    and a plan stored before it was recorded composes as those jobs were planned, with the gaussian's 2."""
    lanczos = dataclasses.replace(plan_of(specs(2)), filter_radius=3.0)
    again = JobPlan.from_dict(lanczos.to_dict(), lanczos.spec, specs(2))
    assert again.filter_radius == 3.0 and again.reach == 3
    old = {k: v for k, v in lanczos.to_dict().items() if k != "filter_radius"}
    assert JobPlan.from_dict(old, lanczos.spec, specs(2)).reach == 2


def test_an_adaptive_plan_keeps_its_first_pass_and_shares() -> None:
    """After a restart the master rebuilds the agents' JobInfo from the stored plan: an adaptive job's first
    pass must survive it (its units' shares live in the units' rows); a plan stored before has none."""
    shared = dataclasses.replace(plan_of(specs(2)), first_spp=8, shares={"mean_spp": 16, "unit_spp": [12, 20]})
    again = JobPlan.from_dict(json.loads(json.dumps(shared.to_dict())), shared.spec, specs(2))
    assert (again.first_spp, again.shares) == (8, {"mean_spp": 16, "unit_spp": [12, 20]})
    old = {k: v for k, v in shared.to_dict().items() if k not in ("first_spp", "shares")}
    assert JobPlan.from_dict(old, shared.spec, specs(2)).first_spp is None


def test_a_plan_keeps_its_films_file_and_an_old_one_gets_what_it_was_written_as() -> None:
    """The film's file and component format decide the job's image file at assembly, after a restart too;
    a plan stored before they were recorded wrote float32 OpenEXR, and is assembled so again."""
    pfm = dataclasses.replace(plan_of(specs(2)), image_file=ImageFile("pfm"))
    again = JobPlan.from_dict(json.loads(json.dumps(pfm.to_dict())), pfm.spec, specs(2))
    assert again.image_file == ImageFile("pfm", "float32") and again.image_file.suffix == ".pfm"
    assert plan_of(specs(2)).image_file == ImageFile("openexr", "float16")  # Mitsuba's default
    old = {k: v for k, v in pfm.to_dict().items() if k != "image_file"}
    assert JobPlan.from_dict(old, pfm.spec, specs(2)).image_file == ImageFile("openexr", "float32")
    with pytest.raises(QuekaroError, match="image file format 'png'"):
        JobPlan.from_dict({**pfm.to_dict(), "image_file": {"format": "png"}}, pfm.spec, specs(2))


def test_bad_files_are_refused(tmp_path: Path) -> None:
    junk = tmp_path / "junk.db"
    junk.write_bytes(b"this is not sqlite" * 100)
    with pytest.raises(StoreError, match=r"junk\.db"):
        JobStore(junk)
    newer = tmp_path / "newer.db"
    sqlite3.connect(newer).execute("PRAGMA user_version = 99").connection.close()
    with pytest.raises(StoreError, match="schema version 99"):
        JobStore(newer)


def test_done_needs_a_durable_result_and_happens_once(tmp_path: Path) -> None:
    store = new_store(tmp_path / "farm.db")
    store.record_award("job-1", 0, "A", "aa" * 16, 1.0, 1.0)
    with pytest.raises(StoreError, match="no durable result"):
        store.mark_done("job-1", 0, now=1)
    assert store.record_result("job-1", 0, "/t/0.exr", HASH, {"spp": 8}, now=1)
    assert store.has_result("job-1", 0, HASH) and not store.has_result("job-1", 0, "00" * 32)
    assert store.mark_done("job-1", 0, now=2)
    assert not store.mark_done("job-1", 0, now=3)
    assert not store.record_result("job-1", 0, "/t/other.exr", "11" * 32, {}, now=4)  # late duplicate
    assert store.results("job-1")[0].tile_path == "/t/0.exr"


def test_an_agent_rendering_two_frames_is_one_agent_busy(tmp_path: Path) -> None:
    """A sequence's frames are jobs of their own: an agent holding a unit of two of them is busy once."""
    store = new_store(tmp_path / "farm.db")
    store.create_job("job-2", "scene.xml", JobSpec({}, RenderOptions(level="S", spp=16)), plan_of(specs(2)), now=100.0)
    store.record_award("job-1", 0, "A", "aa" * 16, 1.0, 1.0)
    store.record_award("job-2", 0, "A", "bb" * 16, 1.0, 1.0)
    store.record_award("job-2", 1, "B", "cc" * 16, 1.0, 1.0)
    assert [store.agents_busy(jobs) for jobs in (["job-1"], ["job-2"], ["job-1", "job-2"])] == [1, 2, 2]


def test_auction_events_are_recorded(tmp_path: Path) -> None:
    store = new_store(tmp_path / "farm.db", n=3)
    auction = au.Auction(ONE_A_ROUND, rng=random.Random(5))
    submit(auction, info_of(store.job("job-1")), [u.unit() for u in store.units("job-1")])
    for name in ("A", "B"):
        store.apply(register(auction, name, 100.0), 100.0)
    awarded = play(auction, store, 101.0, finish=1)
    assert len(awarded) == 2
    progress = store.progress("job-1")
    assert (progress.done, progress.total, progress.agents_busy) == (1, 3, 1)
    # Finished unit took exactly its cost: the ETA is the remaining cost at that rate over one busy agent.
    remaining = sum(u.cost for u in store.units("job-1") if u.status != "done")
    assert progress.eta_s == pytest.approx(remaining)
    # Given the clock, what the running unit has rendered is taken off, at most its own expected time.
    [running] = [u for u in store.units("job-1") if u.status == "awarded"]
    started, cost = store.attempts("job-1", running.index)[-1].started, running.cost
    assert store.progress("job-1", started + 0.25 * cost).eta_s == pytest.approx(remaining - 0.25 * cost)
    assert store.progress("job-1", started + 10 * cost).eta_s == pytest.approx(remaining - cost)
    # A failure on the other award is recorded and its unit is pending again.
    other = awarded[1].message
    fail = m.Failure(
        conversation=other.conversation, job_id="job-1", index=other.unit.index, token=other.token,
        reason="child crashed",
    )  # fmt: skip
    store.apply(message(auction, awarded[1].to, fail, 103.0), 103.0)
    rows = store.db.execute("SELECT agent, outcome, reason, params FROM attempts ORDER BY id").fetchall()
    assert [tuple(r)[:3] for r in rows] == [
        (awarded[0].to, "done", ""), (awarded[1].to, "failed", f"failed on {awarded[1].to}: child crashed")
    ]  # fmt: skip
    assert store.failures("job-1") == [
        (other.unit.index, awarded[1].to, f"failed on {awarded[1].to}: child crashed")
    ]
    assert store.credits() == {awarded[0].to: 1, awarded[1].to: -1}
    while store.job("job-1").status == "running":
        for name in ("A", "B"):
            message(auction, name, m.Heartbeat(conversation="h", busy=()), 104.0)
        play(auction, store, 104.0)
    assert store.job("job-1").status == "done"
    assert {u.status for u in store.units("job-1")} == {"done"}
    assert store.progress("job-1").eta_s == 0.0


def test_the_auctions_own_records_commit_without_waiting_for_the_disk_a_users_command_with(tmp_path: Path) -> None:
    """SQLite's synchronous level of each commit: FULL (on disk when it returns) for a job's creation and a
    user's command (a cancel), NORMAL for the auction's own records (a power cut may lose the last ones:
    their units render again)."""
    level = {1: "NORMAL", 2: "FULL"}
    store = new_store(tmp_path / "farm.db", n=2)
    assert level[store.db.execute("PRAGMA synchronous").fetchone()[0]] == "FULL"
    auction = au.Auction(ONE_A_ROUND, rng=random.Random(5))
    submit(auction, info_of(store.job("job-1")), [u.unit() for u in store.units("job-1")])
    store.apply(register(auction, "A", 100.0), 100.0)
    play(auction, store, 101.0)
    assert level[store.db.execute("PRAGMA synchronous").fetchone()[0]] == "NORMAL"
    store.apply(cancel(auction, "job-1"), 102.0)
    assert level[store.db.execute("PRAGMA synchronous").fetchone()[0]] == "FULL"
    assert store.job("job-1").status == JobStatus.CANCELLED
    assert level[JobStore(tmp_path / "farm.db").db.execute("PRAGMA synchronous").fetchone()[0]] == "FULL"


def _first_unit_done(tmp_path: Path) -> tuple[JobStore, dict[int, float]]:
    """A 3-unit job whose unit 0 agent A rendered at one second per unit of cost; the units' costs."""
    store = new_store(tmp_path / "farm.db", n=3)
    cost = {u.index: u.cost for u in store.units("job-1")}
    store.record_award("job-1", 0, "A", "aa" * 16, 100.0, 1.0)
    store.record_result("job-1", 0, "/t/0.exr", "00" * 32, {"spp": 16}, 101.0)
    store.finish_attempt("aa" * 16, "done", 101.0, cost[0], {"spp": 16})  # one second per unit of cost
    store.mark_done("job-1", 0, 101.0)
    return store, cost


def test_the_eta_counts_down_the_unit_an_agent_renders_not_the_one_it_has_queued(tmp_path: Path) -> None:
    store, cost = _first_unit_done(tmp_path)
    store.record_award("job-1", 1, "A", "bb" * 16, 101.0, 1.0)  # rendering
    store.record_award("job-1", 2, "A", "cc" * 16, 101.0 + cost[1] / 4, 1.0)  # queued behind it
    left = cost[1] + cost[2]
    assert store.progress("job-1").eta_s == pytest.approx(left)
    assert store.progress("job-1", 101.0 + cost[1] / 2).eta_s == pytest.approx(left - cost[1] / 2)


def test_the_eta_counts_down_every_unit_of_the_call_an_agent_renders(tmp_path: Path) -> None:
    """Units (a progressive job's passes) awarded to an agent in one round render in one call: the ETA counts
    down their work together, not the first unit's alone (it stood still once that one's time was up)."""
    store, cost = _first_unit_done(tmp_path)
    store.record_award("job-1", 1, "A", "bb" * 16, 101.0, 1.0)  # one call renders both
    store.record_award("job-1", 2, "A", "cc" * 16, 101.0, 1.0)
    left = cost[1] + cost[2]
    later = 0.9 * left  # past unit 1's own time
    assert later > cost[1] and store.progress("job-1", 101.0 + later).eta_s == pytest.approx(left - later)
    assert store.progress("job-1", 101.0 + 2 * left).eta_s == pytest.approx(0.0)


def test_cancel_ends_units_and_attempts(tmp_path: Path) -> None:
    store = new_store(tmp_path / "farm.db", n=2)
    store.record_award("job-1", 0, "A", "aa" * 16, 101.0, 2.0)
    assert store.cancel("job-1", now=102.0)
    assert not store.cancel("job-1", now=103.0)
    assert {u.status for u in store.units("job-1")} == {"failed"}
    assert store.db.execute("SELECT outcome FROM attempts").fetchone()[0] == "cancelled"
    assert store.job("job-1").error == "cancelled by the user"


def test_uncommitted_work_is_lost_cleanly_when_the_connection_dies(tmp_path: Path) -> None:
    store = new_store(tmp_path / "farm.db", n=2)
    store.db.execute("BEGIN IMMEDIATE")
    store.db.execute("UPDATE units SET status = 'done' WHERE idx = 0")
    store.db.close()  # no commit
    again = JobStore(tmp_path / "farm.db")
    assert {u.status for u in again.units("job-1")} == {"pending"}


def _crashing_master(path: str) -> None:
    """A master that finishes two units, holds two more as awarded, and dies mid-transaction."""
    import os

    store = new_store(Path(path), n=5)
    auction = au.Auction(ONE_A_ROUND, rng=random.Random(9))
    submit(auction, info_of(store.job("job-1")), [u.unit() for u in store.units("job-1")])
    for name in ("A", "B", "C", "D"):
        store.apply(register(auction, name, 100.0), 100.0)
    play(auction, store, 101.0, finish=2)
    store.db.execute("BEGIN IMMEDIATE")
    store.db.execute("UPDATE units SET status = 'done'")  # never committed
    os._exit(3)


def test_master_killed_mid_job_resumes_with_done_units_kept(tmp_path: Path) -> None:
    path = tmp_path / "farm.db"
    proc = multiprocessing.get_context("spawn").Process(target=_crashing_master, args=(str(path),))
    proc.start()
    proc.join(60)
    assert proc.exitcode == 3
    store = JobStore(path)
    before = {u.index: u.status for u in store.units("job-1")}
    assert sorted(before.values()) == ["awarded", "awarded", "done", "done", "pending"]
    auction, out = restore(store, 200.0, rng=random.Random(1))
    assert out == []
    after = {u.index: u.status for u in store.units("job-1")}
    assert after == {i: "done" if s == "done" else "pending" for i, s in before.items()}
    interrupted = store.db.execute("SELECT COUNT(*) FROM attempts WHERE outcome = 'interrupted'").fetchone()[
        0
    ]
    assert interrupted == 2
    state = {i: u.status.value for i, u in auction._jobs["job-1"].units.items()}
    assert state == after
    register(auction, "A", 200.0)
    assert auction._agents["A"].credits == store.credits()["A"]
    # The rebuilt auction finishes the job without rendering a done unit again.
    for name in ("B", "C"):
        register(auction, name, 200.0)
    awarded = []
    while store.job("job-1").status == "running":
        awarded += [s.message.unit.index for s in play(auction, store, 201.0)]
    assert sorted(awarded) == sorted(i for i, s in before.items() if s != "done")
    done_attempts = store.db.execute("SELECT idx, COUNT(*) FROM attempts WHERE outcome = 'done' GROUP BY idx")
    assert all(n == 1 for _, n in done_attempts)


def test_a_restarted_master_still_knows_who_delivered_a_unit(tmp_path: Path) -> None:
    """A heartbeat that crossed a delivery reaches a master that restarted since: the deliverer is not told
    to drop the unit its own tile made done; another agent listing it is."""
    store = new_store(tmp_path / "farm.db", n=2)
    auction, _ = restore(store, 100.0)
    for name in ("A", "B"):
        register(auction, name, 100.0)
    awarded = play(auction, store, 101.0, finish=1)
    deliverer, index = awarded[0].to, awarded[0].message.unit.index
    other = "B" if deliverer == "A" else "A"
    assert store.running_jobs()[0].delivered_by == {index: deliverer}
    auction, _ = restore(store, 200.0)
    held = (m.HeldUnit(job_id="job-1", index=index),)

    def cancels(agent: str) -> list[int]:
        out = message(auction, agent, m.Heartbeat(conversation="h", busy=held), 201.0)
        return [c.message.index for c in out if isinstance(c, au.SendToAgent) and isinstance(c.message, m.Cancel)]

    assert cancels(deliverer) == [] and cancels(other) == [index]


def test_restored_job_that_was_complete_ends_at_once(tmp_path: Path) -> None:
    store = new_store(tmp_path / "farm.db", n=1)
    store.record_award("job-1", 0, "A", "aa" * 16, 100.0, 1.0)
    store.record_result("job-1", 0, "/t/0.exr", HASH, {}, now=101)
    store.mark_done("job-1", 0, now=101)
    assert store.running_jobs() == [RunningJob("job-1", specs(1), [0], [])]
    _, out = restore(store, 200.0)
    assert out == [au.JobDone("job-1")]
    store.apply(out, 200.0)
    assert store.job("job-1").status == JobStatus.DONE


def _writer(path: str, units: int) -> None:
    store = JobStore(path)
    for i in range(units):
        token = f"{i:032x}"
        store.record_award("job-1", i, "A", token, 100.0 + i, 1.0)
        store.record_result("job-1", i, f"/t/{i}.exr", HASH, {}, 100.0 + i)
        store.finish_attempt(token, "done", 100.5 + i, seconds=1.0, params={"spp": 8})
        store.mark_done("job-1", i, 100.5 + i)


def test_readers_see_progress_while_the_master_writes(tmp_path: Path) -> None:
    path = tmp_path / "farm.db"
    new_store(path, n=120).close()
    proc = multiprocessing.get_context("spawn").Process(target=_writer, args=(str(path), 120))
    proc.start()
    reader = JobStore(path, readonly=True)
    seen = []
    deadline = time.monotonic() + 60
    while proc.is_alive() and time.monotonic() < deadline:
        seen.append(reader.progress("job-1").done)
    proc.join(60)
    assert proc.exitcode == 0
    seen.append(reader.progress("job-1").done)
    assert seen == sorted(seen) and seen[-1] == 120
    assert len(set(seen)) > 2  # the reader really overlapped the writer
    with pytest.raises(sqlite3.OperationalError):
        reader.db.execute("UPDATE jobs SET status = 'failed'")


# Schema 6's tables: schema 7 added the jobs' requeued and the agents' draining columns; schema 5's: schema 6
# added the units' depth column; schema 4's: schema 5 keeps the award token's sha256 in place of the token;
# schema 3's: schema 4 added the units' depth_floor column; schema 2's: schema 3 added their spp.
REQUEUED_COLUMN = ("    error    TEXT NOT NULL DEFAULT '',\n    requeued REAL"
                   "                           -- its latest requeue: failures before it are not held against it\n")
DRAINING_COLUMN = ("    last_seen REAL,\n    draining  INTEGER NOT NULL DEFAULT 0 CHECK (draining IN (0, 1))"
                   "  -- drained by the user, across restarts\n")
SCHEMA_6 = [s.replace(REQUEUED_COLUMN, "    error    TEXT NOT NULL DEFAULT ''\n")
            .replace(DRAINING_COLUMN, "    last_seen REAL\n") for s in _SCHEMA.split(";")]
DEPTH_COLUMN = ("    depth    INTEGER CHECK (depth IS NULL OR depth >= -1),"
                "  -- WorkUnit.depth (a pass's, pinned), NULL: none\n")
HASH_COLUMN = ("    token_sha256 TEXT NOT NULL UNIQUE,"
               "      -- the award token's sha256: the token itself is never stored\n")
SCHEMA_5 = [s.replace(DEPTH_COLUMN, "") for s in SCHEMA_6]
SCHEMA_4 = [s.replace(HASH_COLUMN, "    token    TEXT NOT NULL UNIQUE,\n") for s in SCHEMA_5]
FLOOR_COLUMN = ("    depth_floor INTEGER CHECK (depth_floor IS NULL OR depth_floor >= 1),"
                "  -- WorkUnit.depth_floor, NULL: none\n")
SPP_COLUMN = ("    spp      INTEGER CHECK (spp IS NULL OR spp >= 1),"
              "  -- WorkUnit.spp (adaptive jobs), NULL where rules choose\n")
SCHEMA_3 = [s.replace(FLOOR_COLUMN, "") for s in SCHEMA_4]
SCHEMA_2 = [s.replace(SPP_COLUMN, "") for s in SCHEMA_3]
SCHEMA_1_JOBS = """CREATE TABLE jobs (id TEXT PRIMARY KEY, scene TEXT NOT NULL, defines TEXT NOT NULL,
    options TEXT NOT NULL, status TEXT NOT NULL, created REAL NOT NULL, finished REAL,
    error TEXT NOT NULL DEFAULT '')"""


def write_old_store(path: Path, version: int, schema: list[str], job_columns: tuple[str, str]) -> None:
    """A job store as an older version wrote it: its tables, job-1 (its two JSON columns) and 4 units."""
    assert version >= 5 or all("token_sha256" not in statement for statement in schema)
    db = sqlite3.connect(path, isolation_level=None)
    for statement in schema:
        db.execute(statement)
    db.execute("INSERT INTO jobs VALUES ('job-1', 'scene.xml', ?, ?, 'running', 100.0, NULL, '')", job_columns)
    db.executemany("INSERT INTO units (job_id, idx, x, y, w, h, C, S, Nd, cost, status)"
                   " VALUES ('job-1', ?, ?, ?, ?, ?, ?, ?, ?, ?, 'pending')",
                   [(u.index, *u.rect.as_list(), u.C, u.S, u.Nd, u.cost) for u in specs(4)])
    db.execute(f"PRAGMA user_version = {version}")
    db.close()


def test_a_schema_1_store_is_migrated_with_its_jobs(tmp_path: Path) -> None:
    """A farm home written by schema 1 (options and plan in one column) opens, every job and unit kept."""
    path = tmp_path / "farm.db"
    with new_store(path) as store:
        plan = store.job("job-1").plan
    old = {"options": plan["options"], "plan": {k: v for k, v in plan.items() if k != "options"}}
    path.unlink()
    write_old_store(path, 1, [SCHEMA_1_JOBS, *SCHEMA_2[1:]], (json.dumps({"k": "v"}), json.dumps(old)))
    with JobStore(path) as store:
        assert store.db.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION
        record = store.job("job-1")
        assert record.spec == JobSpec({"k": "v"}, RenderOptions("S", 16)) and record.plan == plan
        assert [u.unit() for u in store.units("job-1")] == specs(4)
        assert store.db.execute("PRAGMA foreign_keys").fetchone()[0] == 1


@pytest.mark.parametrize(("version", "schema", "column"),
                         [(2, SCHEMA_2, "spp"), (3, SCHEMA_3, "depth_floor"), (5, SCHEMA_5, "depth")])
def test_an_older_store_gains_the_units_newer_columns(tmp_path: Path, version, schema, column) -> None:
    """A schema 2, 3 or 5 home opens as the latest: its units keep everything and have no planned spp (schema
    3 added it, adaptive jobs), depth floor (schema 4, planning.depthcut) or pinned depth (schema 6, a
    progressive job's passes); a new job's units then keep theirs through the store (what the auction is
    rebuilt from after a restart), and a value below the column's least is refused."""
    path = tmp_path / "farm.db"
    with new_store(path) as store:
        plan, spec = store.job("job-1").plan, store.job("job-1").spec
    path.unlink()
    write_old_store(path, version, schema, (json.dumps(spec.to_dict()), json.dumps(plan)))
    with JobStore(path) as store:
        assert store.db.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION
        assert [u.unit() for u in store.units("job-1")] == specs(4)
        given = [dataclasses.replace(u, **{column: 10 + u.index}) for u in specs(3)]
        store.create_job("job-2", "scene.xml", spec, plan_of(given), 101.0)
        assert [getattr(u, column) for u in store.running_jobs()[1].units] == [10, 11, 12]
        with pytest.raises(sqlite3.IntegrityError):
            store.db.execute(f"UPDATE units SET {column} = -2 WHERE job_id = 'job-2'")


def test_status_changes_are_checked_against_the_transition_table(tmp_path: Path) -> None:
    store = new_store(tmp_path / "farm.db", n=2)
    store.record_award("job-1", 0, "A", "aa" * 16, 101.0, 1.0)
    with pytest.raises(TransitionError, match=r"job 'job-1' unit 0: awarded -> awarded is not an allowed"):
        store.record_award("job-1", 0, "B", "bb" * 16, 101.0, 1.0)  # awarded twice without a requeue
    with pytest.raises(TransitionError, match=r"job 'job-1': running -> running"):
        store.set_status("job-1", JobStatus.RUNNING, 102.0)
    tile = tmp_path / "0.exr"
    tile.write_bytes(b"tile")
    store.record_result("job-1", 0, str(tile), HASH, {}, 102.0)
    store.mark_done("job-1", 0, 102.0)
    store.cancel("job-1", 103.0)
    tile.unlink()
    # A cancelled job does not run again, whatever its tiles: the repair fails whole, nothing half done.
    with pytest.raises(TransitionError, match=r"job 'job-1': cancelled -> running"):
        store.repair(["job-1"], 104.0)
    assert [u.status for u in store.units("job-1")] == [UnitStatus.DONE, UnitStatus.FAILED]
    assert len(store.results("job-1")) == 1
    # The schema's CHECK constraints hold the stored statuses only: ANNOUNCED is the auction's alone.
    with pytest.raises(sqlite3.IntegrityError):
        store.db.execute("UPDATE units SET status = ? WHERE idx = 1", (UnitStatus.ANNOUNCED,))


def test_requeued_and_cancelled_units_are_recorded(tmp_path: Path) -> None:
    store = new_store(tmp_path / "farm.db", n=2)
    auction = au.Auction(ONE_A_ROUND, rng=random.Random(5))
    submit(auction, info_of(store.job("job-1")), [u.unit() for u in store.units("job-1")])
    for name in ("A", "B"):
        store.apply(register(auction, name, 100.0), 100.0)
    awarded = play(auction, store, 101.0, finish=0)
    lost = awarded[0].to
    survivor = next(a.to for a in awarded if a.to != lost)
    late = 101.0 + auction.config.heartbeat_timeout_s + 1
    message(auction, survivor, m.Heartbeat(conversation="h", busy=()), late - 1)
    out = tick(auction, late)
    assert [type(e) for e in out if isinstance(e, au.Record)] == [au.AgentLost, au.UnitRequeued]
    store.apply(out, late)
    index = awarded[0].message.unit.index
    assert store.units("job-1")[index].status == UnitStatus.PENDING

    def outcomes() -> list[str]:
        return [dict(store.db.execute("SELECT token_sha256, outcome FROM attempts").fetchall())[
            token_sha256(a.message.token)] for a in awarded]

    assert outcomes() == ["requeued", "running"]
    progress = store.progress("job-1", late)  # what `quekaro status` tells of it
    assert progress.retried == 1 and progress.last_retry.startswith(f"unit {index} requeued: ")
    assert progress.last_retry.count(lost) == 1, progress.last_retry  # the reason names the agent, once
    store.apply(cancel(auction, "job-1"), late + 1)
    assert store.job("job-1").status == JobStatus.CANCELLED
    assert {u.status for u in store.units("job-1")} == {UnitStatus.FAILED}
    assert outcomes() == ["requeued", "cancelled"]


def test_a_job_the_restarted_master_cannot_describe_fails_alone(tmp_path: Path) -> None:
    store = new_store(tmp_path / "farm.db", n=2, job_id="job-1")
    store.create_job("job-2", "scene.xml", JobSpec(), plan_of(specs(2)), now=100.0)

    def describe(job_id: str) -> m.JobInfo:
        if job_id == "job-1":
            raise FileNotFoundError("bundle gone")
        return info_of(store.job(job_id))

    store.resume(200.0)
    auction, out = au.Auction.restore(store.running_jobs(), describe, store.credits())
    assert out == [au.JobFailed("job-1", "cannot resume the job: FileNotFoundError: bundle gone")]
    assert list(auction._jobs) == ["job-2"]
    store.apply(out, 200.0)
    assert store.job("job-1").status == JobStatus.FAILED and store.job("job-2").status == JobStatus.RUNNING
    assert {u.status for u in store.units("job-1")} == {UnitStatus.FAILED}


def test_an_event_the_store_cannot_record_is_refused(tmp_path: Path) -> None:
    @dataclasses.dataclass(frozen=True)
    class Unheard(au.Record):
        job_id: str

    store = new_store(tmp_path / "farm.db", n=1)
    with pytest.raises(TypeError, match="Unheard"):
        store.apply([au.JobDone("job-1"), Unheard("job-1")], 101.0)
    assert store.job("job-1").status == JobStatus.RUNNING  # one transaction: nothing of it recorded


def test_a_schema_4_store_keeps_the_hash_of_each_award_token_and_finds_its_attempt_by_it(tmp_path: Path) -> None:
    """Schema 5 stores no award token in clear: a schema 4 home's tokens become their sha256, and the
    running attempt they held is still ended by presenting the token."""
    path = tmp_path / "farm.db"
    with new_store(path) as store:
        plan, spec = store.job("job-1").plan, store.job("job-1").spec
    path.unlink()
    write_old_store(path, 4, SCHEMA_4, (json.dumps(spec.to_dict()), json.dumps(plan)))
    db = sqlite3.connect(path, isolation_level=None)
    db.execute("UPDATE units SET status = 'awarded', attempts = 1 WHERE idx = 0")
    db.execute("INSERT INTO attempts (job_id, idx, agent, token, started, outcome) VALUES ('job-1', 0, 'A', ?, 100.0,"
               " 'running')", ("ab" * 16,))
    db.close()
    with JobStore(path) as store:
        assert store.db.execute("SELECT token_sha256 FROM attempts").fetchall()[0][0] == token_sha256("ab" * 16)
        store.record_award("job-1", 1, "B", "cd" * 16, 101.0, 1.0)
        stored = {r[0] for r in store.db.execute("SELECT token_sha256 FROM attempts")}
        assert stored == {token_sha256("ab" * 16), token_sha256("cd" * 16)} and "cd" * 16 not in stored
        store.finish_attempt("ab" * 16, "requeued", 102.0, reason="lost")
        assert store.units("job-1")[0].status == UnitStatus.PENDING


def test_a_sequences_jobs_are_found_in_frame_order_and_an_ended_job_is_deleted_whole(tmp_path: Path) -> None:
    store = new_store(tmp_path / "jobs.sqlite")
    options = RenderOptions(level="S", spp=16)
    for frame, job_id in ((3, "f3"), (1, "f1"), (2, "f2")):
        spec = JobSpec({"frame": str(frame)}, options, "walk", None, "seq-0123456789ab", frame)
        store.create_job(job_id, "scene.xml", spec, plan_of(specs(2)), now=200.0 - frame)
    assert [r.id for r in store.sequence("seq-0123456789ab")] == ["f1", "f2", "f3"]
    assert store.sequence("seq-ffffffffffff") == [] and store.job("f1").spec.name == "walk"
    with pytest.raises(StoreError, match="is running: cancel it before deleting it"):
        store.delete_job("f1")
    store.record_award("f1", 0, "A", "tok-f1", 201.0, 1.0)
    store.record_result("f1", 0, "/tiles/0.exr", HASH, {"spp": 16}, 202.0)
    store.cancel("f1", 203.0)
    store.delete_job("f1")
    with pytest.raises(StoreError, match="no job 'f1'"):
        store.job("f1")
    for table in ("units", "attempts", "results"):
        assert store.db.execute(f"SELECT COUNT(*) FROM {table} WHERE job_id = 'f1'").fetchone()[0] == 0
    assert [r.id for r in store.sequence("seq-0123456789ab")] == ["f2", "f3"]
    assert len(store.units("job-1")) == 4  # the other jobs keep theirs


def test_a_retried_unit_loses_its_result_and_its_done_job_runs_again(tmp_path: Path) -> None:
    store = new_store(tmp_path / "jobs.sqlite", n=1)
    store.record_award("job-1", 0, "A", "tok", 101.0, 1.0)
    store.record_result("job-1", 0, "/tiles/0.exr", HASH, {"spp": 16}, 102.0)
    store.finish_attempt("tok", "done", 102.0, 1.0, {"spp": 16})
    store.mark_done("job-1", 0, 102.0)
    store.set_status("job-1", JobStatus.DONE, 103.0)
    store.apply([au.UnitRetried("job-1", 0, "asked by the user")], 104.0)
    record = store.job("job-1")
    assert (record.status, record.finished) == (JobStatus.RUNNING, None)
    assert [u.status for u in store.units("job-1")] == [UnitStatus.PENDING] and store.results("job-1") == []
    assert [a.outcome for a in store.attempts("job-1")] == ["done"]  # its history stays
    [running] = store.running_jobs()
    assert running.done == [] and running.delivered_by == {}


def test_a_requeued_job_runs_again_with_its_done_units_kept_and_its_failures_forgiven(tmp_path: Path) -> None:
    store = new_store(tmp_path / "jobs.sqlite", n=3)
    store.record_award("job-1", 0, "A", "tok-0", 101.0, 1.0)
    store.record_result("job-1", 0, "/tiles/0.exr", HASH, {"spp": 16}, 102.0)
    store.finish_attempt("tok-0", "done", 102.0, 1.0, {"spp": 16})
    store.mark_done("job-1", 0, 102.0)
    store.record_award("job-1", 1, "A", "tok-1", 103.0, 1.0)
    store.finish_attempt("tok-1", "failed", 104.0, reason="out of memory")
    store.apply([au.JobFailed("job-1", "unit 1 failed 5 times")], 105.0)
    assert [u.status for u in store.units("job-1")] == [UnitStatus.DONE, UnitStatus.FAILED, UnitStatus.FAILED]
    with pytest.raises(StoreError, match="job 'job-1' unit 0: done, not failed with its job: not requeued"):
        store.apply([au.JobRequeued("job-1", (0, 1, 2), 3, "asked by the user")], 106.0)
    assert store.job("job-1").status == JobStatus.FAILED  # one transaction: nothing of it recorded
    store.apply([au.JobRequeued("job-1", (1, 2), 2, "asked by the user")], 106.0)
    record = store.job("job-1")
    assert (record.status, record.finished, record.error) == (JobStatus.RUNNING, None, "")
    assert [u.status for u in store.units("job-1")] == [UnitStatus.DONE, UnitStatus.PENDING, UnitStatus.PENDING]
    assert len(store.results("job-1")) == 1 and [a.outcome for a in store.attempts("job-1")] == ["done", "failed"]
    [running] = store.running_jobs()  # what a restart takes up: the failure before the requeue is forgiven
    assert (running.done, running.failures, running.delivered_by) == ([0], [], {0: "A"})
    store.record_award("job-1", 1, "B", "tok-2", 107.0, 1.0)
    store.finish_attempt("tok-2", "failed", 108.0, reason="crash")
    assert store.failures("job-1") == [(1, "B", "crash")]  # one after it counts
    with pytest.raises(TransitionError, match="job 'job-1': running -> running"):
        store.apply([au.JobRequeued("job-1", (), 0, "asked by the user")], 109.0)


def test_a_drained_agent_stays_drained_in_the_store_until_it_is_resumed(tmp_path: Path) -> None:
    path = tmp_path / "jobs.sqlite"
    with new_store(path) as store:
        store.apply([au.AgentJoined("A", 1.0), au.AgentJoined("B", 1.0), au.AgentDrained("A", 0)], 100.0)
        assert store.drained() == {"A"}
    with JobStore(path) as store:  # a restarted master's
        assert store.drained() == {"A"}
        store.apply([au.AgentResumed("A"), au.AgentDrained("C", 0)], 101.0)
        assert store.drained() == {"C"} and set(store.credits()) == {"A", "B", "C"}


def test_a_schema_6_store_gains_the_requeue_and_drain_columns(tmp_path: Path) -> None:
    path = tmp_path / "farm.db"
    with new_store(path) as store:
        plan, spec = store.job("job-1").plan, store.job("job-1").spec
    path.unlink()
    write_old_store(path, 6, SCHEMA_6, (json.dumps(spec.to_dict()), json.dumps(plan)))
    sqlite3.connect(path, isolation_level=None).execute("INSERT INTO agents (name) VALUES ('A')").connection.close()
    with JobStore(path) as store:
        assert store.db.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION
        assert store.drained() == set() and store.running_jobs()[0].done == []
        store.apply([au.AgentDrained("A", 0)], 101.0)
        assert store.drained() == {"A"}
