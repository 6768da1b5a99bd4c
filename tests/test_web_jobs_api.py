"""The job API's sequences and the page's job actions over real HTTP (the master's aiohttp application, a real
SQLite job store and the real auction behind the stand-in master of tests/test_web_http.py): a frame range
submitted as one job per frame sharing a sequence id, a sequence's summary, list and cancel, job summaries'
name/spp/resolution/-D, downloads named as the CLI names them (a cancelled job's partial PNG), a cancelled
job's units read "cancelled", retry, requeue (a job, a sequence's ended frames), delete, drain and resume (CSRF
on each), and the farm's logs."""

from __future__ import annotations

import io
import json
import time

import numpy as np
from PIL import Image
from test_web_http import ADMIN, AGENT, JOB, Page, run

from core.model.job import JobSpec
from core.model.status import UnitStatus
from master import auction as au
from master.web.auth import CSRF_HEADER

SEQ = "seq-0123456789ab"
BEARER = {"Authorization": f"Bearer {ADMIN}"}


def frames_of(page: Page, statuses: tuple[str, ...]) -> list[str]:
    """A sequence of frames 1..N, each a job of the store, ended as `statuses` says (running stays)."""
    ids = []
    for frame, status in enumerate(statuses, 1):
        job_id = f"frame{frame:05d}"
        page.master.add_job(job_id, name="walk", sequence=SEQ, frame=frame)
        if status != "running":
            page.master.store.set_status(job_id, status, time.time(), "" if status == "done" else status)
        ids.append(job_id)
    return ids


async def api(page: Page, method: str, path: str, **kw) -> tuple[int, dict]:
    response = await page.http.request(method, page.url + path, headers={**BEARER, **kw.pop("headers", {})}, **kw)
    return response.status, await response.json()


def test_a_frame_range_is_one_job_per_frame_sharing_a_new_sequence_id(tmp_path):
    async def scenario(page: Page) -> None:
        spec = {"defines": {"res": "32"}, "options": {"level": "off"}, "name": "walk",
                "frames": {"define": "frame", "first": 1, "last": 5, "step": 2}}
        status, answer = await api(page, "POST", "/api/jobs", data=b"the bundle",
                                   headers={"X-Quekaro-Job": json.dumps(spec)})
        assert status == 201 and answer["job_id"] == answer["sequence"] and answer["sequence"].startswith("seq-")
        assert [j["frame"] for j in answer["jobs"]] == [1, 3, 5]
        assert [j["job_id"] for j in answer["jobs"]] == ["job0000002", "job0000003", "job0000004"]
        specs = page.master.specs
        assert [(s.sequence, s.frame, s.defines["frame"], s.name, s.frames) for s in specs] == [
            (answer["sequence"], n, str(n), "walk", None) for n in (1, 3, 5)]
        assert [bundle for bundle, _, _ in page.master.submitted] == [b"the bundle"] * 3  # received once, linked
        assert not list(page.master.jobs_dir.glob(".frame-*")) and not list(page.master.jobs_dir.glob(".upload-*"))
        plain = {"defines": {}, "options": {"level": "off"}, "name": "one shot"}
        status, answer = await api(page, "POST", "/api/jobs", data=b"b", headers={"X-Quekaro-Job": json.dumps(plain)})
        assert status == 201 and answer == {"job_id": "job0000005", "name": "one shot"}
        assert page.master.specs[-1] == JobSpec({}, page.master.specs[-1].options, "one shot")

    run(tmp_path, scenario)


