"""What the web page shows, as plain dicts read from the job store and the auction (no HTTP here).

- `jobs_view`: every job with its state, level, progress, ETA, times and effect decisions (the job API's
  `job_summary`, plus the options and image size the page shows, and whether a denoised job's AOV pass
  is rendered yet: `aov_pass`);
- `job_view`: one job and its units, each with its rectangle, features (C, S, Nd), state (a unit its
  cancelled job left unrendered reads cancelled), the agent holding or having rendered it, and the
  parameters the rules chose (spp, depth, band, Rl/Ls/Ibs); a progressive job's units are its image's,
  each with its passes together; a sequence id: the sequence and its frames;
- `unit_view`: one unit's attempts (agent, times, outcome) beside the same;
- `agents_view`: the job API's agent rows, with a local farm's restarting processes and blocklists;
- `report_view`: a finished job's report, without its per-unit list (the units are on the page already).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Protocol

from core.home import read_processes
from core.model.frames import SEQUENCE_ID
from core.model.status import JobStatus
from master.auction import pass_origin
from master.job_api import JobService, agent_rows, job_summary, sequence_summary, unit_story
from master.store import JobRecord, UnitRecord
from planning.pipeline import AOV_PASS_FILE
from planning.progressive import describe, report_part

ACCURACY_NOTE = ("The farm keeps no per-job accuracy report yet (no reference render is made for a job; "
                 "`quekaro bench accuracy` measures levels against references): shown is what the job's "
                 "report has.")


class WebService(JobService, Protocol):
    """What the page needs of the master beyond the job API: its home and each job's folder."""

    home: Path

    def job_dir(self, job_id: str) -> Path: ...
    async def retry_unit(self, job_id: str, index: int) -> str | None: ...
    async def drain(self, agent: str, drain: bool) -> str | None: ...
    async def delete_job(self, job_id: str) -> None: ...


def _round(value: float | None, digits: int = 4) -> float | None:
    return None if value is None else round(float(value), digits)


def aov_pass_path(service: WebService, record: JobRecord) -> Path | None:
    """Where a denoised job's AOV pass is kept (master.service renders it once); None for a job not denoised."""
    return service.job_dir(record.id) / AOV_PASS_FILE if record.spec.options.denoise else None


def job_row(service: WebService, record: JobRecord, now: float) -> dict[str, Any]:
    """One job as the jobs table shows it."""
    row = job_summary(service, record.id)
    options = record.spec.options
    end = record.finished if record.finished is not None else now
    row.update({
        "width": record.plan.get("width"), "height": record.plan.get("height"), "depth": record.plan.get("depth"),
        "options": {"spp": options.spp, "depth": options.depth, "units": options.units,
                    "integrator": options.integrator, "variant": options.variant,
                    "defuzzifier": options.defuzzifier, "sensor": options.sensor,
                    "rules": options.rules.name if options.rules else None, "denoise": options.denoise},
        "aov_pass": None if (aov := aov_pass_path(service, record)) is None else aov.is_file(),
        "elapsed_s": round(max(0.0, end - record.created), 1),
    })
    return row


def jobs_view(service: WebService) -> list[dict[str, Any]]:
    """Every job, newest first."""
    now = time.time()
    return [job_row(service, r, now) for r in reversed(service.store.list_jobs())]


def _unit_row(unit: UnitRecord, params: dict[str, Any] | None, agent: str | None,
              job_status: JobStatus) -> dict[str, Any]:
    """A unit as the page shows it: the store's "failed" of a unit its cancelled job left unrendered reads
    "cancelled" (the store's word says only that the job ended without it)."""
    params = params or {}
    outputs = params.get("outputs") or {}
    status = "cancelled" if job_status == JobStatus.CANCELLED and unit.status == "failed" else str(unit.status)
    return {"index": unit.index, "rect": unit.rect.as_list(), "C": _round(unit.C, 6), "S": int(unit.S),
            "Nd": _round(unit.Nd, 6), "cost": _round(unit.cost), "status": status,
            "attempts": unit.attempts, "agent": agent or params.get("agent"),
            "spp": params.get("spp"), "depth": params.get("depth"), "band": params.get("band"),
            "seconds": _round(params.get("seconds"), 3),
            "outputs": {k: _round(v) for k, v in outputs.items() if isinstance(v, int | float)}}


def job_view(service: WebService, job_id: str) -> dict[str, Any]:
    """One job and every unit of it, or a sequence and its frames' rows (raises StoreError for neither).
    `partial`: a job not done has tiles, its partial image shows them alone."""
    if SEQUENCE_ID.fullmatch(job_id):
        now = time.time()
        summary = sequence_summary(service, job_id)
        frames = [job_row(service, service.store.job(f["job_id"]), now) for f in summary["frames"]]
        return {**summary, "job_id": job_id, "frames": frames,
                "frames_done": sum(f["status"] == "done" for f in frames)}
    record = service.store.job(job_id)
    params = {r.index: r.params for r in service.store.results(job_id)}
    holding = {a.index: a.agent for a in service.store.attempts(job_id) if a.outcome == "running"}
    rows = [_unit_row(u, params.get(u.index), holding.get(u.index), record.status)
            for u in service.store.units(job_id)]
    planned = record.planned_units
    units = rows if planned is None else [_unit_of_passes(u, passes) for u, passes in _by_unit(rows, len(planned))]
    return {**job_row(service, record, time.time()), "ranges": record.plan.get("ranges", {}),
            "tiles": len(params), "partial": record.status != JobStatus.DONE and bool(params), "units": units}


