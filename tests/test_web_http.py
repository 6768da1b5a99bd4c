"""The web page's HTTP pieces on a real aiohttp server (the master's guarded one) with a stand-in master
whose job store is a real SQLite file: login and the session cookie's attributes, refusals without the
cookie (an agent's award token and the API's bearer token open nothing), CSRF on every action, the
server-sent events stream emitting on a status change and ending when the master stops, the unit view's
fired rules (held against fuzzy.Engine's activations), the preview PNG (a denoised job's denoised by the real
denoiser once its AOV pass exists), re-submission (with denoising turned on or off), the package data."""

from __future__ import annotations

import asyncio
import io
import json
import shutil
import time
import tomllib
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from fnmatch import fnmatch
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import aiohttp
import numpy as np
import pytest
from PIL import Image

from core.data import default_rules_path
from core.image.compose import compose_shrunk
from core.image.imageio import write_png_planar
from core.image.tiles import Tile, tile_source, write_tile
from core.model import messages as m
from core.model.geometry import Rect
from core.model.job import Effects, JobPlan, JobSpec, RenderOptions, SceneSpec
from core.model.levels import RULE_LEVELS
from core.model.status import JobStatus
from core.model.units import WorkUnit
from core.rules.unit_params import Planner
from master import auction as au
from master.data_plane import close, create_app, serve
from master.job_api import add_job_routes
from master.sessions import SharedAccounts
from master.store import JobStore
from master.web import add_web_routes, events, preview
from master.web.auth import COOKIE, CSRF_HEADER
from master.web.rules import evaluation_rulebase, rule_strengths
from planning.pipeline import AOV_PASS_FILE, save_aov_pass
from quekaro import cmd_farm

REPO = Path(__file__).resolve().parent.parent
ADMIN = "a1" * 24
AWARD = "award-token-of-an-agent-0123456789abcdef"
JOB = "job0000001"
AGENT = "agent-0-abc123@localhost"
W, H = 32, 16


def _units() -> list[WorkUnit]:
    """Four 16 x 8 units, different features (the rules see ranges)."""
    rects = [Rect(0, 0, 16, 8), Rect(16, 0, 16, 8), Rect(0, 8, 16, 8), Rect(16, 8, 16, 8)]
    return [WorkUnit(index=i, rect=r, C=0.01 + 0.05 * i, S=r.area, Nd=0.02 * i, cost=1.0 + i)
            for i, r in enumerate(rects)]