def test_a_sequence_is_listed_summarised_and_cancelled_by_its_id(tmp_path):
    async def scenario(page: Page) -> None:
        ids = frames_of(page, ("done", "running", "running"))
        status, listed = await api(page, "GET", f"/api/jobs?sequence={SEQ}")
        assert status == 200 and [j["job_id"] for j in listed["jobs"]] == ids
        first = listed["jobs"][0]
        assert (first["name"], first["sequence"], first["frame"], first["spp"], first["resolution"], first["level"],
                first["scene"], first["defines"]) == ("walk", SEQ, 1, 16, [32, 16], "S", "scene.xml",
                                                      {"res": "32", "frame": "1"})
        status, summary = await api(page, "GET", f"/api/jobs/{SEQ}")
        assert status == 200 and (summary["sequence"], summary["name"], summary["scene"], summary["status"]) == (
            SEQ, "walk", "scene.xml", "running")
        assert [f["frame"] for f in summary["frames"]] == [1, 2, 3]
        status, refused = await api(page, "GET", f"/api/jobs/{SEQ}/result")
        assert status == 400 and "fetched by its job id" in refused["error"]
        status, cancelled = await api(page, "POST", f"/api/jobs/{SEQ}/cancel")
        assert status == 200 and cancelled["cancelled"] and cancelled["frames_cancelled"] == ids[1:]
        status, summary = await api(page, "GET", f"/api/jobs/{SEQ}")
        assert summary["status"] == "cancelled"  # one done, the rest cancelled
        status, missing = await api(page, "GET", "/api/jobs/seq-ffffffffffff")
        assert status == 404 and "no sequence" in missing["error"]
        plain = await api(page, "GET", f"/api/jobs/{JOB}")
        assert plain[1]["name"] is None and plain[1]["sequence"] is None and plain[1]["frame"] is None

    run(tmp_path, scenario)


def test_a_sequence_fails_while_none_runs_and_one_failed(tmp_path):
    async def scenario(page: Page) -> None:
        frames_of(page, ("done", "failed", "cancelled"))
        assert (await api(page, "GET", f"/api/jobs/{SEQ}"))[1]["status"] == "failed"

    run(tmp_path, scenario)


def _finished(page: Page, job_id: str) -> None:
    """The job done, with the files its assembly writes."""
    page.master.store.set_status(job_id, "done", time.time())
    stem = page.master.result_path(job_id)
    stem.write_bytes(b"v/1\x01 an EXR")
    stem.with_suffix(".json").write_text('{"totals": {}}')
    Image.new("RGB", (32, 16)).save(stem.with_suffix(".png"))


def test_downloads_are_named_as_the_cli_names_them(tmp_path):
    async def scenario(page: Page) -> None:
        [frame] = frames_of(page, ("running",))
        for job_id in (JOB, frame):
            _finished(page, job_id)
        cookie, _ = await page.session()
        expected = {(JOB, "image"): "scene.exr", (JOB, "png"): "scene.png", (JOB, "report"): "scene.json",
                    (frame, "image"): "scene_0001.exr", (frame, "png"): "scene_0001.png"}
        for (job_id, kind), name in expected.items():
            response = await page.http.get(f"{page.url}/ui/api/jobs/{job_id}/download/{kind}",
                                           headers={"Cookie": cookie})
            assert response.status == 200, (kind, await response.text())
            assert response.headers["Content-Disposition"] == f'attachment; filename="{name}"'
        for path, name in ((f"/api/jobs/{JOB}/result", "scene.exr"), (f"/api/jobs/{frame}/result", "scene_0001.exr"),
                           (f"/api/jobs/{JOB}/report", "scene.json")):
            response = await page.http.get(page.url + path, headers=BEARER)
            assert response.headers["Content-Disposition"] == f'attachment; filename="{name}"'
        raw = await page.http.get(f"{page.url}/ui/api/jobs/{JOB}/download/raw", headers={"Cookie": cookie})
        assert raw.status == 404 and "not denoised" in (await raw.json())["error"]
        other = await page.http.get(f"{page.url}/ui/api/jobs/{JOB}/download/tiles", headers={"Cookie": cookie})
        assert other.status == 404
        anonymous = await page.http.get(f"{page.url}/ui/api/jobs/{JOB}/download/image", headers=BEARER)
        assert anonymous.status == 401  # the page's routes need the session, not the API's token

    run(tmp_path, scenario)


def test_a_running_or_cancelled_jobs_partial_image_and_units_read_as_they_are(tmp_path):
    async def scenario(page: Page) -> None:
        cookie, _ = await page.session()
        url = f"{page.url}/ui/api/jobs/{JOB}/download/png"
        view_url = f"{page.url}/ui/api/jobs/{JOB}"
        early = await page.http.get(url, headers={"Cookie": cookie})
        assert early.status == 409 and f"job {JOB} is running: it has no tile yet" in (await early.json())["error"]
        page.master.award(0)
        page.master.finish(0, value=0.5)
        for ended in (False, True):
            if ended:
                page.master.store.cancel(JOB, time.time())
            response = await page.http.get(url, headers={"Cookie": cookie})
            assert response.status == 200
            assert response.headers["Content-Disposition"] == 'attachment; filename="scene.partial.png"'
            pixels = np.asarray(Image.open(io.BytesIO(await response.read())).convert("RGB"))
            assert pixels.shape == (16, 32, 3)
            assert pixels[:8, :16].min() > 100 and pixels[:, 16:].max() == 0 and pixels[8:].max() == 0
            view = await (await page.http.get(view_url, headers={"Cookie": cookie})).json()
            assert view["partial"] is True
            others = "cancelled" if ended else "pending"
            assert [u["status"] for u in view["units"]] == ["done", others, others, others]

    run(tmp_path, scenario)


