"""The web page in a real browser (headless Debian chromium, see tests/web_support.py) against a real local
farm: the embedded XMPP server, the master and two render agents as processes (1 Dr.Jit thread each), tiny
scenes. The tests log in through the form, watch a job render until its image is complete (the page
updated by server-sent events, never reloaded), click a unit and read its features, fired rules, agent and
attempts, colour the partition by the rules' outputs and inputs, read the report and the agents, cancel and
re-submit jobs from the page (denoised too: its preview denoised as its result is), and check the refusals:
no cookie, an agent's award token, no CSRF token, a denoise that is not true or false.
Screenshots go to each test's temporary folder."""

from __future__ import annotations

import io
import json
import re
import secrets
import sqlite3
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image
from selenium.webdriver.common.action_chains import ActionChains
from selenium.webdriver.common.by import By
from selenium.webdriver.remote.webdriver import WebDriver
from selenium.webdriver.support.ui import Select
from web_support import click, http, module_browser, module_farm, rows, screenshot, wait_until

from agents.render_agent import host_name
from core.model.geometry import filter_reach
from core.scene.bundle import make_bundle
from farm.local import LocalFarm
from master.store import JobStore
from master.web.auth import COOKIE, CSRF_HEADER
from master.web.preview import write_preview
from planning.pipeline import AOV_PASS_FILE

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parent.parent
SCENE = REPO / "scenes" / "cbox.xml"
SMALL = {"res": "128", "spp": "1024"}  # the job watched to the end (~10 units at level S)
LONG = {"res": "256", "spp": "1024"}  # a job that is still running when the page cancels it
JOB_TIMEOUT_S = 300.0


def bundle_of(defines: dict[str, str]) -> bytes:
    with tempfile.TemporaryDirectory() as tmp:
        return make_bundle(SCENE, defines, Path(tmp) / "b.tar").path.read_bytes()


farm = pytest.fixture(scope="module", name="farm")(module_farm)
browser = pytest.fixture(scope="module", name="browser")(module_browser)


def admin_token(farm: LocalFarm) -> str:
    return (farm.home / "admin.token").read_text().strip()


def log_in(driver: WebDriver, farm: LocalFarm, token: str | None = None) -> None:
    """Through the login form, as a person does."""
    driver.get(farm.url + "/ui/")
    wait_until(lambda: driver.find_element(By.ID, "token"), 20, "the login form")
    field = driver.find_element(By.ID, "token")
    field.clear()
    field.send_keys(token if token is not None else admin_token(farm))
    driver.find_element(By.ID, "login-button").click()


def logged_in(driver: WebDriver, farm: LocalFarm) -> None:
    """The page open with a session (logging in if the browser has none)."""
    driver.get(farm.url + "/ui/#/jobs")
    if "/ui/login" in driver.current_url:
        log_in(driver, farm)
    wait_until(lambda: driver.find_element(By.ID, "live").text == "live", 20, "the event stream")


def session_cookie(driver: WebDriver) -> str:
    cookie = driver.get_cookie(COOKIE)
    assert cookie is not None, driver.get_cookies()
    return f"{COOKIE}={cookie['value']}"


def job_row(driver: WebDriver, job_id: str):
    return driver.find_element(By.CSS_SELECTOR, f'#jobs-table tr[data-job="{job_id}"]')


def test_login_form_refuses_a_wrong_token_and_sets_a_strict_httponly_cookie(farm, browser, tmp_path):
    browser.delete_all_cookies()
    log_in(browser, farm, token="not-the-token")
    error = wait_until(lambda: browser.find_element(By.ID, "login-error").text, 20, "the login error")
    assert "not the admin token" in error and browser.get_cookie(COOKIE) is None
    screenshot(browser, tmp_path, "login-refused")
    log_in(browser, farm)
    wait_until(lambda: browser.find_element(By.ID, "live").text == "live", 20, "the page and its event stream")
    assert browser.current_url.startswith(farm.url + "/ui/") and admin_token(farm) not in browser.current_url
    cookie = browser.get_cookie(COOKIE)
    assert cookie["httpOnly"] is True and cookie["sameSite"] == "Strict" and cookie["path"] == "/ui"
    assert browser.execute_script("return document.cookie") == ""  # HttpOnly: no script reads it
    screenshot(browser, tmp_path, "jobs-empty")