def _by_unit(rows: list[dict[str, Any]], units: int) -> list[tuple[int, list[dict[str, Any]]]]:
    """A progressive job's rows (its passes) grouped by unit."""
    grouped: dict[int, list[dict[str, Any]]] = {}
    for row in rows:
        grouped.setdefault(pass_origin(row["index"], units)[0], []).append(row)
    return sorted(grouped.items())


# A unit of passes reads as its most active pass: one rendering makes it rendering, then one waiting.
_PASS_STATES = ("awarded", "pending", "done", "cancelled", "failed")


def _unit_of_passes(unit: int, passes: list[dict[str, Any]]) -> dict[str, Any]:
    """A progressive job's unit as the page shows it, from its passes' rows: the samples, seconds and
    attempts of them all, the agents holding or having rendered them, and how many are done."""
    done = [p for p in passes if p["status"] == "done"]
    first = done[0] if done else passes[0]
    agents = sorted({p["agent"] for p in passes if p["agent"] and p["status"] in ("awarded", "done")})
    return {**first, "index": unit, "status": min((p["status"] for p in passes), key=_PASS_STATES.index),
            "attempts": sum(p["attempts"] for p in passes), "agent": ", ".join(agents) or None,
            "spp": sum(p["spp"] or 0 for p in done) or None, "passes": len(done),
            "seconds": _round(sum(p["seconds"] or 0.0 for p in done), 3) if done else None}


def unit_view(service: WebService, job_id: str, index: int) -> dict[str, Any]:
    """One unit: its row, and every attempt at it (agent, started, finished, outcome, seconds, reason); a
    progressive job's unit: its passes together, each attempt naming its pass."""
    record = service.store.job(job_id)
    n = len(record.planned_units) if record.planned_units is not None else None
    rows = [u for u in service.store.units(job_id) if (pass_origin(u.index, n)[0] if n else u.index) == index]
    if not rows:
        raise KeyError(f"job {job_id!r} has no unit {index}")
    results = {r.index: r.params for r in service.store.results(job_id)}
    indices = {u.index for u in rows}
    attempts = sorted((a for a in service.store.attempts(job_id) if a.index in indices), key=lambda a: a.started)
    holding = {a.index: a.agent for a in attempts if a.outcome == "running"}
    shown = [_unit_row(u, results.get(u.index), holding.get(u.index), record.status) for u in rows]
    rendered = results.get(next((u.index for u in rows if u.index in results), rows[0].index)) or {}
    # C and Nd unrounded: the rules are evaluated on them (the job view rounds them for the partition)
    return {**(_unit_of_passes(index, shown) if n else shown[0]), "C": rows[0].C, "Nd": rows[0].Nd,
            "job_id": job_id, "agent_rules": rendered.get("rules"),
            "story": unit_story(service, job_id, rows[-1].index),
            "attempt_list": [{"agent": a.agent, "started": a.started, "finished": a.finished,
                              "outcome": a.outcome, "estimate_s": _round(a.estimate, 2),
                              "seconds": _round(a.seconds, 3), "reason": a.reason,
                              **({"pass": pass_origin(a.index, n)[1]} if n else {})} for a in attempts]}


def _process_states(home: Path) -> dict[str, dict[str, Any]]:
    """A local farm's processes by name (core.home.read_processes; none for a farm run by hand)."""
    return {str(p.get("name")): p for p in read_processes(home)}


def agents_view(service: WebService, counts: dict[str, tuple[int, int]] | None = None) -> list[dict[str, Any]]:
    """The job API's agent rows; state is restarting (the supervisor's word), lost, blocklisted (for a
    running job), rendering or idle; `heard_at` is the wall-clock time of the last message. `counts` are
    the store's units done and failed per agent (read if not given)."""
    processes = _process_states(service.home)
    now = time.time()
    rows = agent_rows(service, counts)
    for row in rows:
        name = row["jid"].split("@", 1)[0].rsplit("-", 1)[0]  # agent-0-a1b2c3@host -> agent-0
        process = processes.get(name, {})
        row["restarts"] = int(process.get("restarts", 0) or 0)
        row["heard_at"] = round(now - row["last_seen_s"], 1)
        if process.get("state", "running") != "running":
            row["state"] = str(process["state"])  # restarting, or failed for good
        elif not row["lost"] and row["blocklisted_for"]:
            row["state"] = "blocklisted"
    return rows


def report_view(service: WebService, job_id: str) -> dict[str, Any]:
    """A finished job's report (its totals, composition, pre-pass, effects; a job in passes: its goal and
    why it stopped), or why there is none yet."""
    record = service.store.job(job_id)
    path = service.result_path(job_id).with_suffix(".json")
    if record.status != JobStatus.DONE or not path.is_file():
        return {"job_id": job_id, "available": False, "status": str(record.status),
                "accuracy": None, "accuracy_note": ACCURACY_NOTE}
    report = json.loads(path.read_text())
    keep = ("totals", "compose", "prepass", "effects", "user", "options", "image", "created", "finished")
    progressive = report_part(report)
    return {"job_id": job_id, "available": True, **{k: report.get(k) for k in keep},
            "passes": describe(progressive) if progressive else None,
            "accuracy": report.get("accuracy"), "accuracy_note": None if report.get("accuracy") else ACCURACY_NOTE}
