"""The master's job API over HTTP (`add_job_routes`); `quekaro submit/status/watch/result/cancel/requeue` use it.

Every route needs the farm's admin token (`Authorization: Bearer ...`):
    POST /api/jobs                 a scene bundle (tar); header X-Quekaro-Job: a `JobSpec`; one with `frames`
                                   becomes one job per frame, sharing a sequence id (`seq-...`)
    GET  /api/jobs[?sequence=SEQ]  every job (or a sequence's, in frame order) with its progress
    GET  /api/jobs/{job}           one job: status, progress, agents busy, ETA, error; a sequence id: its frames
    GET  /api/jobs/{job}/result    the composed image, EXR unless the film asks otherwise (409 until done);
                                   ?partial=1: the tiles so far of a job running, failed or cancelled
                                   (SCENE.partial.exr), composed again as tiles land
    GET  /api/jobs/{job}/report    the JSON report (?partial=1: the partial image's, as last composed)
    GET  /api/jobs/{job}/units/{n} one unit: status, agent, attempts, and its story
    POST /api/jobs/{job}/cancel    cancel the job (a sequence id: every frame)
    POST /api/jobs/{job}/requeue   a failed or cancelled job runs again, its done units kept (a sequence id:
                                   every failed or cancelled frame); 409 with the reason where it will not
    GET  /api/agents               agents the auction knows, with their records
    GET  /api/farm                 the data plane's address, and why jobs are paused if they are
Downloads are named as `quekaro result` names them (`download_name`): SCENE.exr, a frame's SCENE_0001.exr.
"""

from __future__ import annotations

import dataclasses
import hmac
import json
import os
import secrets
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any, Protocol

from aiohttp import web

from core.errors import QuekaroError
from core.model.frames import SEQUENCE_ID, frame_name
from core.model.job import RAW_SUFFIX, JobSpec
from master import sessions
from master.auction import Auction
from master.http_guard import Refusal, bearer_token, disk_full, json_error, read_body_chunks
from master.pass_merge import read_verdicts
from master.store import JobRecord, JobStore, StoreError
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

    async def submit(self, bundle: Path, spec: JobSpec) -> str: ...
    async def cancel(self, job_id: str) -> bool: ...
    async def requeue(self, job_id: str) -> str | None: ...
    async def ensure_assembled(self, job_id: str) -> Path: ...
    async def ensure_partial(self, job_id: str, follow_tiles: bool = True) -> Path: ...
    def job_dir(self, job_id: str) -> Path: ...
    def result_path(self, job_id: str) -> Path: ...
    def result_image(self, job_id: str, partial: bool = False) -> Path: ...
    def partial_path(self, job_id: str) -> Path: ...

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
    app.router.add_post("/api/jobs/{job}/requeue", job_requeue)
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
    """POST /api/jobs: the body is the scene bundle (tar), the header X-Quekaro-Job its `JobSpec`; 201 with
    the new job's id (and its name), or for a frame range the sequence's id and each frame's job."""
    service = _service(request)
    try:
        spec = JobSpec.from_dict(json.loads(request.headers.get("X-Quekaro-Job", "{}")))
    except (ValueError, TypeError, AttributeError, RecursionError) as exc:
        return json_error(400, f"header X-Quekaro-Job: {exc}")
    except QuekaroError as exc:
        return json_error(400, str(exc))
    bundle = await _receive_to_file(request, service.jobs_dir, MAX_BUNDLE_BYTES)
    try:
        if spec.frames is not None:
            sequence, jobs = await _submit_frames(service, bundle, spec)
            return web.json_response({"job_id": sequence, "sequence": sequence, "jobs": jobs}, status=201)
        job_id = await service.submit(bundle, spec)
    except QuekaroError as exc:
        return json_error(422, str(exc))
    finally:
        bundle.unlink(missing_ok=True)
    return web.json_response({"job_id": job_id, **({"name": spec.name} if spec.name else {})}, status=201)


