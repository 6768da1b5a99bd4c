"""The web page's routes on the master's aiohttp application (`add_web_routes`; the job API's address and port).

    GET  /, /ui                             -> /ui/
    GET  /ui/                               the page (a session), else -> /ui/login
    GET  /ui/login, POST /ui/login          the login form; POST the admin token to open a session
    POST /ui/logout                         ends the session (CSRF)
    GET  /ui/static/...                     the page's CSS and JavaScript (no session)
    GET  /ui/api/jobs[/{job}]               jobs table; one job with its units (a sequence id: its frames)
    GET  /ui/api/jobs/{job}/units/{unit}    one unit: attempts, the rules that fired, its lines of the log
    GET  /ui/api/jobs/{job}/preview.png     the image so far
    GET  /ui/api/jobs/{job}/report          a finished job's report
    GET  /ui/api/jobs/{job}/download/{kind} image (EXR), png, report (JSON) or raw (EXR), named as the CLI
                                            names them; of a job not done: its partial image's
    POST /ui/api/jobs/{job}/cancel          (CSRF; a sequence id: every frame)
    POST /ui/api/jobs/{job}/requeue         a failed or cancelled job runs again (CSRF; a sequence id: every
                                            failed or cancelled frame)
    POST /ui/api/jobs/{job}/resubmit        the job again (CSRF); a JSON body {"denoise": bool} may turn
                                            its denoising on or off
    POST /ui/api/jobs/{job}/units/{unit}/retry  a done unit rendered again (CSRF)
    POST /ui/api/jobs/{job}/delete          an ended job's files and rows (CSRF)
    GET  /ui/api/agents                     agents table
    POST /ui/api/agents/drain               {"agent": JID, "drain": bool}: drain or resume it (CSRF)
    GET  /ui/api/logs[/{name}][?lines=N]    the farm's process logs; one log's last lines
    GET  /ui/events[?job=ID]                server-sent events (master.web.events)
"""

from __future__ import annotations

import asyncio
import dataclasses
import html
import json
import logging
import secrets
import shutil
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

from aiohttp import web

from core.errors import QuekaroError
from core.model.geometry import DEFAULT_FILTER_RADIUS, filter_reach
from core.model.job import RGB, JobSpec
from core.model.status import JobStatus
from master.http_guard import JOB_PART, UNIT_PART
from master.job_api import RequeueRefused, attachment, cancel_jobs, requeue_jobs, result_file
from master.store import JobRecord, StoreError
from master.web import auth, logs
from master.web.events import Watcher, stream
from master.web.preview import Previews, shrink_factor
from master.web.rules import fired_rules, planner_for
from master.web.views import WebService, agents_view, aov_pass_path, job_view, jobs_view, report_view, unit_view

log = logging.getLogger(__name__)

STATIC = Path(str(resources.files("master.web") / "static"))
FAILED_LOGIN_DELAY_S = 0.3  # a wrong token waits a little: guessing stays slow (the token has 192 bits anyway)
SECURITY_HEADERS = {
    "Content-Security-Policy": "default-src 'self'; img-src 'self' data:; style-src 'self'; script-src 'self'; "
                               "connect-src 'self'; frame-ancestors 'none'; base-uri 'none'; form-action 'self'",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "X-Frame-Options": "DENY",
}


@dataclass
class WebState:
    """The page's state on the app: the master, sessions, previews, and whether the master is stopping."""

    service: WebService
    sessions: auth.Sessions = field(default_factory=auth.Sessions)
    previews: Previews = field(default_factory=Previews)
    closing: asyncio.Event = field(default_factory=asyncio.Event)


KEY: web.AppKey[WebState] = web.AppKey("quekaro_web", WebState)


