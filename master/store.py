"""The job store: jobs, units, awards and attempts, results and agents' credits in one SQLite file.

SQLite (stdlib `sqlite3`) in WAL mode, so the CLI reads status while the master writes; foreign keys on;
a busy timeout rather than "database is locked" errors; synchronous=FULL because a unit counts as done
only once its tile and the row saying so are both on disk. The schema version lives in `user_version`.

The auction state machine (`master.auction`) never touches the store: the master applies the auction's
events with `JobStore.apply`, and on restart `restore_auction` rebuilds the auction from the rows, with
awarded-but-unfinished units back to pending and finished units left done.
"""

from __future__ import annotations

import json
import random
import sqlite3
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from core.errors import QuekaroError
from core.model import messages as m
from core.model.geometry import Rect
from core.model.job import JobPlan, JobSpec, SceneSpec
from core.model.units import WorkUnit
from master import auction as au

SCHEMA_VERSION = 2

_SCHEMA = """
CREATE TABLE jobs (
    id       TEXT PRIMARY KEY,
    scene    TEXT NOT NULL,
    spec     TEXT NOT NULL,                 -- JSON: JobSpec.to_dict() (-D parameters, options)
    plan     TEXT NOT NULL,                 -- JSON: JobPlan.to_dict() (size, effects, spp, depth, hashes)
    status   TEXT NOT NULL CHECK (status IN ('running', 'done', 'failed', 'cancelled')),
    created  REAL NOT NULL,
    finished REAL,
    error    TEXT NOT NULL DEFAULT ''
);
CREATE TABLE units (
    job_id   TEXT NOT NULL REFERENCES jobs(id) ON DELETE CASCADE,
    idx      INTEGER NOT NULL CHECK (idx >= 0),
    x INTEGER NOT NULL, y INTEGER NOT NULL, w INTEGER NOT NULL, h INTEGER NOT NULL,
    C REAL NOT NULL, S REAL NOT NULL, Nd REAL NOT NULL,
    cost     REAL NOT NULL CHECK (cost >= 0),
    status   TEXT NOT NULL CHECK (status IN ('pending', 'awarded', 'done', 'failed')),
    attempts INTEGER NOT NULL DEFAULT 0,
    PRIMARY KEY (job_id, idx)
);
CREATE TABLE attempts (
    id       INTEGER PRIMARY KEY,
    job_id   TEXT NOT NULL,
    idx      INTEGER NOT NULL,
    agent    TEXT NOT NULL,
    token    TEXT NOT NULL UNIQUE,
    started  REAL NOT NULL,
    finished REAL,
    outcome  TEXT NOT NULL
             CHECK (outcome IN ('running', 'done', 'failed', 'requeued', 'cancelled', 'interrupted')),
    estimate REAL,
    seconds  REAL,
    params   TEXT,                          -- JSON: depth, spp, band, nonfinite chosen by the agent
    reason   TEXT NOT NULL DEFAULT '',
    FOREIGN KEY (job_id, idx) REFERENCES units(job_id, idx) ON DELETE CASCADE
);
CREATE INDEX attempts_unit ON attempts(job_id, idx);
CREATE TABLE results (
    job_id    TEXT NOT NULL,
    idx       INTEGER NOT NULL,
    tile_path TEXT NOT NULL,
    hash      TEXT NOT NULL,
    params    TEXT NOT NULL,                -- JSON
    recorded  REAL NOT NULL,
    PRIMARY KEY (job_id, idx),
    FOREIGN KEY (job_id, idx) REFERENCES units(job_id, idx) ON DELETE CASCADE
);
CREATE TABLE agents (
    name      TEXT PRIMARY KEY,
    credits   INTEGER NOT NULL DEFAULT 0,
    last_seen REAL
);
"""


class StoreError(QuekaroError):
    """A job store that cannot be opened or used as asked (wrong file, newer schema, unknown job)."""


