"""The page's job, unit, agent and log verbs in a real browser (headless Debian chromium, tests/web_support.py)
against a real local farm (the embedded XMPP server, the master, two render agents, tiny scenes): a done job's
downloads named as the CLI names them, a unit rendered again, a cancelled job's units painted cancelled and its
partial image, a job deleted, a cancelled job requeued to its end (its done units not rendered again), an agent
drained and resumed, the logs view, a sequence as one row with its frames, and a link to no job leaving no image
of the job shown before."""

from __future__ import annotations

import io
import time

import numpy as np
import pytest
from PIL import Image
from selenium.webdriver.common.by import By
from selenium.webdriver.remote.webdriver import WebDriver
from test_web_page import JOB_TIMEOUT_S, admin_token, bundle_of, job_row, logged_in, session_cookie
from web_support import click, http, module_browser, module_farm, rows, screenshot, wait_until

from core.image.imageio import read_image
from core.model.frames import FrameRange
from core.model.job import JobSpec, RenderOptions
from farm.local import LocalFarm

pytestmark = pytest.mark.slow

TINY = {"res": "64", "spp": "16"}
LONG = {"res": "256", "spp": "1024"}
farm = pytest.fixture(scope="module", name="farm")(module_farm)
browser = pytest.fixture(scope="module", name="browser")(module_browser)


def open_job(browser: WebDriver, farm: LocalFarm, job_id: str) -> None:
    browser.get(f"{farm.url}/ui/#/job/{job_id}")
    wait_until(lambda: job_id in browser.find_element(By.ID, "job-title").text, 30, f"job {job_id}'s page")


def test_a_done_jobs_downloads_and_a_unit_rendered_again(farm, browser, tmp_path):
    logged_in(browser, farm)
    client = farm.client()
    job_id = client.submit(bundle_of(TINY), TINY, {"level": "off", "units": 4})
    assert client.wait(job_id, JOB_TIMEOUT_S)["status"] == "done"
    open_job(browser, farm, job_id)
    links = wait_until(lambda: rows(browser, "#downloads a[data-download]"), 30, "the download links")
    cookie = {"Cookie": session_cookie(browser)}
    names = {}
    for link in links:
        kind = link["data"]["download"]
        status, headers, body = http("GET", f"{farm.url}/ui/api/jobs/{job_id}/download/{kind}", headers=cookie)
        assert status == 200 and body, kind
        names[kind] = headers["Content-Disposition"]
    assert names == {"image": 'attachment; filename="cbox.exr"', "png": 'attachment; filename="cbox.png"',
                     "report": 'attachment; filename="cbox.json"'}
    screenshot(browser, tmp_path, "downloads")

    browser.execute_script("loadUnit(0)")
    click(browser, '#unit-details button[data-action="retry"]')
    wait_until(lambda: "goes back to the auction" in browser.find_element(By.ID, "message").text, 20, "the retry")
    wait_until(lambda: any(cells[3] == f"retry-{job_id}-0" and cells[1:3] == ["done", "pending"]
                           for cells in [r["cells"] for r in rows(browser, "#story-table tr")][1:]), 20,
               "the retry in the unit's story")
    assert client.wait(job_id, JOB_TIMEOUT_S)["status"] == "done"
    view = browser.find_element(By.ID, "job-view")
    wait_until(lambda: view.get_attribute("data-status") == "done"
               and len(rows(browser, "#downloads a[data-download]")) == 3, 60, "the job done again, its files again")
    browser.execute_script("loadUnit(0)")
    wait_until(lambda: len(rows(browser, "#attempts-table tr")) >= 3, 30, "the unit's second attempt")
    wait_until(lambda: (log := browser.find_element(By.ID, "unit-log").text)  # redrawn as the job polls
               and f"unit 0 of job {job_id}" in log and "to be rendered again" in log, 30, "the retry in its log")
    screenshot(browser, tmp_path, "unit-retried")