@dataclass
class FakeMaster:
    """What the page reads of `master.service.MasterService`, over a real job store."""

    home: Path
    admin_token: str = ADMIN
    paused: str | None = None
    data_plane: str = "http (loopback)"
    shared_accounts: SharedAccounts = field(default_factory=SharedAccounts)
    submitted: list[tuple[bytes, dict[str, str], RenderOptions]] = field(default_factory=list)
    specs: list[JobSpec] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.jobs_dir = self.home / "jobs"
        self.jobs_dir.mkdir(parents=True, exist_ok=True)
        self.store = JobStore(self.home / "jobs.sqlite")
        self.auction = au.Auction()  # the real one: the page reads its read API
        register = m.Register(conversation="register-1", speed=1.0, threads=1, rules="pathtracing.xml")
        self.auction.handle(au.MessageReceived(AGENT, register), time.time())

    def job_dir(self, job_id: str) -> Path:
        return self.jobs_dir / job_id

    def result_path(self, job_id: str) -> Path:
        return self.job_dir(job_id) / "result.exr"

    def partial_path(self, job_id: str) -> Path:
        return self.job_dir(job_id) / "partial.exr"

    def result_image(self, job_id: str, partial: bool = False) -> Path:
        return self.partial_path(job_id) if partial else self.result_path(job_id)

    async def retry_unit(self, job_id: str, index: int) -> str | None:
        """As the master's: the store's unit back to pending where it is done (the auction's decision is
        tests/test_auction_page.py's), else why not."""
        if not any(u.index == index and u.status == "done" for u in self.store.units(job_id)):
            return "only a done unit is retried"
        self.store.apply([au.UnitRetried(job_id, index, "asked by the user")], time.time())
        return None

    async def drain(self, agent: str, drain: bool) -> str | None:
        """Through the real auction, as the master's."""
        kind = au.AgentDrainRequested if drain else au.AgentResumeRequested
        ignored = [i for i in self.auction.handle(kind(agent), time.time()) if isinstance(i, au.MessageIgnored)]
        return ignored[0].reason if ignored else None

    async def delete_job(self, job_id: str) -> None:
        self.store.delete_job(job_id)
        shutil.rmtree(self.job_dir(job_id), ignore_errors=True)

    async def cancel(self, job_id: str) -> bool:
        return self.store.cancel(job_id, time.time())

    async def ensure_assembled(self, job_id: str) -> Path:
        return self.result_path(job_id).with_suffix(".json")

    async def submit(self, bundle: Path, spec: JobSpec) -> str:
        self.submitted.append((bundle.read_bytes(), spec.defines, spec.options))
        self.specs.append(spec)
        bundle.unlink()  # the real master moves it into the new job's folder
        return f"job000000{len(self.submitted) + 1}"

    def add_job(self, job_id: str = JOB, level: str = "S", denoise: bool = False, name: str | None = None,
                sequence: str | None = None, frame: int | None = None) -> None:
        effects = Effects("llvm_ad_rgb", "path", 8, ["the scene's integrator is path"])
        options = RenderOptions(level=level, spp=16, denoise=denoise)
        plan = JobPlan(SceneSpec(Path("scene.xml")), options, W, H, effects, 16, 8, _units(), bundle_sha256="ef" * 32)
        defines = {"res": "32", **({"frame": str(frame)} if frame is not None else {})}
        spec = JobSpec(defines, options, name, None, sequence, frame)
        self.store.create_job(job_id, "scene.xml", spec, plan, time.time())
        self.job_dir(job_id).mkdir(parents=True, exist_ok=True)
        (self.job_dir(job_id) / "bundle.tar").write_bytes(b"the job's bundle")

    def award(self, index: int, token: str = AWARD, job_id: str = JOB) -> None:
        self.store.record_award(job_id, index, AGENT, token, time.time(), 2.0)

    def finish(self, index: int, token: str = AWARD, value: float = 0.5, noise: float = 0.0,
               job_id: str = JOB) -> None:
        """The unit's tile lands (a flat tile of `value`, with Gaussian `noise` if asked), as the master
        records one."""
        rect = _units()[index].rect
        meta = {"job_id": job_id, "unit_index": index, "spp": 12, "depth": 6, "band": 0, "agent": AGENT}
        (self.job_dir(job_id) / "tiles").mkdir(exist_ok=True)
        pixels = value + noise * np.random.default_rng(index).standard_normal((rect.h, rect.w, 3))
        path = write_tile(self.job_dir(job_id) / "tiles" / f"unit-{index}.exr",
                          Tile(pixels.clip(0).astype(np.float32), rect, rect, meta))
        params = {"spp": 12, "depth": 6, "band": 0, "seconds": 1.5, "nonfinite": 0, "agent": AGENT,
                  "outputs": {"Rl": 0.75, "Ls": 0.8, "Ibs": 0.1}, "rules": "pathtracing.xml"}
        self.store.record_result(job_id, index, str(path), "00" * 32, params, time.time())
        self.store.finish_attempt(token, "done", time.time(), 1.5, params)
        self.store.mark_done(job_id, index, time.time())


@dataclass
class Page:
    """A running server with the page mounted, and a client that sends exactly the cookies it is told."""

    url: str
    http: aiohttp.ClientSession
    master: FakeMaster
    runner: Any

    async def login(self, token: str = ADMIN) -> aiohttp.ClientResponse:
        return await self.http.post(self.url + "/ui/login", data={"token": token}, allow_redirects=False)

    async def session(self) -> tuple[str, str]:
        """A logged-in session: (cookie header value, CSRF token from the page's meta tag)."""
        response = await self.login()
        cookie = f"{COOKIE}={response.cookies[COOKIE].value}"
        page = await (await self.http.get(self.url + "/ui/", headers={"Cookie": cookie})).text()
        csrf = page.split('name="csrf-token" content="', 1)[1].split('"', 1)[0]
        return cookie, csrf