def test_an_eta_counts_down_between_events_but_not_while_the_farm_is_paused(farm, browser):
    logged_in(browser, farm)
    shown = browser.execute_script("""
        const ago = Date.now() / 1000 - 30;  // the job's row arrived 30 s ago, with 100 s to go
        const running = eta({status: "running", eta_s: 100, receivedAt: ago});
        const paused = eta({status: "running", eta_s: 100, receivedAt: ago, paused: "the disk is full"});
        document.body.append(running, paused);
        const before = [running.textContent, paused.textContent];
        tickEtas();
        const after = [running.textContent, paused.textContent];
        running.remove(); paused.remove();
        return [...before, ...after];""")
    assert shown == ["1 min 40 s", "1 min 40 s", "1 min 10 s", "1 min 40 s"]


def test_a_noise_jobs_eta_is_a_lower_bound_and_a_cancelled_progressive_job_says_what_fell_short(farm, browser):
    """A noise goal's ETA counts only the passes ordered so far: "at least", still counting down; a
    progressive job that ended early names its units short of their goal, beside its passes."""
    logged_in(browser, farm)
    shown = browser.execute_script("""
        const ago = Date.now() / 1000 - 30;  // the row arrived 30 s ago, with at least 100 s to go
        const span = eta({status: "running", eta_s: 100, eta_at_least: true, receivedAt: ago});
        document.body.append(span);
        const before = span.textContent;
        tickEtas();
        const after = span.textContent;
        span.remove();
        const passes = {done: 9, ordered: 30, spp_mean: 88.5, goal: "noise", share: 0.625};
        const bar = progressBar({units_done: 2, units_total: 6, units_failed: 4, passes});
        const plain = progressBar({units_done: 2, units_total: 6, units_failed: 4, passes: null});
        return [before, after, bar.querySelector(".bar-text").textContent,
                plain.querySelector(".bar-text").textContent, bar.querySelectorAll(".bar span").length,
                bar.querySelector(".bar-passes").style.width];""")
    assert shown == ["at least 1 min 40 s", "at least 1 min 10 s",
                     "2/6 units, 9/30 passes, 88.5 spp, 4 left short of their goal", "2/6 units, 4 left unrendered", 2,
                     "62.5%"]  # the passes' share of the job's work, not 9 of 30 passes


def test_a_running_jobs_time_counts_up_between_events_and_an_ended_ones_stays(farm, browser):
    """The master sends a job again only when a row of it changes: its time froze between units."""
    logged_in(browser, farm)
    shown = browser.execute_script("""
        const ago = Date.now() / 1000 - 30;  // the row arrived 30 s ago, 10 s into the job
        const running = el("td", {}, elapsed({status: "running", elapsed_s: 10, finished: null, receivedAt: ago}));
        const ended = el("td", {}, elapsed({status: "done", elapsed_s: 10, finished: 1, receivedAt: ago}));
        document.body.append(running, ended);
        tickEtas();
        const after = [running.textContent, ended.textContent];
        running.remove(); ended.remove();
        return after;""")
    assert shown[0] in ("40.0 s", "40.1 s") and shown[1] == "10.0 s", shown


@pytest.mark.parametrize("link", ["nonexistent1", ".hidden", "a" * 130, "%zz"])
def test_a_link_to_no_job_says_so_and_leaves_nothing_of_another_job(farm, browser, link):
    """An id the master could never have made was retried every 3 s ('reconnecting' for ever) under the
    title of the job shown before."""
    logged_in(browser, farm)
    browser.get(farm.url + "/ui/#/job/shown0before")
    wait_until(lambda: "no job" in browser.find_element(By.ID, "job-summary").text, 20, "the first refusal")
    browser.get(farm.url + f"/ui/#/job/{link}")
    summary = wait_until(lambda: (t := browser.find_element(By.ID, "job-summary").text) and "no job" in t and t,
                         20, f"the page to say there is no job {link!r}")
    assert "shown0before" not in summary and "shown0before" not in browser.find_element(By.ID, "job-title").text
    time.sleep(4)  # past the page's 3 s retry
    assert browser.find_element(By.ID, "live").text == "live"