def test_a_cancelled_jobs_units_read_cancelled_its_partial_image_and_its_delete(farm, browser, tmp_path):
    logged_in(browser, farm)
    client = farm.client()
    job_id = client.submit(bundle_of(LONG), LONG, {"level": "off", "units": 24})
    wait_until(lambda: any(j["units_done"] for j in client.jobs() if j["job_id"] == job_id), JOB_TIMEOUT_S,
               "a first tile")
    assert client.cancel(job_id) is True
    open_job(browser, farm, job_id)
    wait_until(lambda: browser.find_element(By.ID, "job-view").get_attribute("data-status") == "cancelled", 30,
               "the job cancelled")
    legend = [r["data"]["state"] for r in rows(browser, "#legend span[data-state]")]
    assert legend == ["pending", "awarded", "done", "failed", "cancelled"]
    assert browser.find_element(By.ID, "legend").text.split() == ["queued", "rendering", "done", "failed", "cancelled"]
    units = browser.execute_script("return state.job.units.map((u) => u.status)")
    assert "cancelled" in units and "failed" not in units and "done" in units, units
    assert "partial" in browser.find_element(By.ID, "job-summary").text
    links = wait_until(lambda: rows(browser, "#downloads a[data-download]"), 20, "the partial image's links")
    assert [link["data"]["download"] for link in links] == ["image", "png", "report"]
    status, headers, png = http("GET", f"{farm.url}/ui/api/jobs/{job_id}/download/png",
                                headers={"Cookie": session_cookie(browser)})
    assert status == 200 and headers["Content-Disposition"] == 'attachment; filename="cbox.partial.png"'
    assert Image.open(io.BytesIO(png)).size == (256, 256)
    status, headers, exr = http("GET", f"{farm.url}/ui/api/jobs/{job_id}/download/image",
                                headers={"Cookie": session_cookie(browser)})
    assert status == 200 and headers["Content-Disposition"] == 'attachment; filename="cbox.partial.exr"'
    (tmp_path / "partial.exr").write_bytes(exr)
    assert read_image(tmp_path / "partial.exr").shape == (256, 256, 3)
    screenshot(browser, tmp_path, "cancelled-partial")

    browser.get(f"{farm.url}/ui/#/jobs")
    delete = f'#jobs-table tr[data-job="{job_id}"] button[data-action="delete"]'
    click(browser, delete)
    wait_until(lambda: browser.find_element(By.CSS_SELECTOR, delete).text == "Confirm delete", 10, "armed delete")
    click(browser, delete)
    wait_until(lambda: not browser.find_elements(By.CSS_SELECTOR, f'#jobs-table tr[data-job="{job_id}"]'), 30,
               "the job gone from the table")
    assert job_id not in {j["job_id"] for j in client.jobs()} and not (farm.home / "jobs" / job_id).exists()


def test_a_cancelled_job_requeued_from_the_page_finishes_without_rendering_its_done_units_again(farm, browser,
                                                                                                  tmp_path):
    logged_in(browser, farm)
    client = farm.client()
    spec, options = {"res": "128", "spp": "256"}, {"level": "off", "units": 16}
    job_id = client.submit(bundle_of(spec), spec, options)
    wait_until(lambda: client.status(job_id)["units_done"], JOB_TIMEOUT_S, "a first tile")
    assert client.cancel(job_id) is True

    def attempts() -> dict[int, list[str]]:
        return {i: [a["outcome"] for a in client.unit(job_id, i)["attempts"]] for i in range(16)}

    before = {i for i, outcomes in attempts().items() if "done" in outcomes}
    assert 0 < len(before) < 16, before
    open_job(browser, farm, job_id)
    view = browser.find_element(By.ID, "job-view")
    wait_until(lambda: view.get_attribute("data-status") == "cancelled", 30, "the job cancelled")
    click(browser, '#job-summary button[data-action="requeue"]')
    wait_until(lambda: "runs again" in browser.find_element(By.ID, "message").text, 20, "the requeue said")
    wait_until(lambda: view.get_attribute("data-status") in ("running", "done"), 30, "the job running again")
    assert client.wait(job_id, JOB_TIMEOUT_S)["status"] == "done"
    wait_until(lambda: view.get_attribute("data-status") == "done" and browser.execute_script(
        "return document.getElementById('preview').dataset.final") == "1", 60, "the image filled, final")
    after = attempts()
    assert all(outcomes.count("done") == 1 for outcomes in after.values()), after
    assert all(after[i] == ["done"] for i in before), after  # done before the cancel: never awarded again
    screenshot(browser, tmp_path, "requeued-done")
    requeued = read_image(client.result(job_id, tmp_path / "requeued.exr"))
    whole_id = client.submit(bundle_of(spec), spec, options)  # the same job, never cancelled
    assert client.wait(whole_id, JOB_TIMEOUT_S)["status"] == "done"
    whole = read_image(client.result(whole_id, tmp_path / "whole.exr"))
    assert requeued.shape == whole.shape and np.isfinite(requeued).all()
    assert abs(requeued.mean() - whole.mean()) < 0.05 * whole.mean()  # the same image, other samples