@asynccontextmanager
async def running(tmp_path: Path, denoise: bool = False) -> AsyncIterator[Page]:
    master = FakeMaster(tmp_path / "home")
    master.add_job(denoise=denoise)
    app = create_app(expected=lambda job, unit, token: None, bundle=lambda job: None, on_tile=lambda *a: None,
                     tile_dir=master.jobs_dir)
    add_job_routes(app, master)
    add_web_routes(app, master)
    runner, port = await serve(app, "127.0.0.1", 0)
    # One request a connection, as the master's server answers (master.http_guard); no cookie kept by itself.
    async with aiohttp.ClientSession(cookie_jar=aiohttp.DummyCookieJar(),
                                     connector=aiohttp.TCPConnector(force_close=True)) as http:
        try:
            yield Page(f"http://127.0.0.1:{port}", http, master, runner)
        finally:
            await close(runner)


def run(tmp_path: Path, scenario: Callable[[Page], Awaitable[None]], denoise: bool = False) -> None:
    async def main() -> None:
        async with running(tmp_path, denoise) as page:
            await scenario(page)

    asyncio.run(main())


async def read_events(response: aiohttp.ClientResponse, until: Callable[[str, dict], bool],
                      timeout: float) -> list[tuple[str, dict]]:
    """Server-sent events from a stream until one satisfies `until` (or TimeoutError)."""
    seen: list[tuple[str, dict]] = []

    async def reading() -> None:
        name = ""
        while True:
            line = (await response.content.readline()).decode().rstrip("\n")
            if line.startswith("event: "):
                name = line[7:]
            elif line.startswith("data: "):
                seen.append((name, json.loads(line[6:])))
                if until(name, seen[-1][1]):
                    return

    await asyncio.wait_for(reading(), timeout)
    return seen


# ---- login, cookie, refusals --------------------------------------------------------------------------


def test_login_sets_an_httponly_strict_cookie_and_the_page_needs_it(tmp_path):
    async def scenario(page: Page) -> None:
        first = await page.http.get(page.url + "/ui/", allow_redirects=False)
        assert first.status == 303 and first.headers["Location"] == "/ui/login"
        assert (await page.http.get(page.url + "/", allow_redirects=False)).headers["Location"] == "/ui/"
        form = await page.http.get(page.url + "/ui/login")
        text = await form.text()
        assert form.status == 200 and 'method="post"' in text and 'action="/ui/login"' in text
        wrong = await page.login("not-the-token")
        assert wrong.status == 401 and "Set-Cookie" not in wrong.headers
        assert "not the admin token of this farm" in await wrong.text()
        right = await page.login()
        assert right.status == 303 and right.headers["Location"] == "/ui/"
        cookie = right.headers["Set-Cookie"]
        attributes = {part.strip().split("=", 1)[0].lower(): part for part in cookie.split(";")}
        assert {"httponly", "samesite", "path"} <= set(attributes), cookie
        assert "Strict" in attributes["samesite"] and attributes["path"].strip() == "Path=/ui"
        assert "secure" not in attributes  # plain HTTP on loopback; HTTPS sets Secure (request.secure)
        assert ADMIN not in cookie and ADMIN not in right.headers["Location"]
        session = f"{COOKIE}={right.cookies[COOKIE].value}"
        served = await page.http.get(page.url + "/ui/", headers={"Cookie": session})
        assert served.status == 200 and 'name="csrf-token"' in await served.text()
        assert "script-src 'self'" in served.headers["Content-Security-Policy"]
        assert served.headers["Cache-Control"] == "no-store"

    run(tmp_path, scenario)


@pytest.mark.parametrize("path", ["/ui/api/jobs", f"/ui/api/jobs/{JOB}", f"/ui/api/jobs/{JOB}/units/0",
                                  f"/ui/api/jobs/{JOB}/preview.png", f"/ui/api/jobs/{JOB}/report",
                                  "/ui/api/agents", "/ui/events", f"/ui/events?job={JOB}"])
def test_without_the_cookie_nothing_is_served_not_even_to_tokens(tmp_path, path):
    async def scenario(page: Page) -> None:
        page.master.award(0)  # AWARD is a live award token now
        for headers in ({}, {"X-Quekaro-Token": AWARD}, {"Authorization": f"Bearer {AWARD}"},
                        {"Authorization": f"Bearer {ADMIN}"}, {"Cookie": f"{COOKIE}=forged"}):
            response = await page.http.get(page.url + path, headers=headers, allow_redirects=False)
            assert response.status == 401, (headers, response.status)
            assert "log in first" in (await response.json())["error"]

    run(tmp_path, scenario)