async def _submit_frames(service: JobService, bundle: Path, spec: JobSpec) -> tuple[str, list[dict[str, Any]]]:
    """One job per frame of `spec.frames`, all of one new sequence, each with its own link to the bundle
    (received once). A frame refused cancels the frames submitted before it: a sequence is whole or absent."""
    assert spec.frames is not None
    sequence, jobs = f"seq-{secrets.token_hex(6)}", []
    for frame in spec.frames.frames():
        try:
            job_id = await service.submit(_linked(bundle), spec.frame_job(sequence, frame))
        except QuekaroError as exc:
            for job in jobs:
                await service.cancel(job["job_id"])
            raise QuekaroError(f"-D {spec.frames.define}={frame} (frame {frame} of the sequence): {exc}") from exc
        jobs.append({"frame": frame, "job_id": job_id})
    return sequence, jobs


def _linked(bundle: Path) -> Path:
    """Another name for the received bundle beside it (a hard link; a copy where links are refused): each
    frame's job takes its own."""
    fd, name = tempfile.mkstemp(prefix=".frame-", suffix=".tar", dir=bundle.parent)
    os.close(fd)
    os.unlink(name)
    try:
        os.link(bundle, name)
    except OSError:
        shutil.copyfile(bundle, name)
    return Path(name)


def download_name(record: JobRecord, suffix: str) -> str:
    """What a job's file is called where it lands: its scene's stem, a frame's numbered (cbox_0001.exr)."""
    stem = Path(record.scene).stem
    return (stem if record.spec.frame is None else frame_name(stem, record.spec.frame)) + suffix


def attachment(record: JobRecord, suffix: str) -> dict[str, str]:
    """The Content-Disposition header that names a download as `download_name` does."""
    return {"Content-Disposition": f'attachment; filename="{download_name(record, suffix)}"'}