def add_web_routes(app: web.Application, service: WebService) -> WebState:
    """Mount the page on the master's application (beside the job API, on its bind address)."""
    state = WebState(service)
    app[KEY] = state
    r = app.router
    r.add_get("/", to_page)
    r.add_get("/ui", to_page)
    r.add_get("/ui/", index)
    r.add_get("/ui/login", login_form)
    r.add_post("/ui/login", login)
    r.add_post("/ui/logout", logout)
    r.add_static("/ui/static", STATIC, follow_symlinks=False)  # no data in them: no session needed
    r.add_get("/ui/api/jobs", api_jobs)
    r.add_get("/ui/api/jobs/{job}", api_job)
    r.add_get("/ui/api/jobs/{job}/units/{unit}", api_unit)
    r.add_get("/ui/api/jobs/{job}/preview.png", api_preview)
    r.add_get("/ui/api/jobs/{job}/report", api_report)
    r.add_get("/ui/api/jobs/{job}/download/{kind}", api_download)
    r.add_post("/ui/api/jobs/{job}/cancel", api_cancel)
    r.add_post("/ui/api/jobs/{job}/requeue", api_requeue)
    r.add_post("/ui/api/jobs/{job}/resubmit", api_resubmit)
    r.add_post("/ui/api/jobs/{job}/units/{unit}/retry", api_retry)
    r.add_post("/ui/api/jobs/{job}/delete", api_delete)
    r.add_get("/ui/api/agents", api_agents)
    r.add_post("/ui/api/agents/drain", api_drain)
    r.add_get("/ui/api/logs", api_logs)
    r.add_get("/ui/api/logs/{name}", api_log)
    r.add_get("/ui/events", events)
    app.on_response_prepare.append(_secure_headers)
    app.on_shutdown.append(_closing)
    return state


async def _closing(app: web.Application) -> None:
    app[KEY].closing.set()  # open event streams end, so the master stops at once


async def _secure_headers(request: web.Request, response: web.StreamResponse) -> None:
    """Every page response is framed by nobody, under a Content-Security-Policy that allows this origin's
    own scripts, styles, images and connections only (no inline script); all but the static files are
    `no-store`."""
    if request.path == "/" or request.path.startswith("/ui"):
        response.headers.update(SECURITY_HEADERS)
        if not request.path.startswith("/ui/static/"):
            response.headers["Cache-Control"] = "no-store"


async def to_page(_request: web.Request) -> web.Response:
    """The master's root and /ui lead to the page (which asks for a login first if need be)."""
    return _redirect("/ui/")


def _redirect(location: str) -> web.Response:
    return web.Response(status=303, headers={"Location": location})


def _state(request: web.Request) -> WebState:
    return request.app[KEY]


def _page(name: str, **values: str) -> str:
    """A static HTML file with its {{name}} slots filled (HTML-escaped)."""
    text = (STATIC / name).read_text()
    for key, value in values.items():
        text = text.replace("{{" + key + "}}", html.escape(value, quote=True))
    return text


# ---- login ----------------------------------------------------------------------------------------------


async def login_form(request: web.Request, message: str = "", status: int = 200) -> web.Response:
    """The login form (a POST of the token in its body: no token ever in a URL), with `message` if any."""
    return web.Response(text=_page("login.html", message=message), content_type="text/html", status=status)


async def login(request: web.Request) -> web.Response:
    """The admin token from the form's `token` field opens a session (cookie); anything else gets the form
    again."""
    state = _state(request)
    form = await request.post()
    if not auth.token_matches(str(form.get("token", "")), state.service.admin_token):
        log.warning("web page: a wrong token was posted to the login form from %s", request.remote)
        await asyncio.sleep(FAILED_LOGIN_DELAY_S)
        return await login_form(request, "That is not the admin token of this farm.", status=401)
    session = state.sessions.open()
    response = _redirect("/ui/")
    auth.set_cookie(response, request, session)
    return response


async def logout(request: web.Request) -> web.Response:
    """End the session (a POST with its CSRF token, so no other site can log the user out)."""
    state = _state(request)
    state.sessions.close(await auth.require_action(request, state.sessions))
    response = web.json_response({"logged_out": True})
    auth.clear_cookie(response)
    return response


async def index(request: web.Request) -> web.Response:
    """The page, its session's CSRF token in a meta tag; without a session, the login form."""
    state = _state(request)
    session = auth.session_of(request, state.sessions)
    if session is None:
        return _redirect("/ui/login")
    return web.Response(text=_page("index.html", csrf=session.csrf), content_type="text/html")


# ---- data -----------------------------------------------------------------------------------------------


def _job_id(request: web.Request) -> str:
    job_id = request.match_info["job"]
    if not JOB_PART.fullmatch(job_id):
        raise web.HTTPNotFound(reason="no such job")
    return job_id


def _authorized(request: web.Request) -> WebService:
    state = _state(request)
    auth.require(request, state.sessions)
    return state.service


async def api_jobs(request: web.Request) -> web.Response:
    return web.json_response({"jobs": jobs_view(_authorized(request))})


async def api_job(request: web.Request) -> web.Response:
    service = _authorized(request)
    try:
        return web.json_response(job_view(service, _job_id(request)))
    except StoreError as exc:
        raise web.HTTPNotFound(reason=str(exc)) from None