def test_an_award_token_gets_no_page(tmp_path):
    async def scenario(page: Page) -> None:
        page.master.award(0)
        refused = await page.login(AWARD)
        assert refused.status == 401 and COOKIE not in refused.cookies
        for headers in ({"X-Quekaro-Token": AWARD}, {"Authorization": f"Bearer {AWARD}"}):
            response = await page.http.get(page.url + "/ui/", headers=headers, allow_redirects=False)
            assert response.status == 303 and response.headers["Location"] == "/ui/login"

    run(tmp_path, scenario)


def test_actions_need_the_sessions_csrf_token(tmp_path):
    async def scenario(page: Page) -> None:
        cookie, csrf = await page.session()
        other_cookie, other_csrf = await page.session()
        cancel = f"{page.url}/ui/api/jobs/{JOB}/cancel"
        for headers in ({"Cookie": cookie}, {"Cookie": cookie, CSRF_HEADER: "wrong"},
                        {"Cookie": cookie, CSRF_HEADER: other_csrf}):
            response = await page.http.post(cancel, headers=headers)
            assert response.status == 403 and "CSRF" in (await response.json())["error"]
        assert page.master.store.job(JOB).status == "running"
        no_cookie = await page.http.post(cancel, headers={CSRF_HEADER: csrf})
        assert no_cookie.status == 401
        done = await page.http.post(cancel, headers={"Cookie": cookie, CSRF_HEADER: csrf})
        assert done.status == 200 and (await done.json()) == {"job_id": JOB, "cancelled": True}
        assert page.master.store.job(JOB).status == "cancelled"
        logout = await page.http.post(page.url + "/ui/logout",
                                      headers={"Cookie": other_cookie, CSRF_HEADER: other_csrf})
        assert logout.status == 200
        after = await page.http.get(page.url + "/ui/api/jobs", headers={"Cookie": other_cookie})
        assert after.status == 401

    run(tmp_path, scenario)


def test_resubmit_sends_the_same_bundle_defines_and_options(tmp_path):
    async def scenario(page: Page) -> None:
        cookie, csrf = await page.session()
        response = await page.http.post(f"{page.url}/ui/api/jobs/{JOB}/resubmit",
                                         headers={"Cookie": cookie, CSRF_HEADER: csrf})
        assert response.status == 201
        assert (await response.json()) == {"job_id": "job0000002", "from": JOB, "denoise": False}
        [(bundle, defines, options)] = page.master.submitted
        assert bundle == b"the job's bundle" and defines == {"res": "32"}
        assert options.level == "S" and options.spp == 16 and options.rules is None and not options.denoise
        assert not list(page.master.jobs_dir.glob(".resubmit-*"))

    run(tmp_path, scenario)


@pytest.mark.parametrize("denoise", [False, True])
def test_resubmit_turns_denoising_on_or_off_and_keeps_the_rest(tmp_path, denoise):
    async def scenario(page: Page) -> None:
        cookie, csrf = await page.session()
        response = await page.http.post(f"{page.url}/ui/api/jobs/{JOB}/resubmit", json={"denoise": not denoise},
                                         headers={"Cookie": cookie, CSRF_HEADER: csrf})
        assert response.status == 201 and (await response.json())["denoise"] is (not denoise)
        [(_, defines, options)] = page.master.submitted
        assert options.denoise is (not denoise) and options.level == "S" and options.spp == 16
        assert defines == {"res": "32"}

    run(tmp_path, scenario, denoise=denoise)


@pytest.mark.parametrize(("body", "named"), [
    (b'{"denoise": "yes"}', "denoise: 'yes' is not true or false"),
    (b'{"denoise": 1}', "denoise: '1' is not true or false"),
    (b'{"denoise": null}', "denoise: 'None' is not true or false"),
    (b'{"spp": 4}', "unknown field 'spp'"),
    (b'[true]', "must be a JSON object"),
    (b'{"denoise": tru', "not JSON"),
])
def test_resubmit_refuses_a_denoise_that_is_not_true_or_false(tmp_path, body, named):
    async def scenario(page: Page) -> None:
        cookie, csrf = await page.session()
        response = await page.http.post(f"{page.url}/ui/api/jobs/{JOB}/resubmit", data=body,
                                         headers={"Cookie": cookie, CSRF_HEADER: csrf,
                                                  "Content-Type": "application/json"})
        assert response.status == 400 and named in (await response.json())["error"]
        assert not page.master.submitted and not list(page.master.jobs_dir.glob(".resubmit-*"))

    run(tmp_path, scenario)


