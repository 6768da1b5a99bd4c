"""The job store: jobs, units, awards and attempts, results and agents' credits in one SQLite file.

`JobStore(path)` holds it. The auction (`master.auction`) never touches the store: the master records
the auction's records with `JobStore.apply`. After a restart `resume` sends awarded units back to pending
and the auction rebuilds itself from `running_jobs` and `credits`; drained agents (`drained`) are drained
again as they come back. Statuses (rows and CHECK constraints)
are `core.model.status`'s, and every change is checked against its transition table, as the auction's are.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import sqlite3
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from core.errors import QuekaroError
from core.model.geometry import Rect
from core.model.job import JobPlan, JobSpec, SceneSpec
from core.model.status import (
    STORED_UNIT_STATUSES,
    JobStatus,
    TransitionError,
    UnitStatus,
    job_transition,
    unit_transition,
)
from core.model.units import WorkUnit
from master import auction as au
from planning.progressive import BUDGET, NOISE, TIME, Goal

SCHEMA_VERSION = 7
# The auction's records that answer a user's command: committed to disk before the command is answered.
USER_RECORDS = (au.JobCancelled, au.JobRequeued, au.UnitRetried, au.AgentDrained, au.AgentResumed)
# A unit row's WorkUnit.work in SQL ({t}: the table's alias and a dot, or nothing).
_WORK = "{t}cost * COALESCE({t}spp, 1)"
_INSERT_UNIT = ("INSERT INTO units (job_id, idx, x, y, w, h, C, S, Nd, cost, status, spp, depth_floor, depth)"
                " VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)")


def _sql_set(statuses: Iterable[str]) -> str:
    return ", ".join(f"'{s}'" for s in statuses)


_SCHEMA = f"""
CREATE TABLE jobs (
    id       TEXT PRIMARY KEY,
    scene    TEXT NOT NULL,
    spec     TEXT NOT NULL,                 -- JSON: JobSpec.to_dict() (-D parameters, options)
    plan     TEXT NOT NULL,                 -- JSON: JobPlan.to_dict() (size, effects, spp, depth, hashes)
    status   TEXT NOT NULL CHECK (status IN ({_sql_set(JobStatus)})),
    created  REAL NOT NULL,
    finished REAL,
    error    TEXT NOT NULL DEFAULT '',
    requeued REAL                           -- its latest requeue: failures before it are not held against it
);
CREATE TABLE units (
    job_id   TEXT NOT NULL REFERENCES jobs(id) ON DELETE CASCADE,
    idx      INTEGER NOT NULL CHECK (idx >= 0),
    x INTEGER NOT NULL, y INTEGER NOT NULL, w INTEGER NOT NULL, h INTEGER NOT NULL,
    C REAL NOT NULL, S REAL NOT NULL, Nd REAL NOT NULL,
    cost     REAL NOT NULL CHECK (cost >= 0),
    status   TEXT NOT NULL CHECK (status IN ({_sql_set(STORED_UNIT_STATUSES)})),
    attempts INTEGER NOT NULL DEFAULT 0,
    spp      INTEGER CHECK (spp IS NULL OR spp >= 1),  -- WorkUnit.spp (adaptive jobs), NULL where rules choose
    depth_floor INTEGER CHECK (depth_floor IS NULL OR depth_floor >= 1),  -- WorkUnit.depth_floor, NULL: none
    depth    INTEGER CHECK (depth IS NULL OR depth >= -1),  -- WorkUnit.depth (a pass's, pinned), NULL: none
    PRIMARY KEY (job_id, idx)
);
CREATE TABLE attempts (
    id       INTEGER PRIMARY KEY,
    job_id   TEXT NOT NULL,
    idx      INTEGER NOT NULL,
    agent    TEXT NOT NULL,
    token_sha256 TEXT NOT NULL UNIQUE,      -- the award token's sha256: the token itself is never stored
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
    last_seen REAL,
    draining  INTEGER NOT NULL DEFAULT 0 CHECK (draining IN (0, 1))  -- drained by the user, across restarts
);
"""


def token_sha256(token: str) -> str:
    """What the store keeps of an award token: its sha256 (the token is 128 random bits, so no salt)."""
    return hashlib.sha256(token.encode()).hexdigest()


class StoreError(QuekaroError):
    """A job store that cannot be opened or used as asked (wrong file, newer schema, unknown job)."""


@dataclass(frozen=True)
class JobRecord:
    id: str
    scene: str  # the main scene file inside the job's bundle
    spec: JobSpec
    plan: dict[str, Any]  # JobPlan.to_dict(); `JobStore.plan` rebuilds the JobPlan
    status: JobStatus
    created: float
    finished: float | None
    error: str

    @property
    def planned_units(self) -> set[int] | None:
        """A progressive job's units as its plan made them (their indices); the store's unit rows beyond
        them are their passes. None for a job not in passes."""
        return {int(k) for k in self.plan["neighbours"]} if self.spec.options.in_passes else None


@dataclass(frozen=True)
class UnitRecord:
    job_id: str
    index: int
    rect: Rect
    C: float
    S: float
    Nd: float
    cost: float
    status: UnitStatus
    attempts: int
    spp: int | None = None
    depth_floor: int | None = None
    depth: int | None = None

    def unit(self) -> WorkUnit:
        return WorkUnit(index=self.index, rect=self.rect, C=self.C, S=int(self.S), Nd=self.Nd, cost=self.cost,
                        spp=self.spp, depth_floor=self.depth_floor, depth=self.depth)


@dataclass(frozen=True)
class ResultRecord:
    job_id: str
    index: int
    tile_path: str
    hash: str
    params: dict[str, Any]


@dataclass(frozen=True)
class AttemptRecord:
    """One award of a unit to an agent and how it ended (the web page shows a unit's attempts)."""

    index: int
    agent: str
    started: float
    finished: float | None
    outcome: str  # running, done, failed, requeued, cancelled, interrupted
    estimate: float | None
    seconds: float | None
    reason: str


@dataclass(frozen=True)
class RunningJob:
    """A running job as a restarted master's auction takes it up (`master.auction.Auction.restore`)."""

    job_id: str
    units: list[WorkUnit]
    done: list[int]  # indices of the units done
    failures: list[tuple[int, str, str]]  # (unit index, agent, reason) of its failed attempts, oldest first
    delivered_by: dict[int, str] = field(default_factory=dict)  # done unit -> the agent whose tile it has
    channels: list[str] | None = None  # what every tile of the job carries (its plan's)
    goal: Goal | None = None  # a progressive job's, with its passes so far (the master adds both)
    resumed: au.ResumedPasses | None = None


@dataclass(frozen=True)
class Progress:
    done: int
    total: int
    failed: int
    agents_busy: int
    eta_s: float | None  # None until a unit has finished
    retried: int = 0  # attempts that ended failed or requeued (their unit went back to auction)
    last_retry: str | None = None  # the latest of those: "agent: outcome (reason)"
    eta_at_least: bool = False  # the ETA counts only the passes ordered so far (a noise goal orders more)
    passes: PassProgress | None = None  # a progressive job's passes (its done/total count its image's units)


@dataclass(frozen=True)
class PassProgress:
    """A progressive job's passes: done and ordered (extra passes included; those withdrawn, gone), the
    mean samples per pixel the done ones give the image, and the goal (budget, noise or time)."""

    done: int
    ordered: int
    spp_mean: float
    goal: str
    share: float = 0.0  # of the job done, 0..1: the passes' work (cost x spp) done over ordered; a time goal's seconds


class JobStore:
    """One SQLite file. Use one instance per thread; `readonly=True` for status readers such as the CLI.

    WAL mode, so the CLI reads status while the master writes; foreign keys on; a busy timeout rather
    than "database is locked" errors. Every commit is on disk when it returns (synchronous=FULL), but the
    auction's own records (`apply`): a power cut may lose their last ones (the database stays whole), and
    their units render again; a unit counts as done only once its tile is on disk. The schema version lives
    in `user_version`."""

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
            self._synchronous = "FULL"
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
        if version == 2 and not readonly:
            version = self._migrate_from_2()
        if version == 3 and not readonly:
            version = self._migrate_from_3()
        if version == 4 and not readonly:
            version = self._migrate_from_4()
        if version == 5 and not readonly:
            version = self._migrate_from_5()
        if version == 6 and not readonly:
            version = self._migrate_from_6()
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
                    db.execute("INSERT INTO jobs_v2 (id, scene, spec, plan, status, created, finished, error)"
                               " VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                               (r["id"], r["scene"], json.dumps(spec), json.dumps(plan), r["status"],
                                r["created"], r["finished"], r["error"]))
                db.execute("DROP TABLE jobs")
                db.execute("ALTER TABLE jobs_v2 RENAME TO jobs")
                if db.execute("PRAGMA foreign_key_check").fetchall():
                    raise StoreError(f"{self.path}: migrating from schema 1 broke a foreign key")
                db.execute("PRAGMA user_version = 2")
        finally:
            self.db.execute("PRAGMA foreign_keys = ON")
        return 2

    def _migrate_from_2(self) -> int:
        """Schema 3 adds each unit's planned spp (adaptive jobs); the units stored before have none."""
        with self._tx() as db:
            if db.execute("PRAGMA user_version").fetchone()[0] == 2:
                db.execute("ALTER TABLE units ADD COLUMN spp INTEGER CHECK (spp IS NULL OR spp >= 1)")
                db.execute("PRAGMA user_version = 3")
        return 3

    def _migrate_from_3(self) -> int:
        """Schema 4 adds each unit's depth floor (planning.depthcut); the units stored before have none."""
        with self._tx() as db:
            if db.execute("PRAGMA user_version").fetchone()[0] == 3:
                db.execute("ALTER TABLE units ADD COLUMN depth_floor INTEGER"
                           " CHECK (depth_floor IS NULL OR depth_floor >= 1)")
                db.execute("PRAGMA user_version = 4")
        return 4

    def _migrate_from_4(self) -> int:
        """Schema 5 keeps each award token's sha256 in place of the token (another reader of the file must
        not be able to present it)."""
        with self._tx() as db:
            if db.execute("PRAGMA user_version").fetchone()[0] == 4:
                db.execute("ALTER TABLE attempts RENAME COLUMN token TO token_sha256")
                rows = db.execute("SELECT id, token_sha256 FROM attempts").fetchall()
                db.executemany("UPDATE attempts SET token_sha256 = ? WHERE id = ?",
                               [(token_sha256(r["token_sha256"]), r["id"]) for r in rows])
                db.execute("PRAGMA user_version = 5")
        return 5

    def _migrate_from_5(self) -> int:
        """Schema 6 adds each pass's pinned depth (a progressive job at a rule level); none stored before."""
        with self._tx() as db:
            if db.execute("PRAGMA user_version").fetchone()[0] == 5:
                db.execute("ALTER TABLE units ADD COLUMN depth INTEGER CHECK (depth IS NULL OR depth >= -1)")
                db.execute("PRAGMA user_version = 6")
        return 6

    def _migrate_from_6(self) -> int:
        """Schema 7 keeps each job's latest requeue and each agent's drain; none before. (A schema 1 home's jobs
        table, made anew by `_migrate_from_1`, has its requeued column already.)"""
        with self._tx() as db:
            if db.execute("PRAGMA user_version").fetchone()[0] == 6:
                if "requeued" not in {r["name"] for r in db.execute("PRAGMA table_info(jobs)")}:
                    db.execute("ALTER TABLE jobs ADD COLUMN requeued REAL")
                db.execute("ALTER TABLE agents ADD COLUMN draining INTEGER NOT NULL DEFAULT 0"
                           " CHECK (draining IN (0, 1))")
                db.execute("PRAGMA user_version = 7")
        return 7

    @contextmanager
    def _tx(self, synchronous: str = "FULL") -> Iterator[sqlite3.Connection]:
        """One write transaction: BEGIN IMMEDIATE takes the write lock up front (no upgrade deadlocks); its
        commit at SQLite's `synchronous` level (FULL: on disk when it returns). Inside another, it is part of
        that one."""
        if not self.db.in_transaction:
            if synchronous != self._synchronous:
                self.db.execute(f"PRAGMA synchronous = {synchronous}")
                self._synchronous = synchronous
            self.db.execute("BEGIN IMMEDIATE")
        try:
            yield self.db
        except BaseException:
            if self.db.in_transaction:
                self.db.execute("ROLLBACK")
            raise
        if self.db.in_transaction:
            try:
                self.db.execute("COMMIT")
            except sqlite3.Error:  # e.g. the disk full: nothing of it is kept, and the next one begins afresh
                if self.db.in_transaction:
                    self.db.execute("ROLLBACK")
                raise

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
                "INSERT INTO jobs (id, scene, spec, plan, status, created) VALUES (?, ?, ?, ?, ?, ?)",
                (job_id, scene, json.dumps(spec.to_dict()), json.dumps(plan.to_dict()), JobStatus.RUNNING, now),
            )
            db.executemany(_INSERT_UNIT, _unit_rows(job_id, units))

    def job(self, job_id: str) -> JobRecord:
        row = self.db.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
        if row is None:
            raise StoreError(f"no job {job_id!r}")
        return _job(row)

    def list_jobs(self, status: JobStatus | None = None) -> list[JobRecord]:
        sql, args = "SELECT * FROM jobs", ()
        if status is not None:
            sql, args = sql + " WHERE status = ?", (status,)
        return [_job(r) for r in self.db.execute(sql + " ORDER BY created, id", args)]

    def sequence(self, sequence: str) -> list[JobRecord]:
        """The jobs of a frame sequence (their specs name it), in frame order; empty for an unknown one."""
        jobs = [r for r in self.list_jobs() if r.spec.sequence == sequence]
        return sorted(jobs, key=lambda r: (r.spec.frame, r.created, r.id))

    def delete_job(self, job_id: str) -> None:
        """Forget an ended job: its row, units, attempts and results (its files are the master's to remove).
        A running job is refused (StoreError): cancel it first."""
        with self._tx() as db:
            if self.job(job_id).status == JobStatus.RUNNING:
                raise StoreError(f"job {job_id!r} is running: cancel it before deleting it")
            for table, key in (("results", "job_id"), ("attempts", "job_id"), ("units", "job_id"), ("jobs", "id")):
                db.execute(f"DELETE FROM {table} WHERE {key} = ?", (job_id,))

    def units(self, job_id: str) -> list[UnitRecord]:
        rows = self.db.execute("SELECT * FROM units WHERE job_id = ? ORDER BY idx", (job_id,))
        return [
            UnitRecord(
                r["job_id"], r["idx"], Rect(r["x"], r["y"], r["w"], r["h"]),
                r["C"], r["S"], r["Nd"], r["cost"], UnitStatus(r["status"]), r["attempts"], r["spp"],
                r["depth_floor"], r["depth"],
            )
            for r in rows
        ]  # fmt: skip

    def plan(self, job_id: str, scene_path: Path) -> JobPlan:
        """The stored JobPlan of a job, its scene at `scene_path` (where the master unpacked its bundle)."""
        record = self.job(job_id)
        units = [u.unit() for u in self.units(job_id)]
        planned = record.planned_units
        if planned is not None:  # the units its plan made: pass k of unit u is row k n + u, u's rectangle and
            first: dict[int, WorkUnit] = {}  # features at the pass's spp; a withdrawn pass's row is gone, so
            for unit in units:  # each unit is read from its first row left (each keeps a pass done)
                first.setdefault(au.pass_origin(unit.index, len(planned))[0], unit)
            units = [dataclasses.replace(first[i], index=i, spp=None) for i in sorted(first)]
        return JobPlan.from_dict(record.plan, SceneSpec(scene_path, record.spec.defines), units)

    def results(self, job_id: str) -> list[ResultRecord]:
        rows = self.db.execute("SELECT * FROM results WHERE job_id = ? ORDER BY idx", (job_id,))
        return [
            ResultRecord(r["job_id"], r["idx"], r["tile_path"], r["hash"], json.loads(r["params"]))
            for r in rows
        ]

    def set_status(self, job_id: str, status: JobStatus, now: float, error: str = "") -> None:
        """End a running job (done, failed, cancelled); its unfinished units and attempts end with it. A job
        that has ended already stays as it ended."""
        with self._tx() as db:
            self._end_job(db, job_id, status, now, error)

    def cancel(self, job_id: str, now: float) -> bool:
        """Cancel a running job; False if it had already ended."""
        if self.job(job_id).status != JobStatus.RUNNING:
            return False
        self.set_status(job_id, JobStatus.CANCELLED, now, "cancelled by the user")
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
            if unit["status"] == UnitStatus.DONE:
                return False
            self._result(db, job_id, index, tile_path, tile_hash, params, now)
            return True

    @staticmethod
    def _result(db: sqlite3.Connection, job_id: str, index: int, tile_path: str, tile_hash: str,
                params: dict[str, Any], now: float) -> None:
        db.execute("INSERT OR REPLACE INTO results (job_id, idx, tile_path, hash, params, recorded)"
                   " VALUES (?, ?, ?, ?, ?, ?)", (job_id, index, tile_path, tile_hash, json.dumps(params), now))

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

    def agent_counts(self) -> dict[str, tuple[int, int]]:
        """Units each agent finished and failed, over every job: agent -> (done, failed)."""
        rows = self.db.execute("SELECT agent, SUM(outcome = 'done'), SUM(outcome = 'failed') FROM attempts"
                               " GROUP BY agent")
        return {r[0]: (int(r[1]), int(r[2])) for r in rows}

    def credits(self) -> dict[str, int]:
        return {r["name"]: r["credits"] for r in self.db.execute("SELECT name, credits FROM agents")}

    def drained(self) -> set[str]:
        """The agents the user drained (and did not resume): drained again as they come back after a restart."""
        return {r["name"] for r in self.db.execute("SELECT name FROM agents WHERE draining = 1")}

    def agents_busy(self, job_ids: Sequence[str]) -> int:
        """Agents rendering a unit of any of these jobs now (an agent on two frames counts once)."""
        marks = ", ".join("?" * len(job_ids))
        return self.db.execute(f"SELECT COUNT(DISTINCT agent) FROM attempts WHERE outcome = 'running' AND job_id IN "
                               f"({marks})", tuple(job_ids)).fetchone()[0]

    def attempts(self, job_id: str, index: int | None = None) -> list[AttemptRecord]:
        """A job's attempts (one unit's with `index`), oldest first (without their tokens' hashes)."""
        sql = ("SELECT idx, agent, started, finished, outcome, estimate, seconds, reason FROM attempts"
               " WHERE job_id = ?")
        args: tuple[Any, ...] = (job_id,)
        if index is not None:
            sql, args = sql + " AND idx = ?", (job_id, index)
        return [AttemptRecord(*row) for row in self.db.execute(sql + " ORDER BY id", args)]

    # --- progress ------------------------------------------------------------------------------------

    def progress(self, job_id: str, now: float | None = None) -> Progress:
        """Units done/total, agents rendering now, and an ETA from the finished units' seconds per unit of
        work (WorkUnit.work). Given `now` (wall-clock time, as the attempts' start times), the time the
        units being rendered have already rendered is taken off, each at most its unit's expected time, so
        the ETA counts down between tiles. A progressive job counts the units of its image, not its passes
        (`_unit_progress`), and says how far its passes are (`PassProgress`)."""
        record = self.job(job_id)
        planned = record.planned_units
        rows = self._row_progress(job_id, now, None if planned is None else len(planned))
        return rows if planned is None else self._unit_progress(record, len(planned), rows, now)

    def _row_progress(self, job_id: str, now: float | None, units: int | None = None) -> Progress:
        """Progress counted over the job's unit rows (a progressive job's rows are its passes: `units` the
        units of its image)."""
        db = self.db
        counts = dict(
            db.execute("SELECT status, COUNT(*) FROM units WHERE job_id = ? GROUP BY status", (job_id,))
        )
        total = sum(counts.values())
        busy = self.agents_busy([job_id])
        rate = db.execute(
            f"SELECT SUM(a.seconds), SUM({_WORK.format(t='u.')}) FROM attempts a"
            " JOIN units u ON (a.job_id, a.idx) = (u.job_id, u.idx)"
            " WHERE a.job_id = ? AND a.outcome = 'done'",
            (job_id,),
        ).fetchone()
        left = db.execute(
            f"SELECT COALESCE(SUM({_WORK.format(t='')}), 0) FROM units WHERE job_id = ? AND status IN (?, ?)",
            (job_id, UnitStatus.PENDING, UnitStatus.AWARDED),
        ).fetchone()[0]
        eta = None
        if rate[0] is not None and rate[1]:
            per_work = rate[0] / rate[1]
            eta = max(0.0, left * per_work - self._rendered_so_far(job_id, per_work, now)) / max(1, busy)
        elif left == 0:
            eta = 0.0
        retried, last = self._retries(job_id, units)
        return Progress(counts.get(UnitStatus.DONE, 0), total, counts.get(UnitStatus.FAILED, 0), busy, eta,
                        retried, last)

    def _unit_progress(self, record: JobRecord, units: int, rows: Progress, now: float | None) -> Progress:
        """A progressive job's progress: its `units` image units (`_units_met`), those left short of their
        goal where it ended otherwise than done, its passes (`rows` counted them), and its ETA
        (`_pass_eta`)."""
        goal = Goal.of(record.spec.options, int(record.plan["spp"]))
        done = self._units_met(record, units, goal)
        short = units - done if record.status in (JobStatus.FAILED, JobStatus.CANCELLED) else 0
        eta, at_least = self._pass_eta(record, goal, rows.eta_s, now)
        passes = PassProgress(rows.done, rows.total, self._spp_mean(record.id, units), goal.kind,
                              self._share(record, goal, now))
        return dataclasses.replace(rows, done=done, total=units, failed=short, eta_s=eta, eta_at_least=at_least,
                                   passes=passes)

    def _units_met(self, record: JobRecord, units: int, goal: Goal) -> int:
        """Units of a progressive job whose goal is met. A done job's units all are (each has a verdict). A
        budget job orders every pass at once: a unit is done once it has a pass done and none pending, out, or
        failed with its job (its budget may be its own: a rule level's). A noise or time goal is judged at the
        job's end only."""
        if record.status == JobStatus.DONE:
            return self.db.execute(
                "SELECT COUNT(DISTINCT idx % ?) FROM units WHERE job_id = ? AND status = ?",
                (units, record.id, UnitStatus.DONE)).fetchone()[0]
        if goal.kind != BUDGET:
            return 0
        return self.db.execute(
            "SELECT COUNT(*) FROM (SELECT idx % ? AS unit FROM units WHERE job_id = ? GROUP BY unit"
            " HAVING SUM(status = ?) > 0 AND SUM(status IN (?, ?, ?)) = 0)",
            (units, record.id, UnitStatus.DONE, UnitStatus.PENDING, UnitStatus.AWARDED, UnitStatus.FAILED)
        ).fetchone()[0]

    def _spp_mean(self, job_id: str, units: int) -> float:
        """The samples per pixel the done passes give the image: each pass's spp over its area, over the
        image's (its units' areas: every pass of unit u, row k units + u, has its rectangle)."""
        samples, area = self.db.execute(
            "SELECT SUM(samples), SUM(area) FROM (SELECT SUM(CASE WHEN status = ? THEN spp * w * h ELSE 0 END)"
            " AS samples, MAX(w * h) AS area FROM units WHERE job_id = ? GROUP BY idx % ?)",
            (UnitStatus.DONE, job_id, units)).fetchone()
        return round((samples or 0) / area, 1) if area else 0.0

    def _share(self, record: JobRecord, goal: Goal, now: float | None) -> float:
        """How much of a progressive job is done, 0..1 (`PassProgress.share`): 1 once it is done."""
        if record.status == JobStatus.DONE:
            return 1.0
        if goal.kind == TIME:
            return round(min(1.0, self._spent(record.id, now) / goal.seconds), 3)
        done, ordered = self.db.execute(
            f"SELECT SUM(CASE WHEN status = ? THEN {_WORK.format(t='')} ELSE 0 END), SUM({_WORK.format(t='')})"
            " FROM units WHERE job_id = ?", (UnitStatus.DONE, record.id)).fetchone()
        return round(done / ordered, 3) if ordered else 0.0

    def _pass_eta(self, record: JobRecord, goal: Goal, rows_eta: float | None, now: float | None
                  ) -> tuple[float | None, bool]:
        """(ETA, whether it is only a lower bound). A budget job orders all its passes at once: the passes'
        ETA is the job's. A time goal ends once its seconds from the first award are spent, or when the
        passes out end if later. A noise goal may order more rounds: the ETA of the passes out is a lower
        bound."""
        if record.status != JobStatus.RUNNING or goal.kind == BUDGET:
            return rows_eta, False
        if goal.kind == NOISE:
            return rows_eta, True
        return max(goal.seconds - self._spent(record.id, now), rows_eta or 0.0), False

    def _spent(self, job_id: str, now: float | None) -> float:
        """Seconds from the job's first award to `now` (a time goal counts them); 0 before it, or without `now`."""
        first = self.db.execute("SELECT MIN(started) FROM attempts WHERE job_id = ?", (job_id,)).fetchone()[0]
        return max(0.0, now - first) if first is not None and now is not None else 0.0

    def _retries(self, job_id: str, units: int | None = None) -> tuple[int, str | None]:
        """How many attempts of the job ended without a tile (an agent that failed, died or lied), and
        the latest: a user sees that a job went on after an agent was lost, and why. A progressive job's
        (of `units` units) names the unit and its pass, not the pass's row."""
        retried = "FROM attempts WHERE job_id = ? AND outcome IN ('failed', 'requeued')"
        (count,) = self.db.execute(f"SELECT COUNT(*) {retried}", (job_id,)).fetchone()
        if not count:
            return 0, None
        index, agent, outcome, reason = self.db.execute(
            f"SELECT idx, agent, outcome, reason {retried} ORDER BY id DESC LIMIT 1", (job_id,)).fetchone()
        if units is not None:
            unit, pass_index = au.pass_origin(index, units)
            index = f"{unit}, pass {pass_index}"
        return count, f"unit {index} {outcome}: {reason}" if reason else f"unit {index} {outcome} on {agent}"

    def _rendered_so_far(self, job_id: str, per_work: float, now: float | None) -> float:
        """Seconds the units of a job being rendered have rendered by `now`, each render capped at its work
        x `per_work` (a unit over its time is not done sooner for it). An agent renders one call at a time:
        of the units it holds, those awarded first (together, in one round: one call renders them) are taken
        as rendering, the others as queued."""
        if now is None:
            return 0.0
        running = self.db.execute(
            f"SELECT a.agent, a.started, {_WORK.format(t='u.')} FROM attempts a"
            " JOIN units u ON (a.job_id, a.idx) = (u.job_id, u.idx)"
            " WHERE a.job_id = ? AND a.outcome = 'running' AND u.status = ? ORDER BY a.started",
            (job_id, UnitStatus.AWARDED),
        ).fetchall()
        first: dict[str, list[float]] = {}  # an agent's first call: [started, its units' work]
        for agent, started, work in running:
            call = first.setdefault(agent, [started, 0.0])
            if started == call[0]:
                call[1] += work
        return sum(min(max(0.0, now - started), work * per_work) for started, work in first.values())

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
            self._move_units(db, UnitStatus.PENDING, [UnitStatus.AWARDED],
                             "job_id IN (SELECT id FROM jobs WHERE status = ?)", (JobStatus.RUNNING,),
                             "awarded units of running jobs, on restart")
        return [j.id for j in self.list_jobs(JobStatus.RUNNING)]

    def running_jobs(self) -> list[RunningJob]:
        """Every running job with its units, those done (and by whom) and its past failures: what the auction
        rebuilds itself from after a restart (with `credits`)."""
        return [self.taken_up(record.id) for record in self.list_jobs(JobStatus.RUNNING)]

    def taken_up(self, job_id: str) -> RunningJob:
        """A job as the auction takes it up: running after a restart, or ended to run again (a requeue)."""
        units = self.units(job_id)
        done = [u.index for u in units if u.status == UnitStatus.DONE]
        return RunningJob(job_id, [u.unit() for u in units], done, self.failures(job_id),
                          self._delivered_by(job_id), self.job(job_id).plan.get("channels"))

    def _delivered_by(self, job_id: str) -> dict[int, str]:
        """The agent of each done unit's done attempt (a unit is never done twice)."""
        rows = self.db.execute(
            "SELECT a.idx, a.agent FROM attempts a JOIN units u ON u.job_id = a.job_id AND u.idx = a.idx"
            " WHERE a.job_id = ? AND a.outcome = 'done' AND u.status = ?", (job_id, UnitStatus.DONE))
        return {r["idx"]: r["agent"] for r in rows}

    def repair(self, job_ids: list[str], now: float) -> list[tuple[str, int]]:
        """Units of these jobs marked done whose tile is gone (or never recorded) go back to pending, and a
        job ended as done with such a unit runs again: the store and the disk agree before the auction is
        rebuilt. Returns the (job, unit) pairs repaired."""
        bad = []
        for job_id in job_ids:
            tiles = {r.index: r.tile_path for r in self.results(job_id)}
            bad += [(job_id, u.index) for u in self.units(job_id)
                    if u.status == UnitStatus.DONE and not (u.index in tiles and Path(tiles[u.index]).is_file())]
        with self._tx() as db:
            for job_id, index in bad:
                db.execute("DELETE FROM results WHERE job_id = ? AND idx = ?", (job_id, index))
                self._set_unit(db, job_id, index, UnitStatus.PENDING)
                self._reopen_job(db, job_id)
        return bad

    def failures(self, job_id: str) -> list[tuple[int, str, str]]:
        """The job's failed attempts since its latest requeue (those before are forgiven), oldest first."""
        rows = self.db.execute(
            "SELECT a.idx, a.agent, a.reason FROM attempts a JOIN jobs j ON j.id = a.job_id"
            " WHERE a.job_id = ? AND a.outcome = 'failed' AND a.started >= COALESCE(j.requeued, a.started)"
            " ORDER BY a.id",
            (job_id,),
        )
        return [(r["idx"], r["agent"], r["reason"]) for r in rows]

    def apply(self, instructions: Iterable[au.Instruction], now: float) -> None:
        """Record the auction's records in one transaction (its other instructions are the I/O's business),
        without waiting for the disk unless one answers a user's command (USER_RECORDS)."""
        records = [item for item in instructions if isinstance(item, au.Record)]
        durable = any(isinstance(r, USER_RECORDS) for r in records)
        with self._tx("FULL" if durable else "NORMAL") as db:
            for item in records:
                self._apply(db, item, now)

    def _apply(self, db: sqlite3.Connection, ev: au.Record, now: float) -> None:
        """One record: its unit, attempt or job; and the agent it names is seen now (with its credits, if the
        record carries them). A unit done records its tile's result in the same transaction."""
        match ev:
            case au.UnitAwarded():
                self._award(db, ev.job_id, ev.index, ev.agent, ev.token, now, ev.estimate)
                self._agent(db, ev.agent, now, None)
            case au.UnitDone():
                self._result(db, ev.job_id, ev.index, ev.tile_path, ev.tile_hash, ev.report, now)
                self._finish(db, ev.token, "done", now, ev.seconds, ev.params, "")
                if not self._done(db, ev.job_id, ev.index, now):
                    raise StoreError(f"job {ev.job_id!r} unit {ev.index}: done twice")
                self._agent(db, ev.agent, now, ev.credits)
            case au.UnitFailed():
                self._finish(db, ev.token, "failed", now, None, None, ev.reason)
                self._agent(db, ev.agent, now, ev.credits)
            case au.UnitRequeued():
                self._finish(db, ev.token, "requeued", now, None, None, ev.reason)
                self._agent(db, ev.agent, now, None)
            case au.UnitRetried():  # its tile's row goes (the file is the master's to remove); a done job runs again
                db.execute("DELETE FROM results WHERE job_id = ? AND idx = ?", (ev.job_id, ev.index))
                self._set_unit(db, ev.job_id, ev.index, UnitStatus.PENDING)
                self._reopen_job(db, ev.job_id)
            case au.JobRequeued():
                self._requeue_job(db, ev.job_id, ev.units, now)
            case au.PassesOrdered():
                self._add_units(db, ev.job_id, ev.units)
            case au.JobDone():
                self._end_job(db, ev.job_id, JobStatus.DONE, now, "")
            case au.JobFailed():
                self._end_job(db, ev.job_id, JobStatus.FAILED, now, ev.reason)
            case au.JobCancelled():
                self._end_job(db, ev.job_id, JobStatus.CANCELLED, now, ev.reason)
            case au.AgentDrained() | au.AgentResumed():
                self._agent(db, ev.agent, now, None)
                db.execute("UPDATE agents SET draining = ? WHERE name = ?", (isinstance(ev, au.AgentDrained), ev.agent))
            case au.AgentJoined() | au.AgentLost() | au.AgentBack() | au.AgentBlocklisted() | au.BidRefused():
                self._agent(db, ev.agent, now, None)
            case au.PassesWithdrawn():
                self._withdraw(db, ev.job_id, ev.units)
            case au.PassesSettled():
                pass  # the master writes the verdicts beside the job's tiles; its passes still out end with the job
            case au.MessageIgnored() | au.AgentForgotten() | au.AgentSilent() | au.JobsPaused() | au.JobsResumed():
                pass  # changes nothing here (an agent's row and credits stay)
            case _:
                raise TypeError(f"the job store has no record for a {type(ev).__name__}")

    # --- statements shared by the public methods and `apply` -----------------------------------------

    def _unit(self, db: sqlite3.Connection, job_id: str, index: int) -> sqlite3.Row:
        row = db.execute("SELECT * FROM units WHERE job_id = ? AND idx = ?", (job_id, index)).fetchone()
        if row is None:
            raise StoreError(f"no unit {index} in job {job_id!r}")
        return row

    def _award(
        self, db, job_id: str, index: int, agent: str, token: str, started: float, estimate: float
    ) -> None:
        status = self._unit(db, job_id, index)["status"]
        to = unit_transition(f"job {job_id!r} unit {index}", status, UnitStatus.AWARDED)
        db.execute(
            "UPDATE units SET status = ?, attempts = attempts + 1 WHERE job_id = ? AND idx = ?",
            (to, job_id, index),
        )
        db.execute(
            "INSERT INTO attempts (job_id, idx, agent, token_sha256, started, outcome, estimate)"
            " VALUES (?, ?, ?, ?, ?, 'running', ?)",
            (job_id, index, agent, token_sha256(token), started, estimate),
        )

    def _finish(self, db, token, outcome, finished, seconds, params, reason) -> None:
        digest = token_sha256(token)
        row = db.execute("SELECT job_id, idx FROM attempts WHERE token_sha256 = ?", (digest,)).fetchone()
        if row is None:
            raise StoreError(f"no attempt with the token of sha256 {digest[:12]}...")
        db.execute(
            "UPDATE attempts SET outcome = ?, finished = ?, seconds = ?, params = ?, reason = ?"
            " WHERE token_sha256 = ?",
            (outcome, finished, seconds, None if params is None else json.dumps(params), reason, digest),
        )
        if outcome in ("failed", "requeued"):
            self._move_units(db, UnitStatus.PENDING, [UnitStatus.AWARDED], "job_id = ? AND idx = ?",
                             (row["job_id"], row["idx"]), f"job {row['job_id']!r} unit {row['idx']}, {outcome}")

    def _done(self, db: sqlite3.Connection, job_id: str, index: int, now: float) -> bool:
        if self._unit(db, job_id, index)["status"] == UnitStatus.DONE:
            return False
        if (
            db.execute("SELECT 1 FROM results WHERE job_id = ? AND idx = ?", (job_id, index)).fetchone()
            is None
        ):
            # A unit counts as done only once its tile is on disk and recorded (issue 4, job store).
            raise StoreError(
                f"job {job_id!r} unit {index}: no durable result recorded before marking it done"
            )
        self._set_unit(db, job_id, index, UnitStatus.DONE)
        return True

    def _set_unit(self, db: sqlite3.Connection, job_id: str, index: int, status: UnitStatus) -> None:
        """One unit's status changes, checked against `core.model.status.UNIT_TRANSITIONS`."""
        old = self._unit(db, job_id, index)["status"]
        to = unit_transition(f"job {job_id!r} unit {index}", old, status)
        db.execute("UPDATE units SET status = ? WHERE job_id = ? AND idx = ?", (to, job_id, index))

    def _move_units(self, db: sqlite3.Connection, status: UnitStatus, sources: Sequence[UnitStatus], where: str,
                    args: tuple[Any, ...], what: str) -> None:
        """The units matching `where` whose status is one of `sources` go to `status`; each (source, status)
        is checked against the transition table first, `what` naming the units in the error."""
        for source in sources:
            unit_transition(what, source, status)
        marks = ", ".join("?" * len(sources))
        db.execute(f"UPDATE units SET status = ? WHERE status IN ({marks}) AND {where}", (status, *sources, *args))

    def _reopen_job(self, db: sqlite3.Connection, job_id: str) -> None:
        """A job ended as done runs again (repair, a retried unit); a running job stays running. A failed or
        cancelled one runs again only when requeued (`_requeue_job`)."""
        status = self._job_status(db, job_id)
        if status in (JobStatus.FAILED, JobStatus.CANCELLED):
            raise TransitionError(f"job {job_id!r}: {status} -> running only by a requeue, not by a unit")
        if status != JobStatus.RUNNING:
            to = job_transition(f"job {job_id!r}", status, JobStatus.RUNNING)
            db.execute("UPDATE jobs SET status = ?, finished = NULL WHERE id = ?", (to, job_id))

    def _requeue_job(self, db: sqlite3.Connection, job_id: str, units: Sequence[int], now: float) -> None:
        """A failed or cancelled job runs again: its `units` (failed with it: none done) back to pending, no
        end, no error, and its failures so far forgiven."""
        to = job_transition(f"job {job_id!r}", self._job_status(db, job_id), JobStatus.RUNNING)
        for index in units:
            status = self._unit(db, job_id, index)["status"]
            if status != UnitStatus.FAILED:
                raise StoreError(f"job {job_id!r} unit {index}: {status}, not failed with its job: not requeued")
            self._set_unit(db, job_id, index, UnitStatus.PENDING)
        db.execute("UPDATE jobs SET status = ?, finished = NULL, error = '', requeued = ? WHERE id = ?",
                   (to, now, job_id))

    @staticmethod
    def _job_status(db: sqlite3.Connection, job_id: str) -> JobStatus:
        row = db.execute("SELECT status FROM jobs WHERE id = ?", (job_id,)).fetchone()
        if row is None:
            raise StoreError(f"no job {job_id!r}")
        return JobStatus(row["status"])

    def _end_job(self, db: sqlite3.Connection, job_id: str, status: JobStatus, now: float, error: str) -> None:
        """A running job ends as `status`; a job already ended stays as it ended."""
        status = job_transition(f"job {job_id!r}", JobStatus.RUNNING, status)  # an end state, or this raises
        cur = db.execute(
            "UPDATE jobs SET status = ?, finished = ?, error = ? WHERE id = ? AND status = ?",
            (status, now, error, job_id, JobStatus.RUNNING),
        )
        if cur.rowcount == 0:
            self.job(job_id)  # raises for an unknown job
            return
        # A failed or cancelled job's unfinished units; a done progressive job's passes still out.
        self._move_units(db, UnitStatus.FAILED, [UnitStatus.PENDING, UnitStatus.AWARDED], "job_id = ?",
                         (job_id,), f"unfinished units of job {job_id!r}, {status}")
        db.execute(
            "UPDATE attempts SET outcome = 'cancelled', finished = ?, reason = ?"
            " WHERE job_id = ? AND outcome = 'running'",
            (now, error or "the job's passes reached its goal", job_id),
        )

    @staticmethod
    def _withdraw(db: sqlite3.Connection, job_id: str, units: Sequence[int]) -> None:
        """A progressive job's passes called off before they landed: gone, with their attempts (a pass is
        the job's own bookkeeping, not the user's unit; what was never merged is no part of the image)."""
        marks = ", ".join("?" * len(units))
        db.execute(f"DELETE FROM attempts WHERE job_id = ? AND idx IN ({marks})", (job_id, *units))
        db.execute(f"DELETE FROM units WHERE job_id = ? AND status != ? AND idx IN ({marks})",
                   (job_id, UnitStatus.DONE, *units))

    @staticmethod
    def _add_units(db: sqlite3.Connection, job_id: str, units: Sequence[WorkUnit]) -> None:
        """A progressive job's passes, as units (pass 0 of each unit is the unit the job was created with)."""
        db.executemany(_INSERT_UNIT + " ON CONFLICT (job_id, idx) DO UPDATE SET spp = excluded.spp",
                       _unit_rows(job_id, units))

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
        JobStatus(row["status"]), row["created"], row["finished"], row["error"],
    )  # fmt: skip


def _unit_rows(job_id: str, units: Iterable[WorkUnit]) -> list[tuple[Any, ...]]:
    """`_INSERT_UNIT`'s rows: the units, pending."""
    return [(job_id, u.index, *u.rect.as_list(), u.C, u.S, u.Nd, u.cost, UnitStatus.PENDING, u.spp, u.depth_floor,
             u.depth) for u in units]