@dataclass(frozen=True)
class JobRecord:
    id: str
    scene: str  # the main scene file inside the job's bundle
    spec: JobSpec
    plan: dict[str, Any]  # JobPlan.to_dict(); `JobStore.plan` rebuilds the JobPlan
    status: str
    created: float
    finished: float | None
    error: str


@dataclass(frozen=True)
class UnitRecord:
    job_id: str
    index: int
    rect: Rect
    C: float
    S: float
    Nd: float
    cost: float
    status: str
    attempts: int

    def unit(self) -> WorkUnit:
        return WorkUnit(index=self.index, rect=self.rect, C=self.C, S=int(self.S), Nd=self.Nd, cost=self.cost)


@dataclass(frozen=True)
class ResultRecord:
    job_id: str
    index: int
    tile_path: str
    hash: str
    params: dict[str, Any]


@dataclass(frozen=True)
class Progress:
    done: int
    total: int
    failed: int
    agents_busy: int
    eta_s: float | None  # None until a unit has finished


class JobStore:
    """One SQLite file. Use one instance per thread; `readonly=True` for status readers such as the CLI."""

    def __init__(self, path: str | Path, readonly: bool = False, busy_timeout_s: float = 10.0) -> None:
        self.path = Path(path)
        try:
            if readonly:
                uri = f"file:{self.path.resolve()}?mode=ro"
                self.db = sqlite3.connect(uri, uri=True, timeout=busy_timeout_s, isolation_level=None)
            else:
                self.db = sqlite3.connect(self.path, timeout=busy_timeout_s, isolation_level=None)
            self.db.row_factory = sqlite3.Row
            self.db.execute(f"PRAGMA busy_timeout = {int(busy_timeout_s * 1000)}")
            self.db.execute("PRAGMA foreign_keys = ON")
            if not readonly:
                self.db.execute("PRAGMA journal_mode = WAL")
                self.db.execute("PRAGMA synchronous = FULL")
            self._check_schema(readonly)
        except sqlite3.DatabaseError as exc:
            raise StoreError(f"{self.path}: not a usable job store: {exc}") from exc

    def close(self) -> None:
        self.db.close()

    def __enter__(self) -> JobStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _check_schema(self, readonly: bool) -> None:
        version = self.db.execute("PRAGMA user_version").fetchone()[0]
        if version == 0 and not readonly:
            with self._tx() as db:
                # Re-read under the write lock: another process may have created the schema meanwhile.
                version = db.execute("PRAGMA user_version").fetchone()[0]
                if version == 0:
                    for statement in _SCHEMA.split(";"):
                        db.execute(statement)
                    db.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")
                    version = SCHEMA_VERSION
        if version == 1 and not readonly:
            version = self._migrate_from_1()
        if version != SCHEMA_VERSION:
            raise StoreError(f"{self.path}: schema version {version}, this program reads {SCHEMA_VERSION}")

    def _migrate_from_1(self) -> int:
        """Schema 1 kept {"options", "plan"} in one `options` column and the -D parameters in `defines`:
        split them into `spec` and `plan`, rebuilding the table as SQLite's ALTER TABLE procedure says
        (foreign keys off meanwhile, so the units rows are not cascaded away)."""
        self.db.execute("PRAGMA foreign_keys = OFF")
        try:
            with self._tx() as db:
                if db.execute("PRAGMA user_version").fetchone()[0] != 1:
                    return db.execute("PRAGMA user_version").fetchone()[0]
                rows = db.execute("SELECT * FROM jobs").fetchall()
                db.execute(_SCHEMA.split(";")[0].replace("CREATE TABLE jobs", "CREATE TABLE jobs_v2"))
                for r in rows:
                    old = json.loads(r["options"])
                    spec = {"defines": json.loads(r["defines"]), "options": old["options"]}
                    plan = {**old["plan"], "options": old["options"]}
                    db.execute("INSERT INTO jobs_v2 VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                               (r["id"], r["scene"], json.dumps(spec), json.dumps(plan), r["status"],
                                r["created"], r["finished"], r["error"]))
                db.execute("DROP TABLE jobs")
                db.execute("ALTER TABLE jobs_v2 RENAME TO jobs")
                if db.execute("PRAGMA foreign_key_check").fetchall():
                    raise StoreError(f"{self.path}: migrating from schema 1 broke a foreign key")
                db.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")
        finally:
            self.db.execute("PRAGMA foreign_keys = ON")
        return SCHEMA_VERSION

    @contextmanager
    def _tx(self) -> Iterator[sqlite3.Connection]:
        """One write transaction: BEGIN IMMEDIATE takes the write lock up front (no upgrade deadlocks)."""
        if not self.db.in_transaction:
            self.db.execute("BEGIN IMMEDIATE")
        try:
            yield self.db
        except BaseException:
            if self.db.in_transaction:
                self.db.execute("ROLLBACK")
            raise
        if self.db.in_transaction:
            self.db.execute("COMMIT")

    # --- jobs ----------------------------------------------------------------------------------------

    def create_job(
        self,
        job_id: str,
        scene: str,
        spec: JobSpec,
        plan: JobPlan,
        now: float,
    ) -> None:
        """A job (`scene` is its main file inside the bundle) and all its planned units, in one transaction."""
        units = plan.units
        if not units:
            raise StoreError(f"job {job_id!r} has no units")
        with self._tx() as db:
            if db.execute("SELECT 1 FROM jobs WHERE id = ?", (job_id,)).fetchone():
                raise StoreError(f"job {job_id!r} already exists")
            db.execute(
                "INSERT INTO jobs (id, scene, spec, plan, status, created)"
                " VALUES (?, ?, ?, ?, 'running', ?)",
                (job_id, scene, json.dumps(spec.to_dict()), json.dumps(plan.to_dict()), now),
            )
            db.executemany(
                "INSERT INTO units (job_id, idx, x, y, w, h, C, S, Nd, cost, status)"
                " VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, 'pending')",
                [(job_id, u.index, *u.rect.as_list(), u.C, u.S, u.Nd, u.cost) for u in units],
            )

    def job(self, job_id: str) -> JobRecord:
        row = self.db.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
        if row is None:
            raise StoreError(f"no job {job_id!r} in {self.path}")
        return _job(row)

    def list_jobs(self, status: str | None = None) -> list[JobRecord]:
        sql, args = "SELECT * FROM jobs", ()
        if status is not None:
            sql, args = sql + " WHERE status = ?", (status,)
        return [_job(r) for r in self.db.execute(sql + " ORDER BY created, id", args)]

    def units(self, job_id: str) -> list[UnitRecord]:
        rows = self.db.execute("SELECT * FROM units WHERE job_id = ? ORDER BY idx", (job_id,))
        return [
            UnitRecord(
                r["job_id"], r["idx"], Rect(r["x"], r["y"], r["w"], r["h"]),
                r["C"], r["S"], r["Nd"], r["cost"], r["status"], r["attempts"],
            )
            for r in rows
        ]  # fmt: skip

    def plan(self, job_id: str, scene_path: Path) -> JobPlan:
        """The stored JobPlan of a job, its scene at `scene_path` (where the master unpacked its bundle)."""
        record = self.job(job_id)
        units = [u.unit() for u in self.units(job_id)]
        return JobPlan.from_dict(record.plan, SceneSpec(scene_path, record.spec.defines), units)

    def results(self, job_id: str) -> list[ResultRecord]:
        rows = self.db.execute("SELECT * FROM results WHERE job_id = ? ORDER BY idx", (job_id,))
        return [
            ResultRecord(r["job_id"], r["idx"], r["tile_path"], r["hash"], json.loads(r["params"]))
            for r in rows
        ]

    def set_status(self, job_id: str, status: str, now: float, error: str = "") -> None:
        """End a job (done, failed, cancelled); its unfinished units and attempts end with it."""
        with self._tx() as db:
            self._end_job(db, job_id, status, now, error)

    def cancel(self, job_id: str, now: float) -> bool:
        """Cancel a running job; False if it had already ended."""
        if self.job(job_id).status != "running":
            return False
        self.set_status(job_id, "cancelled", now, "cancelled by the user")
        return True

    # --- awards, attempts, results -------------------------------------------------------------------

    def record_award(
        self, job_id: str, index: int, agent: str, token: str, started: float, estimate: float
    ) -> None:
        with self._tx() as db:
            self._award(db, job_id, index, agent, token, started, estimate)

    def finish_attempt(
        self,
        token: str,
        outcome: str,
        finished: float,
        seconds: float | None = None,
        params: dict[str, Any] | None = None,
        reason: str = "",
    ) -> None:
        """End the attempt holding `token`; a failed or requeued one sends its unit back to pending."""
        with self._tx() as db:
            self._finish(db, token, outcome, finished, seconds, params, reason)

    def record_result(
        self, job_id: str, index: int, tile_path: str, tile_hash: str, params: dict[str, Any], now: float
    ) -> bool:
        """Note a tile the caller has already written durably (fsynced). False if the unit is done already:
        the first finished result wins, and a late duplicate changes nothing."""
        with self._tx() as db:
            unit = self._unit(db, job_id, index)
            if unit["status"] == "done":
                return False
            db.execute(
                "INSERT OR REPLACE INTO results (job_id, idx, tile_path, hash, params, recorded)"
                " VALUES (?, ?, ?, ?, ?, ?)",
                (job_id, index, tile_path, tile_hash, json.dumps(params), now),
            )
            return True

    def has_result(self, job_id: str, index: int, tile_hash: str) -> bool:
        row = self.db.execute(
            "SELECT hash FROM results WHERE job_id = ? AND idx = ?", (job_id, index)
        ).fetchone()
        return row is not None and row["hash"] == tile_hash

    def mark_done(self, job_id: str, index: int, now: float) -> bool:
        """Unit done; requires its result row. False if it was done already (never done twice)."""
        with self._tx() as db:
            return self._done(db, job_id, index, now)

    # --- agents --------------------------------------------------------------------------------------

    def set_agent(self, name: str, now: float, credits: int | None = None) -> None:
        with self._tx() as db:
            self._agent(db, name, now, credits)

    def credits(self) -> dict[str, int]:
        return {r["name"]: r["credits"] for r in self.db.execute("SELECT name, credits FROM agents")}

    # --- progress ------------------------------------------------------------------------------------

    def progress(self, job_id: str) -> Progress:
        """Units done/total, agents rendering now, and an ETA from the finished units' seconds per cost."""
        self.job(job_id)
        db = self.db
        counts = dict(
            db.execute("SELECT status, COUNT(*) FROM units WHERE job_id = ? GROUP BY status", (job_id,))
        )
        total = sum(counts.values())
        busy = db.execute(
            "SELECT COUNT(DISTINCT agent) FROM attempts WHERE job_id = ? AND outcome = 'running'", (job_id,)
        ).fetchone()[0]
        rate = db.execute(
            "SELECT SUM(a.seconds), SUM(u.cost) FROM attempts a"
            " JOIN units u ON (a.job_id, a.idx) = (u.job_id, u.idx)"
            " WHERE a.job_id = ? AND a.outcome = 'done'",
            (job_id,),
        ).fetchone()
        left = db.execute(
            "SELECT COALESCE(SUM(cost), 0) FROM units WHERE job_id = ? AND status IN ('pending', 'awarded')",
            (job_id,),
        ).fetchone()[0]
        eta = None
        if rate[0] is not None and rate[1]:
            eta = left * (rate[0] / rate[1]) / max(1, busy)
        elif left == 0:
            eta = 0.0
        return Progress(counts.get("done", 0), total, counts.get("failed", 0), busy, eta)

    # --- restart and the auction's events ------------------------------------------------------------

    def resume(self, now: float) -> list[str]:
        """After a master restart: awarded units of running jobs go back to pending, their attempts end as
        interrupted; done units stay done. Returns the running jobs' ids."""
        with self._tx() as db:
            db.execute(
                "UPDATE attempts SET outcome = 'interrupted', finished = ?, reason = 'master restarted'"
                " WHERE outcome = 'running'",
                (now,),
            )
            db.execute(
                "UPDATE units SET status = 'pending' WHERE status = 'awarded'"
                " AND job_id IN (SELECT id FROM jobs WHERE status = 'running')"
            )
        return [j.id for j in self.list_jobs("running")]

    def repair(self, job_ids: list[str], now: float) -> list[tuple[str, int]]:
        """Units of these jobs marked done whose tile is gone (or never recorded) go back to pending, and a
        job ended as done with such a unit runs again: the store and the disk agree before the auction is
        rebuilt. Returns the (job, unit) pairs repaired."""
        bad = []
        for job_id in job_ids:
            tiles = {r.index: r.tile_path for r in self.results(job_id)}
            bad += [(job_id, u.index) for u in self.units(job_id)
                    if u.status == "done" and not (u.index in tiles and Path(tiles[u.index]).is_file())]
        with self._tx() as db:
            for job_id, index in bad:
                db.execute("DELETE FROM results WHERE job_id = ? AND idx = ?", (job_id, index))
                db.execute("UPDATE units SET status = 'pending' WHERE job_id = ? AND idx = ?", (job_id, index))
                db.execute("UPDATE jobs SET status = 'running', finished = NULL WHERE id = ?", (job_id,))
        return bad

    def failures(self, job_id: str) -> list[tuple[int, str, str]]:
        rows = self.db.execute(
            "SELECT idx, agent, reason FROM attempts WHERE job_id = ? AND outcome = 'failed' ORDER BY id",
            (job_id,),
        )
        return [(r["idx"], r["agent"], r["reason"]) for r in rows]

    def apply(self, commands: Iterable[au.Command], now: float) -> None:
        """Record the auction's events in one transaction (its Sends are the transport's business)."""
        with self._tx() as db:
            for cmd in commands:
                if isinstance(cmd, au.Event):
                    self._apply(db, cmd, now)

    def _apply(self, db: sqlite3.Connection, ev: au.Event, now: float) -> None:
        d = ev.detail
        if ev.kind == "unit-awarded":
            self._award(db, ev.job_id, ev.index, ev.agent, d["token"], now, d["estimate"])
        elif ev.kind == "unit-done":
            self._finish(db, d["token"], "done", now, d["seconds"], d["params"], "")
            if not self._done(db, ev.job_id, ev.index, now):
                raise StoreError(f"job {ev.job_id!r} unit {ev.index}: done twice")
        elif ev.kind in ("unit-failed", "unit-requeued"):
            outcome = "failed" if ev.kind == "unit-failed" else "requeued"
            self._finish(db, d["token"], outcome, now, None, None, ev.reason)
        elif ev.kind in ("job-done", "job-failed", "job-cancelled"):
            self._end_job(db, ev.job_id, ev.kind.removeprefix("job-"), now, ev.reason)
        if ev.agent is not None and ev.kind != "ignored":
            self._agent(db, ev.agent, now, d.get("credits"))

    # --- statements shared by the public methods and `apply` -----------------------------------------

    def _unit(self, db: sqlite3.Connection, job_id: str, index: int) -> sqlite3.Row:
        row = db.execute("SELECT * FROM units WHERE job_id = ? AND idx = ?", (job_id, index)).fetchone()
        if row is None:
            raise StoreError(f"no unit {index} in job {job_id!r}")
        return row

    def _award(
        self, db, job_id: str, index: int, agent: str, token: str, started: float, estimate: float
    ) -> None:
        self._unit(db, job_id, index)
        db.execute(
            "UPDATE units SET status = 'awarded', attempts = attempts + 1 WHERE job_id = ? AND idx = ?",
            (job_id, index),
        )
        db.execute(
            "INSERT INTO attempts (job_id, idx, agent, token, started, outcome, estimate)"
            " VALUES (?, ?, ?, ?, ?, 'running', ?)",
            (job_id, index, agent, token, started, estimate),
        )

    def _finish(self, db, token, outcome, finished, seconds, params, reason) -> None:
        row = db.execute("SELECT job_id, idx FROM attempts WHERE token = ?", (token,)).fetchone()
        if row is None:
            raise StoreError(f"no attempt with token {token[:8]}...")
        db.execute(
            "UPDATE attempts SET outcome = ?, finished = ?, seconds = ?, params = ?, reason = ?"
            " WHERE token = ?",
            (outcome, finished, seconds, None if params is None else json.dumps(params), reason, token),
        )
        if outcome in ("failed", "requeued"):
            db.execute(
                "UPDATE units SET status = 'pending' WHERE job_id = ? AND idx = ? AND status = 'awarded'",
                (row["job_id"], row["idx"]),
            )

    def _done(self, db: sqlite3.Connection, job_id: str, index: int, now: float) -> bool:
        if self._unit(db, job_id, index)["status"] == "done":
            return False
        if (
            db.execute("SELECT 1 FROM results WHERE job_id = ? AND idx = ?", (job_id, index)).fetchone()
            is None
        ):
            # A unit counts as done only once its tile is on disk and recorded (issue 4, job store).
            raise StoreError(
                f"job {job_id!r} unit {index}: no durable result recorded before marking it done"
            )
        db.execute("UPDATE units SET status = 'done' WHERE job_id = ? AND idx = ?", (job_id, index))
        return True

    def _end_job(self, db: sqlite3.Connection, job_id: str, status: str, now: float, error: str) -> None:
        if status not in ("done", "failed", "cancelled"):
            raise StoreError(f"job status {status!r} is not an end state")
        cur = db.execute(
            "UPDATE jobs SET status = ?, finished = ?, error = ? WHERE id = ? AND status = 'running'",
            (status, now, error, job_id),
        )
        if cur.rowcount == 0:
            self.job(job_id)  # raises for an unknown job; a job already ended stays as it ended
            return
        if status != "done":
            db.execute(
                "UPDATE units SET status = 'failed' WHERE job_id = ? AND status IN ('pending', 'awarded')",
                (job_id,),
            )
            db.execute(
                "UPDATE attempts SET outcome = 'cancelled', finished = ?, reason = ?"
                " WHERE job_id = ? AND outcome = 'running'",
                (now, error, job_id),
            )

    def _agent(self, db: sqlite3.Connection, name: str, now: float, credits: int | None) -> None:
        db.execute(
            "INSERT INTO agents (name, credits, last_seen) VALUES (?, COALESCE(?, 0), ?)"
            " ON CONFLICT(name) DO UPDATE SET credits = COALESCE(?, credits),"
            " last_seen = MAX(COALESCE(last_seen, 0), ?)",
            (name, credits, now, credits, now),
        )