# ---- the data: jobs, units and their rules, preview, agents ---------------------------------------------


def test_job_and_unit_views_show_state_parameters_rules_and_attempts(tmp_path):
    async def scenario(page: Page) -> None:
        cookie, _ = await page.session()
        page.master.award(1)
        page.master.finish(1)
        page.master.award(2, token="second-award-token")
        job = await (await page.http.get(f"{page.url}/ui/api/jobs/{JOB}", headers={"Cookie": cookie})).json()
        assert job["units_total"] == 4 and job["units_done"] == 1 and job["tiles"] == 1
        assert job["effects"]["reasons"] == ["the scene's integrator is path"] and job["level"] == "S"
        units = {u["index"]: u for u in job["units"]}
        assert units[1]["status"] == "done" and units[1]["spp"] == 12 and units[1]["agent"] == AGENT
        assert units[2]["status"] == "awarded" and units[2]["agent"] == AGENT and units[2]["spp"] is None
        assert units[0]["status"] == "pending" and units[0]["C"] == pytest.approx(0.01)
        for odd in ("%C2%B2", "%D9%A1", "1%0A"):  # not ASCII digits: a 500, or unit 1
            seen = await page.http.get(f"{page.url}/ui/api/jobs/{JOB}/units/{odd}", headers={"Cookie": cookie})
            assert seen.status == 404, odd
        unit = await (await page.http.get(f"{page.url}/ui/api/jobs/{JOB}/units/1", headers={"Cookie": cookie})).json()
        assert unit["S"] == 128 and unit["attempt_list"][0]["agent"] == AGENT
        assert unit["attempt_list"][0]["outcome"] == "done"
        rules = unit["rules"]
        assert rules["rules_file"] == default_rules_path().name and rules["level"] == "S"
        assert rules["fired"] and all(0 < r["strength"] <= 1 for r in rules["fired"])
        assert [r["strength"] for r in rules["fired"]] == sorted((r["strength"] for r in rules["fired"]), reverse=True)
        assert set(rules["outputs"]) == {"Rl", "Ls", "Ibs"} and "default one" in rules["note"]
        missing = await page.http.get(f"{page.url}/ui/api/jobs/{JOB}/units/9", headers={"Cookie": cookie})
        assert missing.status == 404
        for part in ("", "/report", "/preview.png"):
            missing = await page.http.get(f"{page.url}/ui/api/jobs/job0000009{part}", headers={"Cookie": cookie})
            text = f"{missing.reason} {await missing.text()}"
            assert missing.status == 404 and "no job 'job0000009'" in text and str(page.master.home) not in text
        agents = await (await page.http.get(f"{page.url}/ui/api/agents", headers={"Cookie": cookie})).json()
        [agent] = agents["agents"]
        assert agent["jid"] == AGENT and agent["units_done"] == 1 and agent["state"] == "idle"

    run(tmp_path, scenario)


def test_agents_view_names_restarting_and_blocklisted_agents(tmp_path):
    async def scenario(page: Page) -> None:
        cookie, _ = await page.session()
        processes = {"processes": [{"name": "agent-0", "state": "restarting", "restarts": 2}]}
        (page.master.home / "processes.json").write_text(json.dumps(processes))
        rows = (await (await page.http.get(f"{page.url}/ui/api/agents", headers={"Cookie": cookie})).json())["agents"]
        assert rows[0]["state"] == "restarting" and rows[0]["restarts"] == 2
        (page.master.home / "processes.json").unlink()
        info = m.JobInfo(job_id=JOB, scene_url="http://127.0.0.1:8765/scene", scene_hash="ef" * 32, width=W, height=H,
                         spp=16, depth=8, level="S", ranges={})
        page.master.auction.handle(au.JobSubmitted(info, _units()), time.time())
        page.master.auction._jobs[JOB].blocklist.add(AGENT)  # as three failures of its units would
        rows = (await (await page.http.get(f"{page.url}/ui/api/agents", headers={"Cookie": cookie})).json())["agents"]
        assert rows[0]["state"] == "blocklisted" and rows[0]["blocklisted_for"] == [JOB] and rows[0]["shared"] is None
        now = time.monotonic()
        for t, resource in ((now - 3, "a"), (now - 2, "b"), (now - 1, "a")):  # two clients, one JID
            page.master.shared_accounts.seen(AGENT, resource, t)
        rows = (await (await page.http.get(f"{page.url}/ui/api/agents", headers={"Cookie": cookie})).json())["agents"]
        assert f"2 clients log in as {AGENT} (resources a, b)" in rows[0]["shared"], rows[0]

    run(tmp_path, scenario)


