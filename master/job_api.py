"""The master's job API over HTTP (`add_job_routes`); `quekaro submit/status/watch/result/cancel` use it.

Every route needs the farm's admin token (`Authorization: Bearer ...`):
    POST /api/jobs                 a scene bundle (tar); header X-Quekaro-Job: {"defines", "options"}
    GET  /api/jobs                 every job with its progress
    GET  /api/jobs/{job}           one job: status, progress, agents busy, ETA, error
    GET  /api/jobs/{job}/result    the composed image, EXR unless the film asks otherwise (409 until done)
    GET  /api/jobs/{job}/report    the JSON report
    GET  /api/jobs/{job}/units/{n} one unit: status, agent, attempts, and its story
    POST /api/jobs/{job}/cancel    cancel the job
    GET  /api/agents               agents the auction knows, with their records
    GET  /api/farm                 the data plane's address, and why jobs are paused if they are
"""

from __future__ import annotations

import dataclasses
import hmac
import json
import os
import tempfile
import time
from pathlib import Path
from typing import Any, Protocol

from aiohttp import web

from core.errors import QuekaroError
from core.model.job import RAW_SUFFIX, JobSpec, RenderOptions
from master import sessions
from master.auction import Auction
from master.http_guard import Refusal, bearer_token, disk_full, json_error, read_body_chunks
from master.store import JobStore, StoreError
from planning import budgets


class JobService(Protocol):
    """What the job API needs of the master (`master.service.MasterService` is it; this module does not
    import it, so that the service can mount these routes). Of the auction it reads only its read API."""

    admin_token: str
    jobs_dir: Path
    store: JobStore
    auction: Auction | None
    paused: str | None
    data_plane: str
    shared_accounts: sessions.SharedAccounts

    async def submit(self, bundle: Path, defines: dict[str, str], options: RenderOptions) -> str: ...
    async def cancel(self, job_id: str) -> bool: ...
    async def ensure_assembled(self, job_id: str) -> Path: ...
    def result_path(self, job_id: str) -> Path: ...
    def result_image(self, job_id: str) -> Path: ...

MAX_BUNDLE_BYTES = 1 << 30
SERVICE_KEY = web.AppKey("quekaro_master", object)


def add_job_routes(app: web.Application, service: JobService) -> None:
    """Mount the job API on the master's aiohttp application."""
    app[SERVICE_KEY] = service
    app.router.add_post("/api/jobs", submit)
    app.router.add_get("/api/jobs", list_jobs)
    app.router.add_get("/api/jobs/{job}", job_status)
    app.router.add_get("/api/jobs/{job}/result", job_result)
    app.router.add_get("/api/jobs/{job}/report", job_report)
    app.router.add_get("/api/jobs/{job}/raw", job_raw)
    app.router.add_get("/api/jobs/{job}/units/{unit:[0-9]{1,7}}", job_unit)
    app.router.add_post("/api/jobs/{job}/cancel", job_cancel)
    app.router.add_get("/api/agents", agents)
    app.router.add_get("/api/farm", farm)


def _service(request: web.Request) -> JobService:
    """The master, once the request's bearer token is the admin token (401 otherwise): anyone who can reach
    the port must not be able to submit or cancel jobs."""
    service = request.app[SERVICE_KEY]
    token = bearer_token(request)
    if not token or not hmac.compare_digest(token.encode(), service.admin_token.encode()):
        raise Refusal(401, "missing or wrong admin token")
    return service


async def _receive_to_file(request: web.Request, folder: Path, limit: int) -> Path:
    """Stream the body to a new file in `folder`, a MiB at a time (never the whole upload in memory)."""
    if request.content_length is not None and request.content_length > limit:
        raise web.HTTPRequestEntityTooLarge(max_size=limit, actual_size=request.content_length)
    folder.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=".upload-", suffix=".tar", dir=folder)
    path, size = Path(name), 0
    try:
        with os.fdopen(fd, "wb") as out:
            async for chunk in read_body_chunks(request):
                size += len(chunk)
                if size > limit:
                    raise web.HTTPRequestEntityTooLarge(max_size=limit, actual_size=size)
                out.write(chunk)
    except BaseException:
        path.unlink(missing_ok=True)
        raise
    return path