def test_retry_delete_and_drain_need_the_csrf_token_and_say_why_they_are_refused(tmp_path):
    async def scenario(page: Page) -> None:
        cookie, csrf = await page.session()
        base = f"{page.url}/ui/api"
        actions = [(f"{base}/jobs/{JOB}/units/0/retry", None), (f"{base}/jobs/{JOB}/delete", None),
                   (f"{base}/agents/drain", {"agent": AGENT, "drain": True})]
        for url, body in actions:
            response = await page.http.post(url, headers={"Cookie": cookie}, json=body)
            assert response.status == 403 and "CSRF" in (await response.json())["error"]
        both = {"Cookie": cookie, CSRF_HEADER: csrf}
        retry = await page.http.post(f"{base}/jobs/{JOB}/units/0/retry", headers=both)
        assert retry.status == 409 and "only a done unit is retried" in (await retry.json())["error"]
        page.master.award(0)
        page.master.finish(0)
        retry = await page.http.post(f"{base}/jobs/{JOB}/units/0/retry", headers=both)
        assert retry.status == 200 and page.master.store.units(JOB)[0].status == "pending"
        delete = await page.http.post(f"{base}/jobs/{JOB}/delete", headers=both)
        assert delete.status == 409 and "cancel it before deleting it" in (await delete.json())["error"]
        page.master.store.cancel(JOB, time.time())
        delete = await page.http.post(f"{base}/jobs/{JOB}/delete", headers=both)
        assert delete.status == 200 and not page.master.job_dir(JOB).exists()
        gone = await page.http.get(f"{base}/jobs/{JOB}", headers={"Cookie": cookie})
        assert gone.status == 404

        drain = f"{base}/agents/drain"
        bad = await page.http.post(drain, headers=both, json={"agent": AGENT, "drain": "yes"})
        assert bad.status == 400
        assert (await page.http.post(drain, headers=both, json={"agent": AGENT, "drain": True})).status == 200
        again = await page.http.post(drain, headers=both, json={"agent": AGENT, "drain": True})
        assert again.status == 409 and "already draining" in (await again.json())["error"]
        [row] = (await (await page.http.get(f"{base}/agents", headers={"Cookie": cookie})).json())["agents"]
        assert (row["state"], row["draining"], row["threads"]) == ("draining", True, 1)
        assert (await page.http.post(drain, headers=both, json={"agent": AGENT, "drain": False})).status == 200
        [row] = (await (await page.http.get(f"{base}/agents", headers={"Cookie": cookie})).json())["agents"]
        assert row["state"] == "idle"

    run(tmp_path, scenario)


def test_the_farms_logs_and_a_units_lines_of_the_masters_log(tmp_path):
    async def scenario(page: Page) -> None:
        cookie, _ = await page.session()
        logs = page.master.home / "logs"
        logs.mkdir()
        (logs / "master.log").write_text("".join(
            f"12:00:0{i} master INFO master.service: unit {u} of job {JOB}: {what}\n"
            for i, (u, what) in enumerate([(0, "awarded to a"), (1, "awarded to b"), (10, "awarded to c"),
                                           (0, "failed on a: out of memory; back to the auction")])))
        (logs / "agent-0.log").write_text("".join(f"line {i}\n" for i in range(500)))
        listed = await (await page.http.get(f"{page.url}/ui/api/logs", headers={"Cookie": cookie})).json()
        assert [entry["name"] for entry in listed["logs"]] == ["agent-0", "master"]
        tail = await (await page.http.get(f"{page.url}/ui/api/logs/agent-0?lines=3",
                                          headers={"Cookie": cookie})).json()
        assert tail == {"name": "agent-0", "lines": ["line 497", "line 498", "line 499"]}
        for path, status in (("/ui/api/logs/nothing", 404), ("/ui/api/logs/master?lines=-1", 400),
                             ("/ui/api/logs/..%2Fjobs.sqlite", 404)):
            assert (await page.http.get(page.url + path, headers={"Cookie": cookie})).status == status, path
        unit = await (await page.http.get(f"{page.url}/ui/api/jobs/{JOB}/units/0", headers={"Cookie": cookie})).json()
        said = [line.split(f"unit 0 of job {JOB}: ", 1)[1] for line in unit["log"]]
        assert said == ["awarded to a", "failed on a: out of memory; back to the auction"]
        assert (await page.http.get(f"{page.url}/ui/api/logs", headers={})).status == 401

    run(tmp_path, scenario)