def test_preview_png_shows_the_tiles_landed_so_far(tmp_path):
    async def scenario(page: Page) -> None:
        cookie, _ = await page.session()
        url = f"{page.url}/ui/api/jobs/{JOB}/preview.png"
        empty = await page.http.get(url, headers={"Cookie": cookie})
        assert empty.status == 200 and empty.headers["Content-Type"] == "image/png"
        assert not np.asarray(Image.open(io.BytesIO(await empty.read()))).any()
        page.master.award(3)
        page.master.finish(3, value=1.0)
        image = np.asarray(Image.open(io.BytesIO(await (await page.http.get(url, headers={"Cookie": cookie})).read())))
        assert image.shape == (H, W, 3)
        assert (image[8:, 16:] == 255).all() and not image[:8].any() and not image[:, :16].any()

    run(tmp_path, scenario)


def test_a_preview_larger_than_its_limit_is_shrunk_and_so_is_a_finished_jobs(tmp_path, monkeypatch):
    monkeypatch.setattr(preview, "MAX_SIDE", 12)  # the 32 x 16 job: 3 times smaller, 11 x 6

    async def scenario(page: Page) -> None:
        cookie, _ = await page.session()
        url = f"{page.url}/ui/api/jobs/{JOB}/preview.png"

        async def shown() -> np.ndarray:
            response = await page.http.get(url, headers={"Cookie": cookie})
            return np.asarray(Image.open(io.BytesIO(await response.read())))

        page.master.award(3)
        page.master.finish(3, value=1.0)  # x 16..31, y 8..15
        image = await shown()
        assert image.shape == (6, 11, 3)
        # Blocks of 3 x 3: those wholly or partly in unit 3 show its white (only covered pixels count),
        # the others black.
        assert (image[2:, 5:] == 255).all() and not image[:2].any() and not image[:, :5].any()
        for index in (0, 1, 2):
            page.master.award(index, token=f"award-{index}")
            page.master.finish(index, token=f"award-{index}", value=1.0)
        page.master.store.set_status(JOB, JobStatus.DONE, time.time())
        Image.new("RGB", (W, H)).save(page.master.result_path(JOB).with_suffix(".png"))  # full size, black
        assert (await shown()).shape == (6, 11, 3) and ((await shown()) == 255).all()

    run(tmp_path, scenario)


def _keep_aov_pass(folder: Path) -> None:
    """A flat grey scene's AOV pass, as master.service keeps it: albedo 0.5, normals facing the camera."""
    planes = np.concatenate([np.full((3, H, W), 0.5), np.zeros((2, H, W)), np.ones((1, H, W))]).astype(np.float32)
    save_aov_pass(folder / AOV_PASS_FILE, planes)


def test_a_denoised_jobs_preview_is_denoised_once_its_aov_pass_exists(tmp_path):
    """Noisy tiles of a flat grey: the raw composition until the AOV pass is kept, then (the same tiles,
    remade) the real denoiser's far smoother image of the same grey."""
    async def scenario(page: Page) -> None:
        cookie, _ = await page.session()

        async def shown() -> np.ndarray:
            response = await page.http.get(f"{page.url}/ui/api/jobs/{JOB}/preview.png", headers={"Cookie": cookie})
            return np.asarray(Image.open(io.BytesIO(await response.read()))).astype(np.float64)

        async def job() -> dict[str, Any]:
            return await (await page.http.get(f"{page.url}/ui/api/jobs/{JOB}", headers={"Cookie": cookie})).json()

        for index in range(4):
            page.master.award(index, token=f"award-{index}")
            page.master.finish(index, token=f"award-{index}", value=0.3, noise=0.15)
        assert (await job())["options"]["denoise"] is True and (await job())["aov_pass"] is False
        raw = await shown()
        tiles = [tile_source(r.tile_path) for r in page.master.store.results(JOB)]  # composed here too
        composed = compose_shrunk(tiles, W, H, 1)
        assert np.array_equal(raw, np.asarray(Image.open(write_png_planar(tmp_path / "mine.png", composed))))
        grey = np.asarray(Image.open(write_png_planar(tmp_path / "grey.png", np.full((3, 1, 1), composed.mean()))))
        _keep_aov_pass(page.master.job_dir(JOB))
        assert (await job())["aov_pass"] is True
        denoised = await shown()  # no tile was added: remade for the AOV pass
        assert denoised.std() < 0.3 * raw.std(), (denoised.std(), raw.std())
        assert abs(denoised.mean() - grey.mean()) < 3, (denoised.mean(), grey.mean())  # the tiles' mean grey

    run(tmp_path, scenario, denoise=True)