def test_watch_a_job_render_until_its_image_is_complete_then_click_a_unit(farm, browser, tmp_path):
    logged_in(browser, farm)
    browser.execute_script("window.__notReloaded = true;")
    browser.get_log("browser")  # drained: what an earlier test logged (a refused login) is not this one's
    job_id = farm.client().submit(bundle_of(SMALL), SMALL, {"level": "S", "units": 8})
    click(browser, f'#jobs-table tr[data-job="{job_id}"] a.job-link', 30)  # the new job, pushed by the events
    view = browser.find_element(By.ID, "job-view")
    preview = browser.find_element(By.ID, "preview")
    seen: list[int] = []
    deadline = time.monotonic() + JOB_TIMEOUT_S
    while time.monotonic() < deadline:
        tiles = int(preview.get_attribute("data-tiles") or 0)
        if not seen or tiles != seen[-1]:
            seen.append(tiles)
            if 0 < tiles < int(view.get_attribute("data-units-total") or 0):
                screenshot(browser, tmp_path, f"job-partial-{tiles}")
        if preview.get_attribute("data-final") == "1":
            seen.append(int(preview.get_attribute("data-tiles")))  # the final image (read after the flag)
            break
        time.sleep(0.2)
    else:
        raise AssertionError(f"the page never showed job {job_id}'s final image (tiles seen: {seen})")
    screenshot(browser, tmp_path, "job-done")
    total = int(view.get_attribute("data-units-total"))
    assert view.get_attribute("data-status") == "done" and int(view.get_attribute("data-units-done")) == total
    assert seen == sorted(seen) and len(set(seen)) >= 2 and seen[-1] == total, seen  # it grew, live
    assert browser.execute_script("return window.__notReloaded === true")  # by events, not reloads
    assert browser.execute_script("return document.getElementById('preview').naturalWidth") == 128
    canvas = browser.find_element(By.ID, "overlay")
    assert canvas.get_attribute("data-done") == str(total)

    # the image the page shows is the job's final image, complete (no unit of it left black)
    cookie = {"Cookie": session_cookie(browser)}
    status, _, png = http("GET", f"{farm.url}/ui/api/jobs/{job_id}/preview.png", headers=cookie)
    assert status == 200 and png == (farm.home / "jobs" / job_id / "result.png").read_bytes()
    image = np.asarray(Image.open(io.BytesIO(png)))
    assert image.shape == (128, 128, 3)
    units = json.loads(http("GET", f"{farm.url}/ui/api/jobs/{job_id}", headers=cookie)[2])["units"]
    assert len(units) == total
    for unit in units:
        x, y, w, h = unit["rect"]
        assert image[y:y + h, x:x + w].max() > 0, unit

    # a click on the partition: that unit's features, rules, agent and attempts
    ActionChains(browser).move_to_element_with_offset(canvas, 0, 0).click().perform()
    wait_until(lambda: rows(browser, "#unit-table tr"), 20, "the unit's details")
    cells = {row["cells"][0]: row["cells"][1] for row in rows(browser, "#unit-table tr")}
    for field in ("C (complexity)", "S (size, px)", "Nd (neighbour difference)", "spp", "depth", "band"):
        assert cells[field] not in ("", "-"), (field, cells)
    assert cells["agent"].startswith("agent-") and cells["state"] == "done", cells
    fired = [row["text"] for row in rows(browser, "#fired-rules li")]
    assert fired and all(" IF " in li and " THEN " in li for li in fired), fired
    attempts = [row["cells"] for row in rows(browser, "#attempts-table tr")][1:]
    assert attempts and any(row[3] == "done" for row in attempts), attempts
    story = [row["cells"] for row in rows(browser, "#story-table tr")][1:]  # time, from, to, stimulus
    assert story and story[-1][1:3] == ["awarded", "done"] and story[-1][3].startswith("tile-"), story
    assert browser.execute_script("return document.getElementById('unit-title').textContent").startswith("Unit ")
    screenshot(browser, tmp_path, "unit-details")

    # colour by the rules' outputs and inputs
    for mode in ("spp", "depth", "band", "C", "Nd"):
        Select(browser.find_element(By.ID, "colour-by")).select_by_value(mode)
        assert canvas.get_attribute("data-colour") == mode
        assert browser.execute_script("return document.getElementById('legend-min').textContent") != "-"
        screenshot(browser, tmp_path, f"colour-{mode}")

    # the report of the finished job (and what the farm does not measure per job)
    report = wait_until(lambda: browser.find_element(By.ID, "report").is_displayed()
                        and browser.find_element(By.ID, "report").text, 30, "the report")
    assert "units" in report and "no per-job accuracy report" in report

    # the agents: both registered, the units shared between them
    click(browser, "#nav-agents")
    agents = wait_until(lambda: len(found := rows(browser, "#agents-table tbody tr")) == 2 and found, 20,
                        "two agents")
    assert {a["data"]["state"] for a in agents} <= {"idle", "rendering"}, agents
    assert sum(int(a["cells"][5]) for a in agents) >= total  # units done, over both
    assert all(a["cells"][7].endswith("s ago") for a in agents), agents
    assert all(a["cells"][1] == host_name() and a["cells"][2] == "1" and a["cells"][4].endswith(" x reference")
               for a in agents), agents  # host, threads, speed
    screenshot(browser, tmp_path, "agents")
    errors = [e for e in browser.get_log("browser") if e["level"] == "SEVERE"]
    assert not errors, errors  # no script error, no resource the page's CSP refused