def job_summary(service: JobService, job_id: str) -> dict[str, Any]:
    """Status and progress of one job, as the CLI shows it. A progressive job's units are its image's (done:
    their goal met), its passes apart (`passes`: done, ordered, mean spp so far, goal; None for a job not
    in passes; `stopped`: why its passes ended, once they have); `eta_at_least`: the ETA counts only the
    passes ordered so far."""
    record = service.store.job(job_id)
    shares = record.plan.get("shares") or None
    progress = service.store.progress(job_id, time.time())  # the store's times are wall-clock
    passes = progress.passes
    return {
        "job_id": record.id, "scene": record.scene, "status": record.status, "error": record.error,
        "name": record.spec.name, "sequence": record.spec.sequence, "frame": record.spec.frame,
        "spp": record.plan.get("spp"), "resolution": [record.plan.get("width"), record.plan.get("height")],
        "defines": dict(record.spec.defines),
        "created": record.created, "finished": record.finished, "level": record.plan["options"]["level"],
        "units_done": progress.done, "units_total": progress.total, "units_failed": progress.failed,
        "agents_busy": progress.agents_busy, "eta_s": progress.eta_s, "eta_at_least": progress.eta_at_least,
        "passes": None if passes is None else {**dataclasses.asdict(passes),
                                               "stopped": read_verdicts(service.job_dir(job_id))[0]},
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
    """Every job, or with `?sequence=SEQ` that sequence's, in frame order."""
    service = _service(request)
    sequence = request.query.get("sequence")
    records = service.store.list_jobs() if sequence is None else service.store.sequence(sequence)
    return web.json_response({"jobs": [job_summary(service, r.id) for r in records]})


def sequence_status(frames: list[dict[str, Any]]) -> str:
    """A sequence's status from its frames': running while one runs, failed if one failed, done when all are,
    else cancelled."""
    statuses = {f["status"] for f in frames}
    for status in ("running", "failed", "done"):
        if status in statuses and (status != "done" or statuses == {"done"}):
            return status
    return "cancelled"


def sequence_summary(service: JobService, sequence: str) -> dict[str, Any]:
    """A sequence and its frames' summaries (StoreError for a sequence the store has no job of)."""
    records = service.store.sequence(sequence)
    if not records:
        raise StoreError(f"no sequence {sequence!r}")
    frames = [job_summary(service, r.id) for r in records]
    return {"sequence": sequence, "name": records[0].spec.name, "scene": records[0].scene,
            "status": sequence_status(frames), "agents_busy": service.store.agents_busy([r.id for r in records]),
            "frames": frames}


async def job_status(request: web.Request) -> web.Response:
    """One job's summary, or a sequence's (`sequence_summary`)."""
    service = _service(request)
    job_id = request.match_info["job"]
    try:
        if SEQUENCE_ID.fullmatch(job_id):
            return web.json_response(sequence_summary(service, job_id))
        return web.json_response(job_summary(service, job_id))
    except StoreError as exc:
        return json_error(404, str(exc))


async def _served_result(request: web.Request, kind: str) -> tuple[JobService, JobRecord] | web.Response:
    """The job whose file of `kind` is asked for, its image composed; or the error response. A running job's
    partial image is composed again for its image, not for its report (it describes the image fetched)."""
    service = _service(request)
    job_id = request.match_info["job"]
    if SEQUENCE_ID.fullmatch(job_id):
        return json_error(400, f"{job_id} is a sequence: each frame's image is fetched by its job id "
                               f"(GET /api/jobs?sequence={job_id} lists them)")
    try:
        record = service.store.job(job_id)
    except StoreError as exc:
        return json_error(404, str(exc))
    if record.status != "done" and not _partial(request):
        return json_error(409, f"job {job_id} is {record.status}" + (f": {record.error}" if record.error else "")
                          + "; ?partial=1 gives its tiles so far")
    try:
        await (service.ensure_assembled(job_id) if record.status == "done"
               else service.ensure_partial(job_id, follow_tiles=kind == "image"))
    except Exception as exc:
        if disk_full(exc):
            raise Refusal(507, "disk full on the master: the job's image is composed once space is freed; "
                               "ask again then") from exc
        if isinstance(exc, QuekaroError) and record.status != "done":  # no tile yet; done or requeued meanwhile
            return json_error(409, str(exc))
        raise
    return service, record


async def job_result(request: web.Request) -> web.StreamResponse:
    """The composed image (`result_image`), 409 until the job is done unless ?partial=1."""
    return await _served_file(request, "image")


async def job_report(request: web.Request) -> web.StreamResponse:
    return await _served_file(request, "report")


async def job_raw(request: web.Request) -> web.StreamResponse:
    """A denoised job's raw image with the denoiser's AOVs (result.raw.exr); 404 for a job not denoised."""
    return await _served_file(request, "raw")


def result_file(service: JobService, job_id: str, kind: str, partial: bool = False) -> Path:
    """A done job's file of `kind`: its composed image, raw image, JSON report or PNG; `partial`: those of
    the tiles so far of a job running or ended without finishing (`ensure_partial`; it has no raw image)."""
    if kind == "image":
        return service.result_image(job_id, partial)
    stem = service.partial_path(job_id) if partial else service.result_path(job_id)
    return stem.with_suffix({"raw": RAW_SUFFIX, "report": ".json", "png": ".png"}[kind])


async def _served_file(request: web.Request, kind: str) -> web.StreamResponse:
    """A done job's file of `kind` (`result_file`), named as `download_name` names it; with ?partial=1 one
    of a job not done: SCENE.partial.exr."""
    found = await _served_result(request, kind)
    if isinstance(found, web.Response):
        return found
    service, record = found
    partial = record.status != "done"  # _served_result lets it through only where ?partial=1 asks
    path = result_file(service, record.id, kind, partial)
    if not path.exists():
        why = ("was not denoised: its image is the raw one" if not partial else "did not finish: its partial image "
               "is not denoised") if kind == "raw" else f"has no {path.name}"
        return json_error(404, f"job {record.id} {why}")
    suffix = RAW_SUFFIX if kind == "raw" else path.suffix
    return web.FileResponse(path, headers=attachment(record, (".partial" if partial else "") + suffix))


def _partial(request: web.Request) -> bool:
    """The query's `partial` (0 or 1): whether a job not done may give its tiles so far."""
    value = request.query.get("partial", "0")
    if value not in ("0", "1"):
        raise Refusal(400, f"partial: {value[:20]!r} is not 0 or 1")
    return value == "1"


async def cancel_jobs(service: JobService, job_id: str) -> dict[str, Any]:
    """Cancel a job, or every frame of a sequence (StoreError for neither): whether any was running."""
    if SEQUENCE_ID.fullmatch(job_id):
        records = service.store.sequence(job_id)
        if not records:
            raise StoreError(f"no sequence {job_id!r}")
        cancelled = [r.id for r in records if await service.cancel(r.id)]
        return {"job_id": job_id, "sequence": job_id, "cancelled": bool(cancelled), "frames_cancelled": cancelled}
    return {"job_id": job_id, "cancelled": await service.cancel(job_id)}


async def job_cancel(request: web.Request) -> web.Response:
    service = _service(request)
    try:
        return web.json_response(await cancel_jobs(service, request.match_info["job"]))
    except StoreError as exc:
        return json_error(404, str(exc))


class RequeueRefused(QuekaroError):
    """A requeue the master will not make: the auction's reason (a running or done job, ...)."""


async def requeue_jobs(service: JobService, job_id: str) -> dict[str, Any]:
    """Run a failed or cancelled job again, or every failed or cancelled frame of a sequence (StoreError for
    neither; RequeueRefused, saying why, where nothing runs again)."""
    if not SEQUENCE_ID.fullmatch(job_id):
        refused = await service.requeue(job_id)
        if refused:
            raise RequeueRefused(f"job {job_id}: {refused}")
        return {"job_id": job_id, "requeued": [job_id]}
    records = service.store.sequence(job_id)
    if not records:
        raise StoreError(f"no sequence {job_id!r}")
    ended = [r.id for r in records if r.status in ("failed", "cancelled")]
    if not ended:
        raise RequeueRefused(f"sequence {job_id}: no frame of it failed or was cancelled")
    refusals = {frame: await service.requeue(frame) for frame in ended}
    requeued = [frame for frame, refused in refusals.items() if not refused]
    if not requeued:
        raise RequeueRefused(f"sequence {job_id}: " + "; ".join(f"job {f}: {r}" for f, r in refusals.items()))
    return {"job_id": job_id, "sequence": job_id, "requeued": requeued,
            "refused": {frame: refused for frame, refused in refusals.items() if refused}}


async def job_requeue(request: web.Request) -> web.Response:
    service = _service(request)
    try:
        return web.json_response(await requeue_jobs(service, request.match_info["job"]))
    except StoreError as exc:
        return json_error(404, str(exc))
    except RequeueRefused as exc:
        return json_error(409, str(exc))


async def farm(request: web.Request) -> web.Response:
    service = _service(request)
    return web.json_response({"data_plane": service.data_plane, "paused": service.paused})


async def agents(request: web.Request) -> web.Response:
    """Every agent the master knows (`agent_rows`)."""
    return web.json_response({"agents": agent_rows(_service(request))})


def agent_rows(service: JobService, counts: dict[str, tuple[int, int]] | None = None) -> list[dict[str, Any]]:
    """Every agent the master knows: its state (lost, draining, rendering, idle), its speed (seconds of the
    reference render it does per second: 2.0 renders twice as fast as the reference machine), its render
    threads, its credits (units done within 10 % of their estimate less those late or failed: what breaks
    ties between equal bids), the units it holds, units done and failed (`counts`: the store's
    `agent_counts`, read if not given), and seconds since it was last heard from, and `shared`, what the
    master says if several clients log in with its JID (the web page shows the same rows)."""
    counts = service.store.agent_counts() if counts is None else counts
    rows = []
    for agent in (service.auction.agent_views(time.time()) if service.auction else ()):
        done, failed = counts.get(agent.name, (0, 0))
        state = "lost" if agent.lost else "draining" if agent.draining else "rendering" if agent.holding else "idle"
        rows.append({"jid": agent.name, "state": state, "lost": agent.lost, "credits": agent.credits,
                     "draining": agent.draining, "threads": agent.threads, "host": agent.host,
                     "speed": agent.speed, "holding": list(agent.holding), "units_done": done,
                     "units_failed": failed, "last_seen_s": agent.heard_s_ago,
                     "blocklisted_for": list(agent.blocklisted_for), "shared": _shared(service, agent.name)})
    return rows


def _shared(service: JobService, jid: str) -> str | None:
    clients = service.shared_accounts.sharing(jid, time.monotonic())
    return sessions.note(jid, clients) if clients else None