def test_aov_planes_are_shrunk_by_the_blocks_the_composition_is():
    """A shrunk preview is denoised with its AOVs shrunk as its colour is (compose_shrunk's blocks)."""
    planar = np.random.default_rng(3).random((6, 17, 23)).astype(np.float32)
    rect = Rect(0, 0, 23, 17)
    tile = Tile(np.moveaxis(planar, 0, -1), rect, rect, {"unit_index": 0}, channels=("R", "G", "B", *"XYZ"))
    for factor in (1, 2, 3, 5):
        expected = compose_shrunk([tile], 23, 17, factor, planes=6)
        assert np.allclose(preview.block_means(planar, factor), expected, atol=1e-6), factor


def test_report_of_an_unfinished_job_says_there_is_none_and_why(tmp_path):
    async def scenario(page: Page) -> None:
        cookie, _ = await page.session()
        report = await (await page.http.get(f"{page.url}/ui/api/jobs/{JOB}/report", headers={"Cookie": cookie})).json()
        assert report["available"] is False and "no per-job accuracy report" in report["accuracy_note"]

    run(tmp_path, scenario)


# ---- live updates ---------------------------------------------------------------------------------------


def test_event_stream_emits_on_a_status_change_and_only_then(tmp_path):
    async def scenario(page: Page) -> None:
        cookie, _ = await page.session()
        stream = await page.http.get(f"{page.url}/ui/events?job={JOB}", headers={"Cookie": cookie})
        assert stream.status == 200 and stream.headers["Content-Type"].startswith("text/event-stream")
        first = await read_events(stream, lambda name, _data: name == "agents", timeout=5)
        assert [name for name, _ in first] == ["jobs", "job", "agents"]
        assert {u["status"] for u in first[1][1]["units"]} == {"pending"}
        with pytest.raises(TimeoutError):  # nothing changed: no jobs or job event
            await read_events(stream, lambda name, _data: name in ("jobs", "job"), timeout=2.5)
        started = time.monotonic()
        page.master.award(0)
        changed = await read_events(stream, lambda name, _data: name == "job", timeout=5)
        took = time.monotonic() - started
        job = changed[-1][1]
        assert job["units"][0]["status"] == "awarded" and job["units"][0]["agent"] == AGENT
        assert took < 2 * events.TICK_S + 0.5, took
        jobs = [data for name, data in changed if name == "jobs"]
        assert jobs and jobs[-1]["jobs"][0]["agents_busy"] == 1

    run(tmp_path, scenario)


def test_a_denoised_jobs_aov_pass_landing_is_an_event_though_no_row_changed(tmp_path):
    """The master keeps the AOV pass as a file, not a row: the stream sends the job again when it lands."""
    async def scenario(page: Page) -> None:
        cookie, _ = await page.session()
        stream = await page.http.get(f"{page.url}/ui/events?job={JOB}", headers={"Cookie": cookie})
        first = await read_events(stream, lambda name, _data: name == "agents", timeout=5)
        assert dict(first)["job"]["aov_pass"] is False
        _keep_aov_pass(page.master.job_dir(JOB))
        changed = await read_events(stream, lambda name, _data: name == "job", timeout=5)
        assert changed[-1][1]["aov_pass"] is True

    run(tmp_path, scenario, denoise=True)


AGENTS_WAIT_S = 2 * events.TICK_S + 1  # an agents event comes within two of its ticks