def test_an_adaptive_jobs_page_says_how_its_samples_were_shared(farm, browser, tmp_path):
    """An adaptive job's page says what `quekaro status JOB` says of its plan: the level's samples from the
    rules, how the pre-pass shared them, and each unit's first pass."""
    logged_in(browser, farm)
    client = farm.client()
    job_id = client.submit(bundle_of(SMALL), SMALL, {"level": "S", "units": 4, "adaptive": True})
    click(browser, f'#jobs-table tr[data-job="{job_id}"] a.job-link', 30)
    shown = wait_until(lambda: browser.find_element(By.ID, "job-adaptive").text, 30, "the job's shares")
    shares = client.status(job_id)["adaptive"]
    assert shares["unit_spp"] and len(shares["unit_spp"]) == 4, shares
    assert f"{shares['mean_spp']} spp per pixel from the rules" in shown, shown
    assert f"each unit renders {shares['first_spp']} spp uniformly" in shown, shown
    assert ("shared by the pre-pass's noise" in shown) == shares["adapted"], shown
    screenshot(browser, tmp_path, "adaptive-job")
    assert client.wait(job_id, JOB_TIMEOUT_S)["status"] == "done"


def _page_progress(browser: WebDriver) -> dict[str, Any]:
    """The job page's progress, read at one instant by the page itself."""
    return browser.execute_script("""
        const view = document.getElementById("job-view");
        const summary = document.getElementById("job-summary");
        const bar = summary.querySelector(".bar-text");
        return {status: view.dataset.status, done: Number(view.dataset.unitsDone),
                total: Number(view.dataset.unitsTotal), passes: view.dataset.passesDone,
                text: bar ? bar.textContent : "", summary: summary.textContent};""")