async def api_unit(request: web.Request) -> web.Response:
    """One unit: its attempts, and the rules that fired for it with their strengths (evaluated in a
    thread: a rule file may need parsing)."""
    service = _authorized(request)
    job_id, unit = _job_id(request), request.match_info["unit"]
    if not UNIT_PART.fullmatch(unit):
        raise web.HTTPNotFound(reason="no such unit")
    try:
        record = service.store.job(job_id)
        view = unit_view(service, job_id, int(unit))
    except (StoreError, KeyError) as exc:
        raise web.HTTPNotFound(reason=str(exc).strip("'\"")) from None
    view["rules"] = await asyncio.to_thread(_rules_of, record, view)
    view["log"] = await asyncio.to_thread(logs.unit_lines, service.home, job_id, int(unit))
    return web.json_response(view)


def _rules_of(record: JobRecord, unit: dict[str, Any]) -> dict[str, Any]:
    """The rules that fired for the unit, by the job's rule file, or the default one when it brought none."""
    options = record.spec.options
    rules = options.rules if options.rules is not None and Path(options.rules).is_file() else None
    agent_rules = unit.get("agent_rules")
    if rules is not None:
        note = f"the job's rule file {rules.name} (from its bundle), which every agent used"
    else:
        note = ("the job brought no rule file: evaluated here with the default one; each agent used its own"
                + (f" (this unit's agent: {agent_rules})" if agent_rules else ""))
    try:
        planner = planner_for(rules, options.defuzzifier)
        ranges = {k: (float(v[0]), float(v[1])) for k, v in record.plan.get("ranges", {}).items()}
        return fired_rules(planner, unit, options.level, ranges, note).to_dict()
    except (QuekaroError, ValueError, KeyError) as exc:
        return {"error": f"the rules could not be evaluated here: {exc}", "note": note}


def _record(service: WebService, job_id: str) -> JobRecord:
    try:
        return service.store.job(job_id)
    except StoreError as exc:
        raise web.HTTPNotFound(reason=str(exc)) from None


async def api_preview(request: web.Request) -> web.StreamResponse:
    """The finished job's PNG, or the tiles landed so far composed (`master.web.preview`). A finished
    job's own result.png is served only when it fits MAX_SIDE; a larger one's preview is composed, once."""
    state = _state(request)
    service = _authorized(request)
    record = _record(service, _job_id(request))
    width, height = int(record.plan["width"]), int(record.plan["height"])
    final = service.result_path(record.id).with_suffix(".png")
    if record.status == JobStatus.DONE and final.is_file() and shrink_factor(width, height) == 1:
        state.previews.forget(record.id)
        return web.FileResponse(final, headers={"Content-Type": "image/png"})
    return web.FileResponse(await _composed(state, record), headers={"Content-Type": "image/png"})


async def _composed(state: WebState, record: JobRecord) -> Path:
    """The PNG of the job's tiles landed so far (the rest black), shrunk where the image is large."""
    service = state.service
    width, height = int(record.plan["width"]), int(record.plan["height"])
    reach = filter_reach(float(record.plan.get("filter_radius", DEFAULT_FILTER_RADIUS)))  # as JobPlan.from_dict
    planned = record.planned_units
    return await state.previews.png(record.id, service.job_dir(record.id), width, height,
                                    service.store.results(record.id), reach,
                                    tuple(record.plan.get("colour", RGB)),  # as JobPlan.from_dict
                                    aov_pass_path(service, record), None if planned is None else len(planned))


DOWNLOADS = ("image", "png", "report", "raw")