def requeues_in_the_store(page: Page) -> None:
    """The stand-in master requeues as the master's store records it (the auction's decision, and its taking up
    of a job it does not know, are tests/test_auction_page.py's): a failed or cancelled job's units not done
    back to pending, the job running; else why not."""
    store = page.master.store

    async def requeue(job_id: str) -> str | None:
        status = store.job(job_id).status
        if status not in ("failed", "cancelled"):
            return f"only a failed or cancelled job is requeued: it is {status}"
        units = tuple(u.index for u in store.units(job_id) if u.status == UnitStatus.FAILED)
        store.apply([au.JobRequeued(job_id, units, len(units), "asked by the user")], time.time())
        return None

    page.master.requeue = requeue


def test_a_requeue_needs_the_csrf_token_or_the_api_token_and_says_why_it_is_refused(tmp_path):
    async def scenario(page: Page) -> None:
        requeues_in_the_store(page)
        cookie, csrf = await page.session()
        url = f"{page.url}/ui/api/jobs/{JOB}/requeue"
        refused = await page.http.post(url, headers={"Cookie": cookie})
        assert refused.status == 403 and "CSRF" in (await refused.json())["error"]
        both = {"Cookie": cookie, CSRF_HEADER: csrf}
        running = await page.http.post(url, headers=both)
        assert running.status == 409
        said = (await running.json())["error"]
        assert said == f"job {JOB}: only a failed or cancelled job is requeued: it is running"
        page.master.award(0)
        page.master.finish(0)
        page.master.store.cancel(JOB, time.time())
        requeued = await page.http.post(url, headers=both)
        assert requeued.status == 200 and await requeued.json() == {"job_id": JOB, "requeued": [JOB]}
        assert [u.status for u in page.master.store.units(JOB)] == ["done", "pending", "pending", "pending"]
        assert page.master.store.job(JOB).status == "running"
        assert (await page.http.post(f"{page.url}/api/jobs/{JOB}/requeue")).status == 401
        status, answer = await api(page, "POST", f"/api/jobs/{JOB}/requeue")
        assert status == 409 and answer["error"].endswith("it is running")
        status, answer = await api(page, "POST", "/api/jobs/job9999999/requeue")
        assert status == 404 and "no job 'job9999999'" in answer["error"]

    run(tmp_path, scenario)


def test_a_sequence_requeue_runs_its_failed_and_cancelled_frames_again(tmp_path):
    async def scenario(page: Page) -> None:
        requeues_in_the_store(page)
        ids = frames_of(page, ("done", "failed", "cancelled", "running"))
        status, answer = await api(page, "POST", f"/api/jobs/{SEQ}/requeue")
        assert status == 200 and answer == {"job_id": SEQ, "sequence": SEQ, "requeued": ids[1:3], "refused": {}}
        assert [page.master.store.job(i).status for i in ids] == ["done", "running", "running", "running"]
        status, answer = await api(page, "POST", f"/api/jobs/{SEQ}/requeue")
        assert status == 409 and answer["error"] == f"sequence {SEQ}: no frame of it failed or was cancelled"
        status, answer = await api(page, "POST", "/api/jobs/seq-ffffffffffff/requeue")
        assert status == 404 and "no sequence" in answer["error"]
        page.master.store.cancel(ids[3], time.time())  # one frame alone: its job id, from the page
        cookie, csrf = await page.session()
        response = await page.http.post(f"{page.url}/ui/api/jobs/{ids[3]}/requeue",
                                        headers={"Cookie": cookie, CSRF_HEADER: csrf})
        assert response.status == 200 and page.master.store.job(ids[3]).status == "running"

    run(tmp_path, scenario)