def test_a_progressive_jobs_page_and_status_count_its_units_and_show_its_passes(farm, browser, tmp_path):
    """A job in passes keeps each pass as a unit row: the page's bar counted those (done and total growing
    as passes were ordered). It counts the image's units, a unit done once all its passes are, and shows
    the passes and the mean spp beside them; `quekaro status` says the same."""
    logged_in(browser, farm)
    defines = {"res": "256", "spp": "256"}
    job_id = farm.client().submit(bundle_of(defines), defines, {"level": "off", "progressive": True, "units": 6})
    with JobStore(farm.home / "jobs.sqlite", readonly=True) as store:
        planned = len(store.job(job_id).planned_units)
    click(browser, f'#jobs-table tr[data-job="{job_id}"] a.job-link', 30)
    seen: list[dict[str, Any]] = []
    deadline = time.monotonic() + JOB_TIMEOUT_S
    while time.monotonic() < deadline and not (seen and seen[-1]["status"] == "done"):
        shown = wait_until(lambda: (p := _page_progress(browser))["text"] and p, 30, "the job's progress")
        if not seen or shown != seen[-1]:
            seen.append(shown)
            if shown["status"] == "running" and shown["passes"] not in ("", "0"):
                screenshot(browser, tmp_path, f"progressive-{shown['passes']}-passes")
        time.sleep(0.2)
    assert seen[-1]["status"] == "done", seen[-1]
    screenshot(browser, tmp_path, "progressive-done")
    running = [s for s in seen if s["status"] == "running" and s["passes"] not in ("", "0")]
    assert running, seen  # the page showed the job between its first pass and its end
    assert all(s["total"] == planned for s in seen), (planned, seen)  # its units, never its passes
    dones = [s["done"] for s in seen]
    assert dones == sorted(dones) and dones[-1] == planned
    for s in running:
        passes = re.search(rf"^{s['done']}/{planned} units, (\d+)/(\d+) passes, [\d.]+ spp$", s["text"])
        assert passes, s
        # 128, 64, 32, 32: a farm's pass holds at least 2^18 samples (Config.pass_samples)
        assert int(passes.group(1)) == int(s["passes"]) and int(passes.group(2)) >= 4 * planned, s
        assert int(passes.group(1)) > s["done"], s  # a unit is done only once all its passes are
    assert any(re.search(r"ETA\s*\d", s["summary"]) for s in running), running  # a figure, counting down
    final = re.search(rf"^{planned}/{planned} units, (\d+)/(\d+) passes, ([\d.]+) spp$", seen[-1]["text"])
    assert final and float(final.group(3)) == 256, seen[-1]  # its budget: an extra pass stands in, never adds
    assert final.group(1) == final.group(2), seen[-1]  # the passes it kept all done: those withdrawn are gone
    report = wait_until(lambda: browser.find_element(By.ID, "report").is_displayed()
                        and browser.find_element(By.ID, "report").text, 30, "the report")
    assert re.search(rf"passes: each unit's own samples; stopped: .+ \({final.group(1)} passes\)", report), report
    # the partition is the image's units, each with its passes together, not one rectangle a pass
    canvas = browser.find_element(By.ID, "overlay")
    assert (canvas.get_attribute("data-units"), canvas.get_attribute("data-done")) == (str(planned), str(planned))
    ActionChains(browser).move_to_element_with_offset(canvas, 0, 0).click().perform()
    wait_until(lambda: rows(browser, "#unit-table tr"), 20, "the unit's details")
    cells = {row["cells"][0]: row["cells"][1] for row in rows(browser, "#unit-table tr")}
    assert cells["state"] == "done" and cells["spp"] == "256" and int(cells["passes done"]) >= 4, cells
    attempts = [row["cells"] for row in rows(browser, "#attempts-table tr")][1:]  # pass, agent, ..., outcome
    assert len({row[0] for row in attempts if row[4] == "done"}) == int(cells["passes done"]), attempts
    status = subprocess.run([sys.executable, "-m", "quekaro", "status", job_id, "--home", str(farm.home)],
                            capture_output=True, text=True, timeout=60, cwd=REPO)
    assert status.returncode == 0, status.stderr
    assert re.search(rf"{job_id}\s+done\s+{planned}/{planned} units, {final.group(1)}/{final.group(2)} passes, "
                     rf"{final.group(3)} spp\s+agents busy", status.stdout), status.stdout