async def api_download(request: web.Request) -> web.StreamResponse:
    """A job's file to save, named as `quekaro result` names it (SCENE.exr, a frame's SCENE_0001.exr): a
    done job's image, PNG, report or raw image; those of a job running or ended without finishing are of its
    partial image (its tiles so far, the rest black), named SCENE.partial.exr. 409 for what the job does not
    have yet."""
    state = _state(request)
    service = _authorized(request)
    record, kind = _record(service, _job_id(request)), request.match_info["kind"]
    if kind not in DOWNLOADS:
        raise web.HTTPNotFound(reason=f"no download {kind[:40]!r}: {', '.join(DOWNLOADS)}")
    partial = record.status != JobStatus.DONE
    if partial and (kind == "raw" or not service.store.results(record.id)):
        why = "its partial image is not denoised" if kind == "raw" else "it has no tile yet"
        raise web.HTTPConflict(reason=f"job {record.id} is {record.status}: {why}")
    if partial and kind == "png":  # the page's own preview, shrunk where the image is large
        return web.FileResponse(await _composed(state, record), headers=attachment(record, ".partial.png"))
    try:
        await (service.ensure_partial(record.id, follow_tiles=kind == "image") if partial
               else service.ensure_assembled(record.id))
    except QuekaroError as exc:  # done or requeued meanwhile
        raise web.HTTPConflict(reason=str(exc)) from None
    path = result_file(service, record.id, kind, partial)
    if not path.is_file():
        raise web.HTTPNotFound(reason=f"job {record.id} has no {kind} file" + (": it was not denoised"
                                                                              if kind == "raw" else ""))
    suffix = ".raw.exr" if kind == "raw" else path.suffix
    return web.FileResponse(path, headers=attachment(record, (".partial" if partial else "") + suffix))


async def api_report(request: web.Request) -> web.Response:
    service = _authorized(request)
    try:
        return web.json_response(report_view(service, _job_id(request)))
    except StoreError as exc:
        raise web.HTTPNotFound(reason=str(exc)) from None


async def api_agents(request: web.Request) -> web.Response:
    return web.json_response({"agents": agents_view(_authorized(request))})


async def api_logs(request: web.Request) -> web.Response:
    """The farm's process logs (a local farm's: none for a farm of separate hosts), each with its size."""
    service = _authorized(request)
    found = logs.farm_logs(service.home)
    return web.json_response({"logs": [{"name": n, "bytes": p.stat().st_size} for n, p in found.items()]})


async def api_log(request: web.Request) -> web.Response:
    """One process's log: its last `lines` lines (default 200)."""
    service = _authorized(request)
    name, lines = request.match_info["name"], request.query.get("lines", "200")
    path = logs.farm_logs(service.home).get(name)
    if path is None:
        raise web.HTTPNotFound(reason=f"no log of {name[:64]!r}")
    if not lines.isascii() or not lines.isdigit():
        raise web.HTTPBadRequest(reason=f"lines={lines[:20]!r}: a count of lines")
    return web.json_response({"name": name, "lines": await asyncio.to_thread(logs.tail, path, int(lines))})


# ---- actions (POST, CSRF) -------------------------------------------------------------------------------


async def api_cancel(request: web.Request) -> web.Response:
    """Cancel a job, as `quekaro cancel` does (the master's own cancel)."""
    state = _state(request)
    await auth.require_action(request, state.sessions)
    job_id = _job_id(request)
    try:
        answer = await cancel_jobs(state.service, job_id)
    except StoreError as exc:
        raise web.HTTPNotFound(reason=str(exc)) from None
    log.info("web page: job %s %s", job_id, "cancelled" if answer["cancelled"] else "had already ended")
    return web.json_response(answer)


async def api_requeue(request: web.Request) -> web.Response:
    """Run a failed or cancelled job again, as `quekaro requeue` does: 409 with the reason where it will not."""
    state = _state(request)
    await auth.require_action(request, state.sessions)
    job_id = _job_id(request)
    try:
        answer = await requeue_jobs(state.service, job_id)
    except StoreError as exc:
        raise web.HTTPNotFound(reason=str(exc)) from None
    except RequeueRefused as exc:
        raise web.HTTPConflict(reason=str(exc)) from None
    log.info("web page: %s runs again", ", ".join(f"job {j}" for j in answer["requeued"]))
    return web.json_response(answer)


async def api_retry(request: web.Request) -> web.Response:
    """Render a done unit again (`MasterService.retry_unit`): 409 with the auction's reason where it will not."""
    state = _state(request)
    await auth.require_action(request, state.sessions)
    job_id, unit = _job_id(request), request.match_info["unit"]
    if not UNIT_PART.fullmatch(unit):
        raise web.HTTPNotFound(reason="no such unit")
    _record(state.service, job_id)
    refused = await state.service.retry_unit(job_id, int(unit))
    if refused:
        raise web.HTTPConflict(reason=f"unit {unit} of job {job_id}: {refused}")
    log.info("web page: unit %s of job %s to be rendered again", unit, job_id)
    return web.json_response({"job_id": job_id, "unit": int(unit), "retried": True})