def test_an_agent_drained_gets_no_unit_and_resumed_it_does(farm, browser, tmp_path):
    logged_in(browser, farm)
    click(browser, "#nav-agents")
    agents = wait_until(lambda: len(found := rows(browser, "#agents-table tbody tr")) == 2 and found, 20, "agents")
    jid = sorted(a["data"]["agent"] for a in agents)[0]
    row = f'#agents-table tr[data-agent="{jid}"]'
    click(browser, f'{row} button[data-action="drain"]')
    wait_until(lambda: browser.find_element(By.CSS_SELECTOR, row).get_attribute("data-state") == "draining", 20,
               "the agent draining")
    screenshot(browser, tmp_path, "agent-draining")
    client = farm.client()
    job_id = client.submit(bundle_of(TINY), TINY, {"level": "off", "units": 4})
    assert client.wait(job_id, JOB_TIMEOUT_S)["status"] == "done"
    rendered_by = {a["agent"] for i in range(client.status(job_id)["units_total"])
                   for a in client.unit(job_id, i)["attempts"]}
    assert rendered_by and jid not in rendered_by, rendered_by
    click(browser, f'{row} button[data-action="resume"]')
    wait_until(lambda: browser.find_element(By.CSS_SELECTOR, row).get_attribute("data-state") == "idle", 20,
               "the agent resumed")


def test_the_logs_view_shows_each_processs_log(farm, browser):
    logged_in(browser, farm)
    click(browser, "#nav-logs")
    names = wait_until(lambda: [o.get_attribute("value") for o in browser.find_elements(By.CSS_SELECTOR,
                                                                                         "#log-name option")],
                       20, "the logs listed")
    assert "master" in names and "agent-0" in names, names
    browser.execute_script("const s = document.getElementById('log-name'); s.value = 'master';"
                           "s.dispatchEvent(new Event('change'));")
    text = wait_until(lambda: (t := browser.find_element(By.ID, "log-text")).get_attribute("data-log") == "master"
                      and t.text, 20, "the master's log")
    assert "master" in text


def test_a_sequence_is_one_row_its_view_lists_its_frames_and_no_job_leaves_no_image(farm, browser, tmp_path):
    logged_in(browser, farm)
    client = farm.client()
    # the frame number drives a parameter cbox.xml has (its spp): each frame is a job of its own
    spec = JobSpec({"res": "32"}, RenderOptions(level="off", units=2), "orbit", FrameRange("spp", 1, 2))
    answer = client.submit_spec(bundle_of({"res": "32", "spp": "1"}), spec)
    sequence = answer["sequence"]
    for job in answer["jobs"]:
        assert client.wait(job["job_id"], JOB_TIMEOUT_S)["status"] == "done"
    browser.get(f"{farm.url}/ui/#/jobs")
    wait_until(lambda: "2/2 frames done" in job_row(browser, sequence).text, 30, "the sequence's row")
    assert not browser.find_elements(By.CSS_SELECTOR, f'#jobs-table tr[data-job="{answer["jobs"][0]["job_id"]}"]')
    assert "orbit" in job_row(browser, sequence).text
    cells = rows(browser, f'#jobs-table tr[data-job="{sequence}"]')[0]["cells"]
    assert "1..2" in cells[4] and "res=32 spp=1..2" in cells[6], cells  # spp and -D over the frames
    click(browser, f'#jobs-table tr[data-job="{sequence}"] a.job-link')
    frames = wait_until(lambda: rows(browser, "#frames-table tbody tr"), 30, "the frames")
    assert [f["data"]["frame"] for f in frames] == ["1", "2"] and all(f["data"]["status"] == "done" for f in frames)
    screenshot(browser, tmp_path, "sequence")

    open_job(browser, farm, answer["jobs"][1]["job_id"])
    wait_until(lambda: browser.execute_script("return document.getElementById('preview').naturalWidth") == 32, 30,
               "the frame's image")
    browser.get(f"{farm.url}/ui/#/job/nothing0here")
    wait_until(lambda: browser.find_element(By.ID, "no-job").text == "no job nothing0here", 20, "no job")
    assert browser.execute_script("return document.getElementById('preview').getAttribute('src')") is None
    assert not browser.find_element(By.ID, "job-stage-part").is_displayed()
    time.sleep(1)
    assert admin_token(farm) not in browser.current_url