def test_a_link_to_a_job_opened_without_a_session_leads_to_that_job_after_the_login(farm, browser):
    """The view is in the URL's fragment (#/job/ID), which no request carries: the login ended on the
    job list."""
    client = farm.client()
    job_id = client.submit(bundle_of(SMALL), SMALL, {"level": "off", "units": 4})
    # From the login page (no event stream): on the app's page, the cookie's removal could send the page
    # of the previous test's job to the login first (its stream's 401), racing this test's navigation.
    browser.get(f"{farm.url}/ui/login")
    browser.delete_all_cookies()
    browser.get(f"{farm.url}/ui/#/job/{job_id}")
    wait_until(lambda: browser.find_element(By.ID, "token"), 20, "the login form")
    assert browser.current_url == f"{farm.url}/ui/login#/job/{job_id}", browser.current_url
    browser.find_element(By.ID, "token").send_keys(admin_token(farm))
    browser.find_element(By.ID, "login-button").click()
    title = wait_until(lambda: job_id in browser.find_element(By.ID, "job-title").text and
                       browser.find_element(By.ID, "job-title").text, 30, "the job's own page")
    assert browser.current_url == f"{farm.url}/ui/#/job/{job_id}" and job_id in title
    assert not browser.find_element(By.ID, "job-view").get_attribute("hidden")
    assert client.wait(job_id, JOB_TIMEOUT_S)["status"] == "done"


def test_cancel_and_resubmit_from_the_page(farm, browser, tmp_path):
    logged_in(browser, farm)
    client = farm.client()
    job_id = client.submit(bundle_of(LONG), LONG, {"level": "off", "units": 24})
    wait_until(lambda: job_row(browser, job_id).get_attribute("data-status") == "running", 30,
               "the long job running in the table")
    cancel = f'#jobs-table tr[data-job="{job_id}"] button[data-action="cancel"]'
    click(browser, cancel)  # arms the button
    wait_until(lambda: browser.find_element(By.CSS_SELECTOR, cancel).text == "Confirm cancel", 10, "armed cancel")
    screenshot(browser, tmp_path, "cancel-armed")
    click(browser, cancel)
    wait_until(lambda: job_row(browser, job_id).get_attribute("data-status") == "cancelled", 30,
               "the job cancelled on the page")
    assert client.status(job_id)["status"] == "cancelled"
    assert client.cancel(job_id) is False  # it had already ended (the master said True to every cancel)
    wait_until(lambda: "left unrendered" in job_row(browser, job_id).text, 10, "the units the cancel left")
    assert "failed" not in job_row(browser, job_id).text  # it said "24 failed"
    screenshot(browser, tmp_path, "cancelled")

    before = {j["job_id"] for j in client.jobs()}
    click(browser, f'#jobs-table tr[data-job="{job_id}"] button[data-action="resubmit"]')
    again = wait_until(lambda: {j["job_id"] for j in client.jobs()} - before, 120, "the job submitted again")
    [new_id] = again
    new = client.status(new_id)
    assert new["scene"] == client.status(job_id)["scene"] and new["level"] == "off"
    wait_until(lambda: job_row(browser, new_id), 30, "the re-submitted job on the page")
    assert new_id in browser.execute_script("return document.getElementById('message').textContent")
    screenshot(browser, tmp_path, "resubmitted")
    assert client.cancel(new_id) is True  # the farm has nothing left to render after this test
    assert client.cancel(new_id) is False


def _previews(farm: LocalFarm, job_id: str, folder: Path) -> tuple[np.ndarray, np.ndarray]:
    """The finished job's tiles as the page's preview composes them: (raw, denoised with its AOV pass)."""
    with JobStore(farm.home / "jobs.sqlite", readonly=True) as store:
        plan, results = store.job(job_id).plan, store.results(job_id)
    size, reach = (plan["width"], plan["height"]), filter_reach(plan["filter_radius"])
    aov = farm.home / "jobs" / job_id / AOV_PASS_FILE
    return tuple(np.asarray(Image.open(write_preview(folder / f"{name}.png", *size, results, reach, aov=a)), float)
                 for name, a in (("raw", None), ("denoised", aov)))