async def api_delete(request: web.Request) -> web.Response:
    """Delete an ended job: its rows and its folder. 409 for a running job."""
    state = _state(request)
    await auth.require_action(request, state.sessions)
    record = _record(state.service, _job_id(request))
    if record.status == JobStatus.RUNNING:
        raise web.HTTPConflict(reason=f"job {record.id} is running: cancel it before deleting it")
    await state.service.delete_job(record.id)
    state.previews.forget(record.id)
    log.info("web page: job %s deleted", record.id)
    return web.json_response({"job_id": record.id, "deleted": True})


async def api_drain(request: web.Request) -> web.Response:
    """Drain an agent (the auction awards it nothing new; it finishes what it holds), or resume it."""
    state = _state(request)
    await auth.require_action(request, state.sessions)
    body = await _json_object(request)
    agent, drain = body.get("agent"), body.get("drain")
    if not isinstance(agent, str) or not isinstance(drain, bool) or set(body) != {"agent", "drain"}:
        raise web.HTTPBadRequest(reason='expected {"agent": JID, "drain": true or false}')
    refused = await state.service.drain(agent, drain)
    if refused:
        raise web.HTTPConflict(reason=refused)
    log.info("web page: agent %s %s", agent, "draining" if drain else "resumed")
    return web.json_response({"agent": agent, "draining": drain})


RESUBMIT_FIELDS = ("denoise",)  # what a re-submission may change of the job's options


async def _json_object(request: web.Request) -> dict[str, Any]:
    """The request's JSON object body ({} without a body); 400 for a body that is not one."""
    body = await request.read()
    if not body.strip():
        return {}
    try:
        data = json.loads(body)
    except (ValueError, RecursionError):
        raise web.HTTPBadRequest(reason="the body is not JSON") from None
    if not isinstance(data, dict):
        raise web.HTTPBadRequest(reason="the body must be a JSON object, e.g. {\"denoise\": true}")
    return data


async def _resubmit_changes(request: web.Request) -> dict[str, Any]:
    """The options a re-submission changes: its JSON body's fields (none without a body). 400 for a body
    that is not a JSON object, an unknown field, or a denoise that is not true or false."""
    changes = await _json_object(request)
    unknown = sorted(set(changes) - set(RESUBMIT_FIELDS))
    if unknown:
        raise web.HTTPBadRequest(reason=f"unknown field {unknown[0][:40]!r}: a re-submission may change "
                                        f"only {', '.join(RESUBMIT_FIELDS)}")
    if "denoise" in changes and not isinstance(changes["denoise"], bool):
        raise web.HTTPBadRequest(reason=f"denoise: {str(changes['denoise'])[:40]!r} is not true or false")
    return changes


async def api_resubmit(request: web.Request) -> web.Response:
    """Submit the job again: the same bundle, -D parameters and options (its rule file is in the bundle),
    with denoise set as the body asks, if it does."""
    state = _state(request)
    await auth.require_action(request, state.sessions)
    service, job_id = state.service, _job_id(request)
    changes = await _resubmit_changes(request)
    try:
        record = service.store.job(job_id)
    except StoreError as exc:
        raise web.HTTPNotFound(reason=str(exc)) from None
    bundle = service.job_dir(job_id) / "bundle.tar"
    if not bundle.is_file():
        raise web.HTTPConflict(reason=f"job {job_id}'s bundle is no longer on the master")
    copy = service.jobs_dir / f".resubmit-{secrets.token_hex(6)}.tar"
    await asyncio.to_thread(shutil.copyfile, bundle, copy)
    try:
        options = dataclasses.replace(record.spec.options, rules=None, **changes)
        new_id = await service.submit(copy, JobSpec(dict(record.spec.defines), options, record.spec.name))
    except QuekaroError as exc:
        raise web.HTTPUnprocessableEntity(reason=str(exc).replace("\n", " ")[:500]) from None
    finally:
        copy.unlink(missing_ok=True)
    log.info("web page: job %s submitted again as %s%s", job_id, new_id, ", denoised" if options.denoise else "")
    return web.json_response({"job_id": new_id, "from": job_id, "denoise": options.denoise}, status=201)


# ---- live updates ---------------------------------------------------------------------------------------


async def events(request: web.Request) -> web.StreamResponse:
    """The page's live updates (`master.web.events`), for as long as its session lives."""
    state = _state(request)
    session = auth.require(request, state.sessions)
    job_id = request.query.get("job") or None
    if job_id is not None and not JOB_PART.fullmatch(job_id):
        raise web.HTTPNotFound(reason="no such job")
    watcher = Watcher(state.service, job_id)
    return await stream(request, watcher, lambda: state.sessions.alive(session), state.closing)