def _job(row: sqlite3.Row) -> JobRecord:
    return JobRecord(
        row["id"], row["scene"], JobSpec.from_dict(json.loads(row["spec"])), json.loads(row["plan"]),
        row["status"], row["created"], row["finished"], row["error"],
    )  # fmt: skip


def restore_auction(
    store: JobStore,
    job_info: Callable[[JobRecord], m.JobInfo],
    now: float,
    config: au.Config | None = None,
    rng: random.Random | None = None,
) -> tuple[au.Auction, list[au.Command]]:
    """Rebuild the auction after a master restart: every running job with its done units and past failures,
    the agents' credits; awarded units are back to pending. `job_info` builds a job's CFP description (its
    scene URL depends on where the master serves now). Returns the auction and the events of resuming
    (e.g. a job that was in fact complete), which the caller should `apply`."""
    store.resume(now)
    auction = au.Auction(config, rng, credits=store.credits())
    out: list[au.Command] = []
    for record in store.list_jobs("running"):
        units = store.units(record.id)
        done = [u.index for u in units if u.status == "done"]
        try:
            info = job_info(record)
        except Exception as exc:  # one job the master cannot describe must not stop the others
            store.set_status(record.id, "failed", now, f"cannot resume the job: {type(exc).__name__}: {exc}")
            continue
        out += auction.add_job(info, [u.unit() for u in units], done, store.failures(record.id))
    return auction, out
