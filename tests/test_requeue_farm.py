"""Requeue and drain on a real local farm (the embedded XMPP server, the master, two render agents): `quekaro
requeue` runs a cancelled job again, its done units not rendered twice, and refuses a done job saying why; an
agent drained from the page stays drained through a master restart (the store keeps it, and the restarted
master drains it again as it comes back)."""

from __future__ import annotations

import json
import subprocess
import sys
import urllib.parse
from collections.abc import Iterator

import pytest
from test_web_page import JOB_TIMEOUT_S, admin_token, bundle_of
from web_support import http, wait_until

from farm.client import FarmClient
from farm.local import LocalFarm
from master.web.auth import COOKIE, CSRF_HEADER

pytestmark = pytest.mark.slow

LONG = {"res": "128", "spp": "512"}
TINY = {"res": "32", "spp": "4"}


@pytest.fixture(scope="module")
def farm(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LocalFarm]:
    with LocalFarm(tmp_path_factory.mktemp("farm") / "home", agents=2, threads=1) as farm:
        farm.wait_for_agents()
        yield farm


def quekaro(farm: LocalFarm, *args: str) -> subprocess.CompletedProcess:
    done = subprocess.run([sys.executable, "-m", "quekaro", *args, "--home", str(farm.home)], capture_output=True,
                          text=True, timeout=300)
    assert "Traceback" not in done.stderr, done.stderr
    return done


def done_attempts(client: FarmClient, job_id: str) -> dict[int, int]:
    """Each unit's attempts that ended done."""
    units = client.status(job_id)["units_total"]
    return {i: sum(a["outcome"] == "done" for a in client.unit(job_id, i)["attempts"]) for i in range(units)}


def cancelled_early(client: FarmClient) -> tuple[str, set[int]]:
    """A job of 16 units cancelled once a first unit is done: its id and the units done before the cancel."""
    job_id = client.submit(bundle_of(LONG), LONG, {"level": "off", "units": 16})
    wait_until(lambda: client.status(job_id)["units_done"], JOB_TIMEOUT_S, "a first tile")
    assert client.cancel(job_id) is True
    done = {i for i, n in done_attempts(client, job_id).items() if n}
    assert 0 < len(done) < 16, done
    return job_id, done


def test_quekaro_requeue_runs_a_cancelled_job_again_and_refuses_a_done_one(farm: LocalFarm) -> None:
    helped = quekaro(farm, "requeue", "--help")
    assert helped.returncode == 0 and "failed or cancelled" in helped.stdout and "seq-" in helped.stdout
    client = farm.client()
    job_id, before = cancelled_early(client)
    requeued = quekaro(farm, "requeue", job_id)
    assert (requeued.returncode, requeued.stdout) == (0, f"{job_id}: runs again (its done units kept)\n"), requeued
    assert client.wait(job_id, JOB_TIMEOUT_S)["status"] == "done"
    assert set(done_attempts(client, job_id).values()) == {1}  # every unit done once
    assert [len(client.unit(job_id, i)["attempts"]) for i in sorted(before)] == [1] * len(before)  # not awarded again
    again = quekaro(farm, "requeue", job_id)
    assert again.returncode == 2 and "only a failed or cancelled job is requeued: it is done" in again.stderr, again
    missing = quekaro(farm, "requeue", "nojob000000")
    assert missing.returncode == 2 and "no job 'nojob000000'" in missing.stderr, missing


def page_session(farm: LocalFarm) -> dict[str, str]:
    """A session of the page over plain HTTP: its cookie and CSRF token as headers."""
    form = urllib.parse.urlencode({"token": admin_token(farm)}).encode()
    status, headers, _ = http("POST", f"{farm.url}/ui/login", {"Content-Type": "application/x-www-form-urlencoded"},
                              form)
    assert status == 303, status
    cookie = headers["Set-Cookie"].split(";", 1)[0]
    assert cookie.startswith(f"{COOKIE}=")
    _, _, page = http("GET", f"{farm.url}/ui/", {"Cookie": cookie})
    csrf = page.decode().split('name="csrf-token" content="', 1)[1].split('"', 1)[0]
    return {"Cookie": cookie, CSRF_HEADER: csrf, "Content-Type": "application/json"}


def restart_master(farm: LocalFarm) -> None:
    master = farm.children[0]
    master.proc.kill()
    master.proc.wait()
    farm._spawn(master)  # the same command again, a child of the farm (it dies with it)
    wait_until(lambda: farm.client().jobs() is not None, 60, "the master back")


def test_a_drained_agent_stays_drained_through_a_master_restart(farm: LocalFarm) -> None:
    client = farm.client()
    jid = sorted(a["jid"] for a in client.agents())[0]
    body = json.dumps({"agent": jid, "drain": True}).encode()
    status, _, said = http("POST", f"{farm.url}/ui/api/agents/drain", page_session(farm), body)
    assert status == 200, said
    restart_master(farm)
    states = wait_until(lambda: (rows := {a["jid"]: a["state"] for a in farm.client().agents()}) and len(rows) == 2
                        and rows, 60, "both agents back")
    assert states[jid] == "draining", states
    job_id = client.submit(bundle_of(TINY), TINY, {"level": "off", "units": 4})
    assert client.wait(job_id, JOB_TIMEOUT_S)["status"] == "done"
    rendered_by = {a["agent"] for i in range(4) for a in client.unit(job_id, i)["attempts"]}
    assert rendered_by and jid not in rendered_by, rendered_by
    body = json.dumps({"agent": jid, "drain": False}).encode()
    assert http("POST", f"{farm.url}/ui/api/agents/drain", page_session(farm), body)[0] == 200
    assert {a["jid"]: a["state"] for a in client.agents()}[jid] != "draining"