def test_resubmit_a_job_denoised_from_the_page(farm, browser, tmp_path):
    """The new job's options say denoise, it finishes with a raw image beside its own, its page says so,
    and its preview (the tiles composed and denoised) is its denoised result, not the raw composition."""
    logged_in(browser, farm)
    client = farm.client()
    defines = {"res": "64", "spp": "16"}
    job_id = client.submit(bundle_of(defines), defines, {"level": "off", "units": 4})
    assert client.wait(job_id, JOB_TIMEOUT_S)["status"] == "done"
    before = {j["job_id"] for j in client.jobs()}
    button = f'#jobs-table tr[data-job="{job_id}"] button[data-action="resubmit-denoise"]'
    assert wait_until(lambda: browser.find_element(By.CSS_SELECTOR, button).text, 20, "the button") \
        == "Re-submit denoised"
    click(browser, button)
    [new_id] = wait_until(lambda: {j["job_id"] for j in client.jobs()} - before, 120, "the job submitted denoised")
    cookie = {"Cookie": session_cookie(browser)}
    assert json.loads(http("GET", f"{farm.url}/ui/api/jobs/{new_id}", headers=cookie)[2])["options"]["denoise"]
    assert client.wait(new_id, JOB_TIMEOUT_S)["status"] == "done"
    status, _, raw = http("GET", f"{farm.url}/api/jobs/{new_id}/raw",
                          headers={"Authorization": f"Bearer {admin_token(farm)}"})
    assert status == 200 and raw[:4] == b"\x76\x2f\x31\x01"  # an OpenEXR file

    browser.get(f"{farm.url}/ui/#/job/{new_id}")
    shown = wait_until(lambda: "the image is denoised" in (t := browser.find_element(By.ID, "job-denoise").text)
                       and t, 30, "the job's page saying it is denoised")
    assert shown.startswith("denoised") and "raw one is kept" in shown
    again = '#job-summary button[data-action="resubmit-denoise"]'
    assert browser.find_element(By.CSS_SELECTOR, again).text == "Re-submit without denoising"
    screenshot(browser, tmp_path, "denoised-job")

    raw_preview, denoised = _previews(farm, new_id, tmp_path)
    result = np.asarray(Image.open(farm.home / "jobs" / new_id / "result.png"), float)
    assert np.abs(denoised - result).max() <= 1, np.abs(denoised - result).max()
    assert np.abs(raw_preview - result).mean() > 3 * np.abs(denoised - result).mean() + 1


def test_no_cookie_no_page_and_an_award_token_or_a_missing_csrf_token_gets_nothing(farm, browser):
    logged_in(browser, farm)
    # The store keeps an award token's sha256 only (schema 5): a token of an award's shape stands in here;
    # a live award token's refusal is tests/test_web_http.py's (its store records one).
    with sqlite3.connect(f"file:{farm.home / 'jobs.sqlite'}?mode=ro", uri=True) as db:
        [job_id] = db.execute("SELECT job_id FROM attempts ORDER BY id LIMIT 1").fetchone()
    award = secrets.token_hex(16)
    status, headers, _ = http("GET", farm.url + "/ui/")
    assert status == 303 and headers["Location"] == "/ui/login"
    for path in ("/ui/api/jobs", "/ui/api/agents", f"/ui/api/jobs/{job_id}", "/ui/events"):
        for token_headers in ({}, {"X-Quekaro-Token": award}, {"Authorization": f"Bearer {award}"}):
            status, _, body = http("GET", farm.url + path, headers=token_headers)
            assert status == 401 and b"log in first" in body, (path, token_headers, status)
    status, headers, _ = http("POST", farm.url + "/ui/login", data=f"token={award}".encode(),
                              headers={"Content-Type": "application/x-www-form-urlencoded"})
    assert status == 401 and "Set-Cookie" not in headers
    cookie = session_cookie(browser)
    cancel = f"{farm.url}/ui/api/jobs/{job_id}/cancel"
    for extra in ({}, {CSRF_HEADER: "forged"}):
        status, _, body = http("POST", cancel, headers={"Cookie": cookie, **extra})
        assert status == 403 and b"CSRF" in body
    csrf = browser.find_element(By.CSS_SELECTOR, 'meta[name="csrf-token"]').get_attribute("content")
    status, _, _ = http("POST", cancel, headers={CSRF_HEADER: csrf})  # the token without the cookie
    assert status == 401
    status, _, body = http("POST", f"{farm.url}/ui/api/jobs/{job_id}/resubmit", data=b'{"denoise": "yes"}',
                           headers={"Cookie": cookie, CSRF_HEADER: csrf, "Content-Type": "application/json"})
    assert status == 400 and b"denoise: 'yes' is not true or false" in body