async def submit(request: web.Request) -> web.Response:
    """POST /api/jobs: the body is the scene bundle (tar), the header X-Quekaro-Job its `JobSpec`
    ({"defines", "options"}); 201 with the new job's id."""
    service = _service(request)
    try:
        spec = JobSpec.from_dict(json.loads(request.headers.get("X-Quekaro-Job", "{}")))
    except (ValueError, TypeError, AttributeError, RecursionError) as exc:
        return json_error(400, f"header X-Quekaro-Job: {exc}")
    except QuekaroError as exc:
        return json_error(400, str(exc))
    bundle = await _receive_to_file(request, service.jobs_dir, MAX_BUNDLE_BYTES)
    try:
        job_id = await service.submit(bundle, spec.defines, spec.options)
    except QuekaroError as exc:
        return json_error(422, str(exc))
    finally:
        bundle.unlink(missing_ok=True)
    return web.json_response({"job_id": job_id}, status=201)


def job_summary(service: JobService, job_id: str) -> dict[str, Any]:
    """Status and progress of one job, as the CLI shows it. A progressive job's units are its image's (done:
    their goal met), its passes apart (`passes`: done, ordered, mean spp so far, goal; None for a job not
    in passes); `eta_at_least`: the ETA counts only the passes ordered so far."""
    record = service.store.job(job_id)
    shares = record.plan.get("shares") or None
    progress = service.store.progress(job_id, time.time())  # the store's times are wall-clock
    passes = progress.passes
    return {
        "job_id": record.id, "scene": record.scene, "status": record.status, "error": record.error,
        "created": record.created, "finished": record.finished, "level": record.plan["options"]["level"],
        "units_done": progress.done, "units_total": progress.total, "units_failed": progress.failed,
        "agents_busy": progress.agents_busy, "eta_s": progress.eta_s, "eta_at_least": progress.eta_at_least,
        "passes": None if passes is None else dataclasses.asdict(passes),
        "attempts_retried": progress.retried, "last_retry": progress.last_retry,
        "result_ready": service.result_path(job_id).with_suffix(".json").exists(),
        "effects": record.plan.get("effects", {}), "adaptive": shares,
        "adaptive_text": budgets.describe(shares) if shares else None,
        "paused": service.paused if record.status == "running" else None,
    }


def unit_story(service: JobService, job_id: str, index: int) -> list[dict[str, Any]]:
    """The unit's changes of status since the master started, each with the stimulus that made it and its
    auction time (wall time less any pause): empty for a unit of a job the running master did not auction."""
    story = service.auction.story(job_id, index) if service.auction else []
    return [{"stimulus_id": t.stimulus_id, "start": t.start, "finish": t.finish, "at": round(t.at, 3)}
            for t in story]


def unit_summary(service: JobService, job_id: str, index: int) -> dict[str, Any]:
    """One unit as `quekaro status JOB --unit N` shows it; KeyError for a unit the job does not have."""
    units = [u for u in service.store.units(job_id) if u.index == index]
    if not units:
        raise KeyError(f"job {job_id} has no unit {index}")
    attempts = service.store.attempts(job_id, index)
    return {"job_id": job_id, "index": index, "status": str(units[0].status),
            "agent": next((a.agent for a in attempts if a.outcome == "running"), None),
            "attempts": [{"agent": a.agent, "started": a.started, "finished": a.finished, "outcome": a.outcome,
                          "seconds": a.seconds, "reason": a.reason} for a in attempts],
            "story": unit_story(service, job_id, index)}


async def job_unit(request: web.Request) -> web.Response:
    """One unit: status, agent, attempts, and its story (the stimuli that moved it: `unit_story`)."""
    service = _service(request)
    try:
        return web.json_response(unit_summary(service, request.match_info["job"], int(request.match_info["unit"])))
    except (StoreError, KeyError) as exc:
        return json_error(404, str(exc).strip("'\""))