def test_the_agents_event_is_sent_when_a_row_changes_not_as_their_ages_tick(tmp_path):
    async def scenario(page: Page) -> None:
        cookie, _ = await page.session()
        stream = await page.http.get(f"{page.url}/ui/events", headers={"Cookie": cookie})
        await read_events(stream, lambda name, _data: name == "agents", timeout=5)
        with pytest.raises(TimeoutError):  # last_seen_s grows by the second: the page ages it itself
            await read_events(stream, lambda name, _data: name == "agents", timeout=3.5)
        agent = page.master.auction._agents[AGENT]
        agent.last_seen -= 30  # what the page shows is now 30 s off (AGE_SLACK_S is 5)
        [(_, data)] = await read_events(stream, lambda name, _data: name == "agents", timeout=AGENTS_WAIT_S)
        assert data["agents"][0]["last_seen_s"] >= 30 and "server_now" in data
        agent.lost = True
        [(_, data)] = await read_events(stream, lambda name, _data: name == "agents", timeout=AGENTS_WAIT_S)
        assert data["agents"][0]["state"] == "lost"

    run(tmp_path, scenario)


def test_event_streams_end_when_the_master_stops_or_the_session_ends(tmp_path):
    async def scenario(page: Page) -> None:
        cookie, csrf = await page.session()
        stream = await page.http.get(f"{page.url}/ui/events", headers={"Cookie": cookie})
        await read_events(stream, lambda name, _data: name == "agents", timeout=5)
        await page.http.post(page.url + "/ui/logout", headers={"Cookie": cookie, CSRF_HEADER: csrf})
        await asyncio.wait_for(stream.content.read(), 3 * events.TICK_S)  # the stream ends (EOF)
        cookie, _ = await page.session()
        stream = await page.http.get(f"{page.url}/ui/events", headers={"Cookie": cookie})
        await read_events(stream, lambda name, _data: name == "agents", timeout=5)
        started = time.monotonic()
        await close(page.runner)
        assert time.monotonic() - started < 5  # not aiohttp's 60 s wait for open handlers

    run(tmp_path, scenario)


# ---- the rules, and the package ---------------------------------------------------------------------------


@pytest.mark.parametrize("level", RULE_LEVELS)
def test_fired_rule_strengths_agree_with_the_engines_activations(level):
    """Each output label's activation in fuzzy.Engine is the max strength of the rules concluding it."""
    planner = Planner()
    rng = np.random.default_rng(7)
    ranges = {"C": (0.0, 0.4), "S": (64.0, 4096.0), "Nd": (0.0, 0.2)}
    rulebase = evaluation_rulebase(planner, ranges)
    for _ in range(20):
        unit = {"C": rng.uniform(-0.05, 0.45), "S": rng.uniform(0, 5000), "Nd": rng.uniform(0, 0.25),
                "Op": rulebase.op_value(level)}
        strengths = rule_strengths(rulebase, unit, ranges)
        activations = planner.engine.activations({k: np.array([v]) for k, v in unit.items()}, ranges)
        for out in rulebase.outputs:
            for j, label in enumerate(out.labels):
                concluding = [s for rule, s in zip(rulebase.rules, strengths, strict=True)
                              if any(c.variable == out.name and c.label == label for c in rule.consequents)]
                assert activations[out.name][0, j] == pytest.approx(max(concluding, default=0.0), abs=1e-12)


def test_the_page_files_ship_as_package_data():
    data = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    patterns = data.get("master.web", [])
    static = sorted(p.relative_to(REPO / "master" / "web").as_posix()
                    for p in (REPO / "master" / "web" / "static").iterdir())
    assert {"static/index.html", "static/login.html", "static/app.js", "static/style.css"} <= set(static)
    assert all(any(fnmatch(name, pattern) for pattern in patterns) for name in static), (patterns, static)


def test_demo_prints_the_pages_url(tmp_path, monkeypatch, capsys):
    """`quekaro demo` (what `make demo` runs) names the page's URL and where its login token is."""

    class Stop(Exception):
        pass

    class StubFarm:
        url, n_agents, home = "http://127.0.0.1:8123", 2, tmp_path

        def __init__(self, *args: Any, **kwargs: Any) -> None:
            pass

        def __enter__(self) -> StubFarm:
            return self

        def __exit__(self, *exc: object) -> None:
            pass

        def wait_for_agents(self) -> None:
            raise Stop  # the page's URL is printed before the farm is waited for

    monkeypatch.setattr(cmd_farm, "LocalFarm", StubFarm)
    args = SimpleNamespace(home=tmp_path, agents=2, threads=1, rules=[], http_port=0, level="S", out=tmp_path / "x",
                           log_format="text")
    with pytest.raises(Stop):
        cmd_farm.run_demo(args)
    out = capsys.readouterr().out
    assert f"web page: http://127.0.0.1:8123/ui/ (log in with the admin token in {tmp_path / 'admin.token'}" in out