async def list_jobs(request: web.Request) -> web.Response:
    service = _service(request)
    return web.json_response({"jobs": [job_summary(service, r.id) for r in service.store.list_jobs()]})


async def job_status(request: web.Request) -> web.Response:
    service = _service(request)
    try:
        return web.json_response(job_summary(service, request.match_info["job"]))
    except StoreError as exc:
        return json_error(404, str(exc))


async def _finished_result(request: web.Request) -> tuple[JobService, str] | web.Response:
    service = _service(request)
    job_id = request.match_info["job"]
    try:
        record = service.store.job(job_id)
    except StoreError as exc:
        return json_error(404, str(exc))
    if record.status != "done":
        return json_error(409, f"job {job_id} is {record.status}" + (f": {record.error}" if record.error else ""))
    try:
        await service.ensure_assembled(job_id)
    except Exception as exc:
        if disk_full(exc):
            raise Refusal(507, "disk full on the master: the job's image is composed once space is freed; "
                               "ask again then") from exc
        raise
    return service, job_id


async def job_result(request: web.Request) -> web.StreamResponse:
    """The composed image (`result_image`), 409 until the job is done."""
    found = await _finished_result(request)
    if isinstance(found, web.Response):
        return found
    service, job_id = found
    image = service.result_image(job_id)
    return web.FileResponse(image, headers={"Content-Disposition": f'attachment; filename="{job_id}{image.suffix}"'})


async def job_report(request: web.Request) -> web.StreamResponse:
    found = await _finished_result(request)
    if isinstance(found, web.Response):
        return found
    service, job_id = found
    return web.FileResponse(service.result_path(job_id).with_suffix(".json"))


async def job_raw(request: web.Request) -> web.StreamResponse:
    """A denoised job's raw image with the denoiser's AOVs (result.raw.exr); 404 for a job not denoised."""
    found = await _finished_result(request)
    if isinstance(found, web.Response):
        return found
    service, job_id = found
    raw = service.result_path(job_id).with_suffix(RAW_SUFFIX)
    if not raw.exists():
        return json_error(404, f"job {job_id} was not denoised: its image is the raw one")
    return web.FileResponse(raw, headers={"Content-Disposition": f'attachment; filename="{job_id}{RAW_SUFFIX}"'})


async def job_cancel(request: web.Request) -> web.Response:
    service = _service(request)
    job_id = request.match_info["job"]
    try:
        cancelled = await service.cancel(job_id)
    except StoreError as exc:
        return json_error(404, str(exc))
    return web.json_response({"job_id": job_id, "cancelled": cancelled})


async def farm(request: web.Request) -> web.Response:
    service = _service(request)
    return web.json_response({"data_plane": service.data_plane, "paused": service.paused})


async def agents(request: web.Request) -> web.Response:
    """Every agent the master knows (`agent_rows`)."""
    return web.json_response({"agents": agent_rows(_service(request))})


def agent_rows(service: JobService, counts: dict[str, tuple[int, int]] | None = None) -> list[dict[str, Any]]:
    """Every agent the master knows: its state (lost, rendering, idle), speed, credits, the units it holds,
    units done and failed (`counts`: the store's `agent_counts`, read if not given), and seconds since it
    was last heard from, and `shared`, what the master says if several clients log in with its JID (the
    web page shows the same rows)."""
    counts = service.store.agent_counts() if counts is None else counts
    rows = []
    for agent in (service.auction.agent_views(time.time()) if service.auction else ()):
        done, failed = counts.get(agent.name, (0, 0))
        state = "lost" if agent.lost else "rendering" if agent.holding else "idle"
        rows.append({"jid": agent.name, "state": state, "lost": agent.lost, "credits": agent.credits,
                     "speed": agent.speed, "holding": list(agent.holding), "units_done": done,
                     "units_failed": failed, "last_seen_s": agent.heard_s_ago,
                     "blocklisted_for": list(agent.blocklisted_for), "shared": _shared(service, agent.name)})
    return rows


def _shared(service: JobService, jid: str) -> str | None:
    clients = service.shared_accounts.sharing(jid, time.monotonic())
    return sessions.note(jid, clients) if clients else None
